"""File formats: exact parsing, tolerated variants, and one clear error per kind of bad input."""

import re

import numpy as np
import pytest

from meshseg.data.io import atomic_write, read_mesh, read_obj, read_off, read_psb_labels, read_seg, write_off
from meshseg.data.mesh import MeshDataError

TETRA_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
TETRA_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
TETRA_OFF = "OFF\n4 4 6\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n"


def write(tmp_path, name, text):
    p = tmp_path / name
    p.write_bytes(text.encode() if isinstance(text, str) else text)
    return p


def test_read_off_plain(tmp_path):
    v, f = read_off(write(tmp_path, "t.off", TETRA_OFF))
    assert v.dtype == np.float64 and f.dtype == np.int64
    np.testing.assert_array_equal(v, TETRA_V)
    np.testing.assert_array_equal(f, TETRA_F)


@pytest.mark.parametrize(
    "text",
    [
        "# made by hand\nOFF\n# counts next\n4 4 0\n\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n",
        "OFF 4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n",
        TETRA_OFF.replace("\n", "\r\n"),
        # COFF: colours after each vertex and face; a comment inside the body
        "COFF\n4 4 0\n0 0 0 255 0 0 255\n1 0 0 255 0 0 255\n0 1 0 9 9 9 9\n# mid\n0 0 1 1 1 1 1\n"
        "3 0 2 1 0.5 0.5 0.5\n3 0 1 3 1 1 1\n3 0 3 2 0 0 0\n3 1 2 3 0 0 0\n",
        "4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n",  # header keyword omitted
    ],
)
def test_read_off_variants(tmp_path, text):
    v, f = read_off(write(tmp_path, "t.off", text))
    np.testing.assert_array_equal(v, TETRA_V)
    np.testing.assert_array_equal(f, TETRA_F)


def test_trailing_junk_ignored(tmp_path):
    junk = TETRA_OFF + '<!DOCTYPE FilterScript>\n<FilterScript>\n  <Param name="x" value="1 2 3"/>\n</FilterScript>\n'
    v, f = read_off(write(tmp_path, "junk.off", junk))
    np.testing.assert_array_equal(v, TETRA_V)
    np.testing.assert_array_equal(f, TETRA_F)


def test_psb_file_with_meshlab_junk_equals_cleaned_copy(tmp_path, psb):
    """A real L-PSB file with a MeshLab XML tail reads exactly like its records alone."""
    raw = (psb.root / "Armadillo/281.off").read_bytes()
    lines = raw.split(b"\n")
    nv, nf = map(int, lines[1].split()[:2])
    assert len([x for x in lines[2 + nv + nf :] if x.strip()]) > 0, "fixture must have trailing junk"
    assert b"<filter name=" in b"\n".join(lines[2 + nv + nf :])
    clean = b"\n".join(lines[: 2 + nv + nf]) + b"\n"
    v1, f1 = read_off(write(tmp_path, "junk.off", raw))
    v2, f2 = read_off(write(tmp_path, "clean.off", clean))
    assert v1.shape == (nv, 3) and f1.shape == (nf, 3)
    np.testing.assert_array_equal(v1, v2)
    np.testing.assert_array_equal(f1, f2)


def test_write_off_round_trips_exactly(tmp_path):
    rng = np.random.default_rng(0)
    v = rng.normal(size=(50, 3)) * 1e3
    f = rng.integers(0, 50, size=(80, 3))
    write_off(tmp_path / "r.off", v, f)
    v2, f2 = read_off(tmp_path / "r.off")
    np.testing.assert_array_equal(v, v2)
    np.testing.assert_array_equal(f, f2)
    assert not list(tmp_path.glob(".*tmp")), "atomic write leaves no temporary file"


def test_a_label_with_no_faces_is_a_blank_line(tmp_path):
    # Kalogerakis 2010's released .lab files write a label that no face has as its name and a blank line
    p = write(tmp_path, "61.lab", "wing\n1 3\nrudder\n \nbody\n2 4\n")
    labels, names = read_psb_labels(p, 4)
    assert names == ("wing", "rudder", "body")
    np.testing.assert_array_equal(labels, [0, 2, 0, 2])
    # blank lines between blocks, or between a name and its indices, are not labels
    labels, names = read_psb_labels(write(tmp_path, "2.lab", "\nwing\n\n1 3\n\nbody\n2 4\n\n"), 4)
    assert names == ("wing", "body")
    np.testing.assert_array_equal(labels, [0, 1, 0, 1])


