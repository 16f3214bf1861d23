"""Mesh and label file formats: OFF, OBJ (groups as labels), L-PSB `_labels.txt`, COSEG `.seg`.

Readers return plain arrays; `Mesh` validates them. Every error is a `MeshDataError` naming the
file and the problem.
"""

from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO

import numpy as np

from meshseg.data.mesh import Mesh, MeshDataError
from meshseg.errors import ConfigError

_OFF_KEYWORD = re.compile(rb"^(ST)?C?N?OFF$")


def _records(lines: list[bytes], start: int, first_lineno: int):
    """Yield (line number, tokens) of non-blank, non-comment lines from `start` on."""
    for i in range(start, len(lines)):
        tokens = lines[i].split(b"#", 1)[0].split()
        if tokens:
            yield first_lineno + i, tokens


def _parse_off_header(lines: list[bytes], path: Path) -> tuple[int, int, int]:
    """Return (n_vertices, n_faces, index of the first body line)."""
    records = _records(lines, 0, 1)
    try:
        lineno, tokens = next(records)
    except StopIteration:
        raise MeshDataError(path, "empty file") from None
    keyword = tokens[0]
    if _OFF_KEYWORD.match(keyword):
        tokens = tokens[1:]
    elif keyword.endswith(b"OFF"):
        raise MeshDataError(path, f"unsupported OFF variant {keyword.decode(errors='replace')!r} on line {lineno}")
    elif not keyword.lstrip(b"+-").isdigit():
        raise MeshDataError(
            path, f"not an OFF file: line {lineno} starts with {keyword[:20].decode(errors='replace')!r}"
        )
    if tokens[:1] == [b"BINARY"]:
        raise MeshDataError(path, "binary OFF is not supported")
    if not tokens:  # counts on the next record
        try:
            lineno, tokens = next(records)
        except StopIteration:
            raise MeshDataError(path, "truncated: no vertex/face counts after the OFF header") from None
    try:
        nv, nf = int(tokens[0]), int(tokens[1])
    except (IndexError, ValueError):
        raise MeshDataError(
            path,
            f"line {lineno}: expected 'n_vertices n_faces n_edges', got {b' '.join(tokens).decode(errors='replace')!r}",
        ) from None
    if nv <= 0 or nf <= 0:
        raise MeshDataError(path, f"empty mesh: header declares {nv} vertices and {nf} faces")
    return nv, nf, lineno  # body starts on the line after `lineno` (1-based) = index lineno


def _shown(tokens: list[bytes]) -> str:
    """A bad record as it reads in the file, cut to 60 characters, for an error message."""
    return b" ".join(tokens)[:60].decode(errors="replace")


