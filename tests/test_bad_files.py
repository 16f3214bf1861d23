"""Bad files get one MeshDataError naming the file and the problem, and nothing half-written stays."""

import io
import os
import subprocess
import sys
import tarfile
import time

import numpy as np
import pytest

from meshseg.data.archive import remove_stale_partials, resolve_root
from meshseg.data.io import read_off, read_seg
from meshseg.errors import MeshDataError


def test_an_off_header_claiming_more_than_the_file_holds_is_refused_before_allocating(tmp_path):
    path = tmp_path / "huge.off"
    path.write_text("OFF\n3 2000000000 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    with pytest.raises(MeshDataError, match=r"huge\.off: header declares 3 vertices and 2000000000 faces, more than"):
        read_off(path)


@pytest.mark.parametrize(
    "label, problem", [("--1", "is not an integer"), ("1" * 23, "is out of range"), ("x", "is not an integer")]
)
def test_bad_seg_labels_name_the_file_and_line(tmp_path, label, problem):
    path = tmp_path / "3.seg"
    path.write_text(f"1\n2\n{label}\n")
    with pytest.raises(MeshDataError, match=rf"3\.seg: label 3 {problem}"):
        read_seg(path)
    path.write_text("1\n-2\n+3\n")
    with pytest.raises(MeshDataError, match="negative label -2"):
        read_seg(path)


def _archive(tmp_path, suffix):
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:" + suffix) as t:
        data = b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n" * 2000
        info = tarfile.TarInfo("db/a.off")
        info.size = len(data)
        t.addfile(info, io.BytesIO(data))
    return buf.getvalue()


@pytest.mark.parametrize("suffix", ["xz", "gz"])
def test_a_bit_flipped_archive_is_one_error_and_leaves_nothing(tmp_path, suffix):
    raw = bytearray(_archive(tmp_path, suffix))
    raw[20] ^= 0xFF  # inside the compressed stream
    path = tmp_path / f"db.tar.{suffix}"
    path.write_bytes(bytes(raw))
    cache = tmp_path / "cache"
    with pytest.raises(MeshDataError, match=rf"db\.tar\.{suffix}: cannot unpack archive \(corrupt or truncated\?\)"):
        resolve_root(path, cache)
    assert list(cache.iterdir()) == []


def test_stale_partial_unpacks_are_removed_and_live_ones_kept(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = tmp_path / f".db-abc.partial-{dead.stdout.strip()}-x1"
    live = tmp_path / f".db-abc.partial-{os.getpid()}-x2"
    old = tmp_path / ".db-abc.partial-zz"  # named before pids were recorded
    young = tmp_path / ".db-abc.partial-yy"
    for d in (stale, live, old, young):
        d.mkdir()
        (d / "big").write_bytes(b"0" * 1000)
    os.utime(old, (time.time() - 7 * 3600,) * 2)
    assert sorted(remove_stale_partials(tmp_path)) == sorted([stale, old])
    assert live.exists() and young.exists()
    # and an unpack cleans them on its own
    dead_again = tmp_path / f".db-abc.partial-{dead.stdout.strip()}-x3"
    dead_again.mkdir()
    path = tmp_path / "db.tar.gz"
    path.write_bytes(_archive(tmp_path, "gz"))
    root = resolve_root(path, tmp_path)
    assert (root / "db" / "a.off").is_file() and not dead_again.exists()
    assert np.isclose(read_off(root / "db" / "a.off")[0].sum(), 2.0)


def test_a_cache_dir_that_is_a_file_is_one_error(tmp_path):
    from meshseg.errors import ConfigError
    from meshseg.features.cache import FeatureCache

    (tmp_path / "cache").write_text("not a folder")
    with pytest.raises(ConfigError, match=r"paths.cache_dir=.*cache is a file; it must be a folder"):
        FeatureCache(tmp_path / "cache")


def test_feature_saving_survives_its_folder_vanishing(tmp_path, monkeypatch):
    """A user clearing the cache while features are saved: the folder is made again, the file written."""
    import shutil
    import tempfile

    from meshseg.features.cache import FeatureCache

    real = tempfile.mkstemp
    calls = []

    def vanishing(*args, **kwargs):
        calls.append(kwargs["dir"])
        if len(calls) == 1:
            shutil.rmtree(kwargs["dir"])  # gone between mkdir and the temporary file
        return real(*args, **kwargs)

    monkeypatch.setattr(tempfile, "mkstemp", vanishing)
    path = tmp_path / "features" / "gc" / "abc.npz"
    FeatureCache._save(path, np.ones((4, 1), np.float32))
    assert len(calls) == 2 and np.load(path)["x"].shape == (4, 1)
    assert [p.name for p in path.parent.iterdir()] == ["abc.npz"]  # no temporary file left


def test_group_counts_are_checked_before_any_work():
    from meshseg.errors import ConfigError
    from meshseg.features.registry import get_group

    for value in (0, -3, 2.5, "many"):
        with pytest.raises(ConfigError, match=rf"features.params.agd.n_samples={value} is not allowed"):
            get_group("agd").params({"n_samples": value})
    assert get_group("agd").params({"n_samples": 64}) == {"n_samples": 64}


def test_features_out_that_is_a_folder_is_refused_before_computing(tmp_path):
    from conftest import REPO

    mesh = tmp_path / "m.off"
    mesh.write_text("OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n")
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "meshseg.features",
            f"mesh={mesh}",
            f"out={tmp_path}",
            f"paths.cache_dir={tmp_path}/cache",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 1 and r.stderr.strip() == f"error: out={tmp_path} is a folder; name the .npy file to write"
    assert not (tmp_path / "cache").exists()  # nothing was computed


def test_a_mesh_of_one_point_is_refused_naming_its_file(tmp_path):
    from meshseg.data.mesh import Mesh

    V = np.ones((4, 3))
    with pytest.raises(MeshDataError, match=r"flat\.off: all 4 vertices the faces use coincide"):
        Mesh(V, np.array([[0, 1, 2], [0, 2, 3]]), source="flat.off")


def test_a_coseg_set_without_shapes_is_named(tmp_path):
    from meshseg.data.datasets import COSEG

    for name in ("chairs", "empty"):
        (tmp_path / name / "shapes").mkdir(parents=True)
        (tmp_path / name / "gt").mkdir()
    (tmp_path / "chairs" / "shapes" / "1.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    ds = COSEG(str(tmp_path), str(tmp_path / "cache"))
    assert ds.mesh_ids("chairs") == ["1"]
    with pytest.raises(MeshDataError, match=r"empty/shapes: COSEG set 'empty' has no shapes"):
        ds.mesh_ids("empty")