BAD_OFF = [
    ("", "empty file"),
    ("OFF\n", "truncated"),
    ("OFF\n0 0 0\n", "empty mesh"),
    (
        "OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n",
        "truncated: header declares 4 vertices and 4 faces, file holds 6 records",
    ),
    (TETRA_OFF.replace("3 1 2 3", "4 1 2 3 0"), "face 3 has 4 vertices; only triangle"),
    (TETRA_OFF.replace("0 1 0\n", "0 one 0\n"), "vertex record 2 is not 3 numbers"),
    (TETRA_OFF.replace("3 0 1 3", "3 0 1.5 3"), "face record 1 is not integers"),
    ("ply\nformat ascii 1.0\n", "not an OFF file"),
    ("4OFF\n4 4 0\n", "unsupported OFF variant '4OFF'"),
]
BAD_LABELS = [
    ("", "empty file"),
    ("wing\n1 2 3\nbody\n", "truncated"),
    ("wing\n1 2\nbody\n2 3 4\n", "face 2 is labelled twice ('body' and label 'wing')"),
    ("wing\n1 2\nbody\n3\n", "1 of 4 faces have no label (first: face 4)"),
    ("wing\n1 2 5\nbody\n3 4\n", "label 'wing' lists face 5, outside 1..4"),
    ("wing\n1 2 x\nbody\n3 4\n", "face indices of label 'wing' are not integers"),
]


@pytest.mark.parametrize(
    "name, text, problem",
    [("bad.off", t, p) for t, p in BAD_OFF] + [("1_labels.txt", t, p) for t, p in BAD_LABELS],
)
def test_a_bad_file_raises_one_clear_error_naming_it(tmp_path, name, text, problem):
    p = write(tmp_path, name, text)
    read = read_off if name.endswith(".off") else lambda path: read_psb_labels(path, 4)
    with pytest.raises(MeshDataError, match=re.escape(problem)) as e:
        read(p)
    assert str(e.value).startswith(str(p))


def test_read_mesh_off_obj_and_errors(tmp_path):
    mesh = read_mesh(write(tmp_path, "tet.off", TETRA_OFF))
    assert (mesh.id, mesh.source) == ("tet", str(tmp_path / "tet.off"))
    np.testing.assert_array_equal(mesh.faces, TETRA_F)
    obj = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\ng a\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
    np.testing.assert_array_equal(read_mesh(write(tmp_path, "tet.OBJ", obj)).vertices, TETRA_V)
    with pytest.raises(MeshDataError, match=re.escape("unknown mesh format '.ply': use .off or .obj")):
        read_mesh(write(tmp_path, "tet.ply", TETRA_OFF))
    with pytest.raises(MeshDataError, match="none.off: cannot read"):
        read_mesh(tmp_path / "none.off")


def test_atomic_write_leaves_nothing_behind_when_the_writer_fails(tmp_path):
    atomic_write(tmp_path / "a.txt", lambda fh: fh.write("old"), "w")

    def fail(fh):
        fh.write(b"half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_write(tmp_path / "a.txt", fail)
    assert (tmp_path / "a.txt").read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_read_obj_groups_become_labels(tmp_path):
    text = (
        "# cube corner\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nvt 0 0\nvn 0 0 1\n"
        "f 1 3 2\ng wing\nf 1/1/1 2/1/1 4/1/1\nf -4//1 -1//1 -2//1\ng body\nf 2 3 4\n"
    )
    v, f, labels, names = read_obj(write(tmp_path, "m.obj", text))
    np.testing.assert_array_equal(v, TETRA_V)
    np.testing.assert_array_equal(f, TETRA_F)
    assert names == ("default", "wing", "body")
    np.testing.assert_array_equal(labels, [0, 1, 1, 2])


def test_read_obj_rejects_quads(tmp_path):
    p = write(tmp_path, "q.obj", "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n")
    with pytest.raises(MeshDataError, match="line 5: face has 4 vertices"):
        read_obj(p)


def test_read_psb_labels(tmp_path):
    p = write(tmp_path, "1_labels.txt", "wing\r\n1 3\r\nbody\r\n2 4 \r\n")
    labels, names = read_psb_labels(p, 4)
    assert names == ("wing", "body")
    np.testing.assert_array_equal(labels, [0, 1, 0, 1])


def test_read_seg(tmp_path):
    np.testing.assert_array_equal(read_seg(write(tmp_path, "a.seg", "2\n2\n3\n1\n"), 4), [2, 2, 3, 1])


@pytest.mark.parametrize(
    "text, problem",
    [
        ("", "empty file"),
        ("1\n2\n3\n", "3 labels for a mesh of 4 faces"),
        ("1\n2\nx\n3\n", "label 3 is not an integer"),
        ("1\n-2\n1\n3\n", "negative label -2 on face 2"),
    ],
)
def test_bad_seg(tmp_path, text, problem):
    p = write(tmp_path, "a.seg", text)
    with pytest.raises(MeshDataError, match=re.escape(problem)):
        read_seg(p, 4)
