"""The labelled triangle mesh every later stage consumes, and its validation."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from meshseg.errors import MeshDataError

__all__ = ["Mesh", "MeshDataError", "face_areas"]


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area of each triangle (F,)."""
    v0, v1, v2 = (vertices[faces[:, i]] for i in range(3))
    return 0.5 * np.linalg.norm(np.cross(v1 - v0, v2 - v0), axis=1)


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh with optional per-face labels.

    `labels[f]` indexes `label_names`, the vocabulary of the mesh's category (a mesh may use only
    part of it). `source` names where the data came from, for error messages.
    """

    vertices: np.ndarray
    faces: np.ndarray
    labels: np.ndarray | None = None
    label_names: tuple[str, ...] = ()
    id: str = ""
    category: str = ""
    source: str = field(default="<memory>", repr=False)

    def __post_init__(self) -> None:
        v = np.ascontiguousarray(self.vertices, dtype=np.float64)
        f = np.asarray(self.faces)
        src = self.source
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
            raise MeshDataError(src, f"vertices must be a non-empty N x 3 array, got shape {v.shape}")
        if f.ndim != 2 or len(f) == 0:
            raise MeshDataError(src, f"faces must be a non-empty F x 3 array, got shape {f.shape}")
        if f.shape[1] != 3:
            raise MeshDataError(src, f"only triangle faces are supported, got {f.shape[1]} vertices per face")
        if not np.issubdtype(f.dtype, np.integer):
            raise MeshDataError(src, f"face indices must be integers, got dtype {f.dtype}")
        f = np.ascontiguousarray(f, dtype=np.int64)
        bad = ~np.isfinite(v).all(axis=1)
        if bad.any():
            raise MeshDataError(
                src, f"{bad.sum()} vertices have NaN/inf coordinates (first: vertex {np.flatnonzero(bad)[0]})"
            )
        out = (f < 0) | (f >= len(v))
        if out.any():
            row = np.flatnonzero(out.any(axis=1))[0]
            raise MeshDataError(
                src,
                f"face {row} has vertex index {f[row][out[row]][0]} outside 0..{len(v) - 1} "
                f"({out.any(axis=1).sum()} such faces)",
            )
        used = np.unique(f)
        if np.ptp(v[used], axis=0).max() == 0:  # every feature needs a size and a shape
            raise MeshDataError(src, f"all {len(used)} vertices the faces use coincide: the mesh has no extent")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f)
        object.__setattr__(self, "label_names", tuple(self.label_names))
        if self.labels is not None:
            lab = np.asarray(self.labels)
            if lab.shape != (len(f),):
                raise MeshDataError(src, f"{lab.size} labels for {len(f)} faces")
            if not np.issubdtype(lab.dtype, np.integer):
                raise MeshDataError(src, f"labels must be integers, got dtype {lab.dtype}")
            lab = np.ascontiguousarray(lab, dtype=np.int64)
            unknown = (lab < 0) | (lab >= len(self.label_names))
            if unknown.any():
                raise MeshDataError(
                    src,
                    f"unknown label id {lab[unknown][0]} on face {np.flatnonzero(unknown)[0]}: "
                    f"the vocabulary has {len(self.label_names)} labels {list(self.label_names)}",
                )
            object.__setattr__(self, "labels", lab)

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    @cached_property
    def face_areas(self) -> np.ndarray:
        return face_areas(self.vertices, self.faces)

    @cached_property
    def n_degenerate(self) -> int:
        """Faces of zero area (kept: they weigh nothing in the area-weighted metric)."""
        return int((self.face_areas == 0.0).sum())

    @cached_property
    def content_hash(self) -> str:
        """Hash of the geometry alone: caches keyed on it can never serve another mesh."""
        h = hashlib.sha256()
        h.update(np.asarray(self.vertices.shape, np.int64).tobytes())
        h.update(self.vertices.tobytes())
        h.update(self.faces.tobytes())
        return h.hexdigest()[:32]