def read_off(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read an OFF triangle mesh: exactly the declared vertex and face records, ignoring anything
    after them (170 L-PSB files carry a MeshLab XML fragment there).

    Returns (vertices float64 (V, 3), faces int64 (F, 3)).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise MeshDataError(path, f"cannot read: {e.strerror}") from None
    lines = data.split(b"\n")
    nv, nf, body = _parse_off_header(lines, path)
    if 2 * (nv + nf) > len(data):  # every record takes 2 bytes at least: refuse before allocating for it
        raise MeshDataError(
            path,
            f"header declares {nv} vertices and {nf} faces, more than the file's "
            f"{len(data)} bytes can hold (truncated file or bad header?)",
        )
    # Fast path: one record per line, plain "x y z" and "3 i j k"; numpy parses each block in C.
    try:
        v = np.fromstring(b" ".join(lines[body : body + nv]), sep=" ")
        f = np.fromstring(b" ".join(lines[body + nv : body + nv + nf]), dtype=np.int64, sep=" ")
        if v.size == 3 * nv and f.size == 4 * nf:
            v, f = v.reshape(nv, 3), f.reshape(nf, 4)
            if (f[:, 0] == 3).all():
                return v, f[:, 1:]
    except ValueError:
        pass
    return _read_off_slow(lines, body, nv, nf, path)


def _read_off_slow(lines: list[bytes], body: int, nv: int, nf: int, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Record-by-record parse: tolerates comments, blank lines and extra per-record values
    (colours, normals), and says exactly which record is wrong."""
    records = _records(lines, body, 1)
    last = max((i + 1 for i, line in enumerate(lines) if line.strip()), default=0)

    def short(lineno: int, what: str) -> MeshDataError:
        if lineno == last:  # the file stops mid-record
            return MeshDataError(path, f"truncated: file ends inside {what} (line {lineno})")
        return MeshDataError(path, f"line {lineno}: {what} is incomplete")

    v = np.empty((nv, 3))
    f = np.empty((nf, 3), np.int64)
    count = 0
    try:
        for i in range(nv):
            lineno, tokens = next(records)
            count += 1
            if len(tokens) < 3:
                raise short(lineno, f"vertex record {i}")
            try:
                v[i] = [float(t) for t in tokens[:3]]
            except ValueError:
                raise MeshDataError(
                    path,
                    f"line {lineno}: vertex record {i} is not 3 numbers: {_shown(tokens)!r}",
                ) from None
        for i in range(nf):
            lineno, tokens = next(records)
            count += 1
            try:
                n = int(tokens[0])
                idx = [int(t) for t in tokens[1:4]]
            except ValueError:
                raise MeshDataError(
                    path,
                    f"line {lineno}: face record {i} is not integers: {_shown(tokens)!r}",
                ) from None
            if n != 3:
                raise MeshDataError(
                    path, f"line {lineno}: face {i} has {n} vertices; only triangle meshes are supported"
                )
            if len(idx) != 3:
                raise short(lineno, f"face record {i}")
            f[i] = idx
    except StopIteration:
        raise MeshDataError(
            path, f"truncated: header declares {nv} vertices and {nf} faces, file holds {count} records"
        ) from None
    return v, f


def write_off(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write an OFF file atomically; %.17g round-trips float64 exactly."""
    path = Path(path)
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    lines = [f"OFF\n{len(vertices)} {len(faces)} 0\n"]
    lines += [f"{x:.17g} {y:.17g} {z:.17g}\n" for x, y, z in vertices.tolist()]
    lines += [f"3 {a} {b} {c}\n" for a, b, c in faces.tolist()]
    atomic_write(path, lambda fh: fh.write("".join(lines)), "w")


def read_mesh(path: str | os.PathLike) -> Mesh:
    """An .off or .obj triangle mesh file as a `Mesh` (an .obj's groups are ignored), its id the file's stem."""
    p = Path(path)
    if p.suffix.lower() == ".off":
        v, f = read_off(p)
    elif p.suffix.lower() == ".obj":
        v, f, _, _ = read_obj(p)
    else:
        raise MeshDataError(p, f"unknown mesh format {p.suffix!r}: use .off or .obj")
    return Mesh(v, f, id=p.stem, source=str(p))


def atomic_write(path: str | os.PathLike, write: Callable[[IO], object], mode: str = "wb") -> None:
    """Write `path` through `write(file)` into a temporary file beside it (opened with `mode`), then rename
    it: a killed run never leaves a half-written file under the name."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, mode) as fh:
            write(fh)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _writable_folder(folder: Path, what: str) -> None:
    """`folder` (existing) takes new files: probed by making one, which a read-only file system or a
    permission refuses even to root."""
    try:
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".meshseg-probe.")
    except OSError as e:
        raise ConfigError(f"{what}: cannot write in {folder} ({e.strerror})") from None
    os.close(fd)
    os.unlink(probe)


def check_output_file(path, setting: str) -> Path:
    """An output file named on the command line, checked before any work: not a folder, its folder there and
    writable. `setting` names it in the one-line error (e.g. `out`)."""
    p = Path(path).expanduser()
    what = f"{setting}={path}"
    if p.is_dir():
        raise ConfigError(f"{what} is a folder; name the file to write")
    folder = p.parent
    if not folder.exists():
        raise ConfigError(f"{what}: its folder {folder} does not exist")
    if not folder.is_dir():
        raise ConfigError(f"{what}: {folder} is a file, not a folder")
    _writable_folder(folder, what)
    return p


def check_output_folder(path, setting: str) -> Path:
    """An output folder (made if missing), checked before any work: no file in its place or on its way, the
    nearest existing folder writable."""
    p = Path(path).expanduser()
    what = f"{setting}={path}"
    if p.exists() and not p.is_dir():
        raise ConfigError(f"{what} is a file; it must be a folder (or not exist yet)")
    there = p
    while not there.exists():
        there = there.parent
    if not there.is_dir():
        raise ConfigError(f"{what}: {there} is a file, not a folder")
    _writable_folder(there, what)
    return p


def read_obj(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[str, ...]]:
    """Read a triangle OBJ; `g` groups become per-face labels.

    Returns (vertices, faces, labels, group names in order of first use). Faces before any `g`
    line belong to group "default". Texture/normal indices (`v/vt/vn`) and negative (relative)
    indices are understood.
    """
    path = Path(path)
    try:
        text = path.read_text(errors="replace")
    except OSError as e:
        raise MeshDataError(path, f"cannot read: {e.strerror}") from None
    verts: list[list[float]] = []
    faces: list[list[int]] = []
    labels: list[int] = []
    groups: dict[str, int] = {}
    current = "default"
    for lineno, line in enumerate(text.splitlines(), 1):
        tokens = line.split("#", 1)[0].split()
        if not tokens:
            continue
        key = tokens[0]
        if key == "v":
            try:
                verts.append([float(t) for t in tokens[1:4]])
                if len(tokens) < 4:
                    raise ValueError
            except ValueError:
                raise MeshDataError(path, f"line {lineno}: vertex is not 3 numbers: {line.strip()[:60]!r}") from None
        elif key == "f":
            if len(tokens) != 4:
                raise MeshDataError(
                    path, f"line {lineno}: face has {len(tokens) - 1} vertices; only triangle meshes are supported"
                )
            try:
                idx = [int(t.split("/", 1)[0]) for t in tokens[1:]]
            except ValueError:
                raise MeshDataError(
                    path, f"line {lineno}: face indices are not integers: {line.strip()[:60]!r}"
                ) from None
            # OBJ is 1-based; negative indices count back from the latest vertex.
            faces.append([i - 1 if i > 0 else len(verts) + i for i in idx])
            labels.append(groups.setdefault(current, len(groups)))
        elif key == "g":
            current = " ".join(tokens[1:]) or "default"
    if not verts or not faces:
        raise MeshDataError(path, f"empty mesh: {len(verts)} vertices, {len(faces)} faces")
    return (np.asarray(verts, np.float64), np.asarray(faces, np.int64), np.asarray(labels, np.int64), tuple(groups))


_INTEGERS = re.compile(r"\s*-?\d+(\s+-?\d+)*\s*")


def _label_blocks(path: Path) -> list[tuple[int, str, str]]:
    """(line number of the indices, label name, indices text) of each block of an L-PSB labels file.

    A block is a name line and the line after it. A blank line after a name is a label with no faces
    (Kalogerakis 2010's released labellings have such blocks), unless face indices follow it on the
    next non-blank line; other blank lines are ignored."""
    try:
        raw = path.read_text(errors="replace").splitlines()
    except OSError as e:
        raise MeshDataError(path, f"cannot read: {e.strerror}") from None
    if not any(line.strip() for line in raw):
        raise MeshDataError(path, "empty file")
    blocks, i = [], 0
    while i < len(raw):
        if not raw[i].strip():
            i += 1
            continue
        name, j = raw[i].strip(), i + 1
        if j >= len(raw):
            raise MeshDataError(path, f"truncated: label {name!r} on line {i + 1} has no line of face indices")
        if not raw[j].strip():
            k = next((k for k in range(j, len(raw)) if raw[k].strip()), None)
            if k is not None and _INTEGERS.fullmatch(raw[k]):
                j = k
        blocks.append((j + 1, name, raw[j]))
        i = j + 1
    return blocks


def read_psb_labels(path: str | os.PathLike, n_faces: int) -> tuple[np.ndarray, tuple[str, ...]]:
    """Read an L-PSB `<id>_labels.txt`: pairs of lines, a label name then its 1-based face indices.

    Every face must be labelled exactly once. Returns (labels into `names`, names in file order;
    a name used by two blocks is one label).
    """
    path = Path(path)
    labels = np.full(n_faces, -1, np.int64)
    names: dict[str, int] = {}
    for lineno, name, text in _label_blocks(path):
        try:
            idx = np.array(text.split(), dtype=np.int64) - 1
        except ValueError:
            raise MeshDataError(path, f"line {lineno}: face indices of label {name!r} are not integers") from None
        bad = (idx < 0) | (idx >= n_faces)
        if bad.any():
            raise MeshDataError(
                path, f"line {lineno}: label {name!r} lists face {idx[bad][0] + 1}, outside 1..{n_faces}"
            )
        label = names.setdefault(name, len(names))
        uniq, counts = np.unique(idx, return_counts=True)
        twice = np.concatenate([uniq[counts > 1], idx[labels[idx] >= 0]])
        if twice.size:
            f = int(twice[0])
            other = f"label {list(names)[labels[f]]!r}" if labels[f] >= 0 else "the same label"
            raise MeshDataError(path, f"face {f + 1} is labelled twice ({name!r} and {other})")
        labels[idx] = label
    missing = np.flatnonzero(labels < 0)
    if missing.size:
        raise MeshDataError(path, f"{missing.size} of {n_faces} faces have no label (first: face {missing[0] + 1})")
    return labels, tuple(names)


def write_psb_labels(path: str | os.PathLike, labels: np.ndarray, names) -> None:
    """Write per-face labels (indices into `names`) as an L-PSB `_labels.txt`: for each label with faces,
    its name, then its 1-based face indices (what `read_psb_labels` reads back)."""
    labels = np.asarray(labels, np.int64)
    lines = []
    for i, name in enumerate(names):
        faces = np.flatnonzero(labels == i) + 1
        if faces.size:
            lines += [f"{name}\n", " ".join(map(str, faces.tolist())) + "\n"]
    atomic_write(path, lambda fh: fh.write("".join(lines)), "w")


def write_seg(path: str | os.PathLike, values: np.ndarray) -> None:
    """Write a COSEG `.seg`: one integer label per face, in face order."""
    text = "".join(f"{v}\n" for v in np.asarray(values, np.int64).tolist())
    atomic_write(path, lambda fh: fh.write(text), "w")


def read_psb_label_names(path: str | os.PathLike) -> tuple[str, ...]:
    """Label names of an L-PSB labels file, without parsing the indices (for vocabularies)."""
    return tuple(dict.fromkeys(name for _, name, _ in _label_blocks(Path(path))))


def read_seg(path: str | os.PathLike, n_faces: int | None = None) -> np.ndarray:
    """Read a COSEG `.seg`: one integer label per face, in face order."""
    path = Path(path)
    lines = _read_lines(path)
    for i, t in enumerate(lines):
        if not re.fullmatch(r"[+-]?\d{1,9}", t.strip()):  # at most 9 digits: no label needs more
            problem = "is not an integer" if not re.fullmatch(r"[+-]?\d+", t.strip()) else "is out of range"
            raise MeshDataError(path, f"label {i + 1} {problem}: {t.strip()[:40]!r}")
    seg = np.array([int(t) for t in lines], np.int64)
    if n_faces is not None and len(seg) != n_faces:
        raise MeshDataError(path, f"{len(seg)} labels for a mesh of {n_faces} faces")
    if (seg < 0).any():
        raise MeshDataError(path, f"negative label {seg[seg < 0][0]} on face {np.flatnonzero(seg < 0)[0] + 1}")
    return seg


def _read_lines(path: Path) -> list[str]:
    """Non-blank lines of a small text file; an empty file is an error."""
    try:
        text = path.read_text(errors="replace")
    except OSError as e:
        raise MeshDataError(path, f"cannot read: {e.strerror}") from None
    lines = [line for line in text.splitlines() if line.strip()]
    if not lines:
        raise MeshDataError(path, "empty file")
    return lines
