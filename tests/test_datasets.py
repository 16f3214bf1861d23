"""Datasets from folders and archives: real L-PSB and COSEG, tiny hand-made ones, atomic unpacking."""

import io
import re
import tarfile

import numpy as np
import pytest

import meshseg.data.archive as archive
from meshseg.data.__main__ import summarize
from meshseg.data.archive import resolve_root
from meshseg.data.datasets import PSB, Synthetic, sort_ids
from meshseg.data.mesh import MeshDataError

TETRA = "OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n"


def make_psb(root, meshes):
    """meshes: {(category, id): (off text, labels text)}"""
    for (cat, mid), (off, labels) in meshes.items():
        (root / cat).mkdir(parents=True, exist_ok=True)
        (root / cat / f"{mid}.off").write_text(off)
        (root / cat / f"{mid}_labels.txt").write_text(labels)
    return root


def test_psb_every_mesh_loads_with_one_label_per_face(psb):
    """All 380 L-PSB meshes: 20 per category, labels on every face, 7,768,858 faces in total."""
    assert len(psb.categories) == 19
    out = io.StringIO()
    assert summarize(psb, out) == (380, 7_768_858)
    rows = out.getvalue().splitlines()
    assert rows[-1] == "total: 380 meshes, 7768858 faces"
    for row in rows[1:-1]:
        assert row.split()[1] == "20", row
    # spot-check one mesh: every face labelled, labels drawn from the category vocabulary
    mesh = psb.load("Airplane", "61")
    assert mesh.n_faces == 10796 and mesh.labels.shape == (10796,)
    assert mesh.label_names == psb.label_names("Airplane")
    assert set(np.unique(mesh.labels)) <= set(range(len(mesh.label_names)))
    assert psb.mesh_ids("Airplane") == [str(i) for i in range(61, 81)]


def test_coseg_fragment(coseg):
    assert coseg.categories == ["chairs", "tele-aliens"]
    assert len(coseg.mesh_ids("chairs")) == 22 and len(coseg.mesh_ids("tele-aliens")) == 5
    mesh = coseg.load("chairs", "0")
    assert mesh.labels.shape == (mesh.n_faces,)
    # .seg values 1..3 become vocabulary indices 0..2, names keep the integers
    assert coseg.label_names("chairs") == ("1", "2", "3")
    raw = np.loadtxt(coseg._dirs["chairs"] / "gt" / "0.seg", dtype=int)
    np.testing.assert_array_equal(np.asarray(coseg.label_names("chairs"))[mesh.labels].astype(int), raw)


def test_psb_vocabulary_is_per_category_union(tmp_path):
    root = make_psb(
        tmp_path / "db",
        {
            ("Cup", "2"): (TETRA, "handle\n1\nbody\n2 3 4\n"),
            ("Cup", "10"): (TETRA, "body\n1 2 3 4\n"),
        },
    )
    ds = PSB(str(root), str(tmp_path / "cache"))
    assert ds.categories == ["Cup"] and ds.mesh_ids("Cup") == ["2", "10"]
    assert ds.label_names("Cup") == ("body", "handle")
    np.testing.assert_array_equal(ds.load("Cup", "2").labels, [1, 0, 0, 0])
    np.testing.assert_array_equal(ds.load("Cup", "10").labels, [0, 0, 0, 0])
    with pytest.raises(ValueError, match=re.escape("has no category 'Mug'; it has ['Cup']")):
        ds.mesh_ids("Mug")


@pytest.mark.parametrize(
    "off, labels, problem",
    [
        (TETRA.replace("3 1 2 3", "3 1 2 9"), "a\n1 2 3 4\n", "face 3 has vertex index 9 outside 0..3"),
        (TETRA.replace("0 1 0\n", "0 nan 0\n"), "a\n1 2 3 4\n", "NaN/inf"),
        (TETRA, "a\n1 2 3\n", "1 of 4 faces have no label"),
        (TETRA, "a\n1 2 3 4\nb\n4\n", "face 4 is labelled twice"),
        (TETRA[:40], "a\n1 2 3 4\n", "truncated"),
    ],
)
def test_bad_mesh_in_dataset_names_the_file(tmp_path, off, labels, problem):
    root = make_psb(tmp_path / "db", {("Cup", "1"): (off, labels)})
    ds = PSB(str(root), str(tmp_path / "cache"))
    with pytest.raises(MeshDataError, match=re.escape(problem)) as e:
        ds.load("Cup", "1")
    assert re.search(r"db/Cup/1(_labels\.txt|\.off): ", str(e.value))


def test_missing_labels_file(tmp_path):
    root = make_psb(tmp_path / "db", {("Cup", "1"): (TETRA, "a\n1 2 3 4\n")})
    (root / "Cup" / "2.off").write_text(TETRA)
    with pytest.raises(MeshDataError, match=r"Cup/2_labels.txt: labels file missing"):
        PSB(str(root), str(tmp_path / "cache")).load("Cup", "2")


def tar_of(folder, dest):
    with tarfile.open(dest, "w:gz") as t:
        t.add(folder, arcname="LabeledDB_new")
    return dest


def test_archive_unpacked_once_and_atomically(tmp_path, monkeypatch):
    root = make_psb(tmp_path / "db", {("Cup", "1"): (TETRA, "a\n1 2 3 4\n")})
    arc = tar_of(root, tmp_path / "db.tar.gz")
    cache = tmp_path / "cache"

    # A killed unpack (here: interrupted mid-extraction) leaves no folder that is later trusted.
    real_extract = tarfile.TarFile.extractall

    def dying_extract(self, path, *a, **kw):
        (tmp_path / "marker").write_text(str(path))
        real_extract(self, path, *a, **kw)
        raise KeyboardInterrupt

    monkeypatch.setattr(tarfile.TarFile, "extractall", dying_extract)
    with pytest.raises(KeyboardInterrupt):
        resolve_root(arc, cache)
    assert list(cache.iterdir()) == []
    monkeypatch.undo()

    folder = resolve_root(arc, cache)
    assert folder.parent == cache and folder.name.startswith("db-")
    ds = PSB(str(arc), str(cache))
    assert ds.root == folder / "LabeledDB_new" and ds.load("Cup", "1").n_faces == 4
    # second use: no extraction at all
    monkeypatch.setattr(tarfile.TarFile, "extractall", lambda *a, **k: pytest.fail("unpacked twice"))
    assert resolve_root(arc, cache) == folder
    assert len(ds.data_hash) == 16 and ds.data_hash == archive.file_sha256(arc)[:16]


def test_corrupt_archive_is_one_error_and_leaves_nothing(tmp_path):
    root = make_psb(tmp_path / "db", {("Cup", "1"): (TETRA, "a\n1 2 3 4\n")})
    arc = tar_of(root, tmp_path / "db.tar.gz")
    arc.write_bytes(arc.read_bytes()[:60])
    with pytest.raises(MeshDataError, match=r"db.tar.gz: cannot unpack archive"):
        resolve_root(arc, tmp_path / "cache")
    assert list((tmp_path / "cache").iterdir()) == []


def test_root_errors(tmp_path):
    with pytest.raises(MeshDataError, match="dataset.root does not exist"):
        resolve_root(tmp_path / "nope", tmp_path)
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(MeshDataError, match="neither a folder nor an archive"):
        resolve_root(tmp_path / "x.txt", tmp_path)
    (tmp_path / "empty").mkdir()
    with pytest.raises(MeshDataError, match="no L-PSB category folders"):
        PSB(str(tmp_path / "empty"), str(tmp_path))


def test_synthetic_dataset():
    ds = Synthetic(categories=["cup", "table"], meshes_per_category=3, seed=1)
    assert ds.categories == ["cup", "table"] and ds.mesh_ids("cup") == ["0", "1", "2"]
    meshes = list(ds.meshes("table"))
    assert len(meshes) == 3
    for m in meshes:
        assert m.labels.shape == (m.n_faces,) and 1500 <= m.n_faces <= 6000
        assert set(np.unique(m.labels)) == set(range(len(ds.label_names("table"))))
    assert ds.data_hash != Synthetic(categories=["cup", "table"], meshes_per_category=3, seed=2).data_hash
    with pytest.raises(ValueError, match="no categories \\['boat'\\]"):
        Synthetic(categories=["boat"])
    with pytest.raises(ValueError, match="no mesh '3'"):
        ds.load("cup", "3")


def test_sort_ids_numeric_first():
    assert sort_ids(["10", "2", "b", "1", "a"]) == ["1", "2", "10", "a", "b"]
