"""Multi-scale features (paper §3.4): X^k(u) = mean of X over N^k(u), the faces at most k−1
steps from face u (X^1 = X). A step crosses a shared edge (`adjacency="edge"`) or a shared vertex
(`adjacency="vertex"`); the paper does not say which."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from meshseg.errors import ConfigError
from meshseg.features.geometry import face_adjacency


def step_matrix(F: np.ndarray, adjacency: str = "edge") -> sp.csr_matrix:
    """F x F 0/1 matrix: faces one step apart, plus each face itself."""
    nf = len(F)
    if adjacency == "edge":
        a = face_adjacency(F)
    elif adjacency == "vertex":
        inc = sp.csr_matrix((np.ones(3 * nf), (np.repeat(np.arange(nf), 3), F.ravel())), shape=(nf, F.max() + 1))
        a = (inc @ inc.T).tocsr()
    else:
        raise ConfigError(f"unknown ring adjacency {adjacency!r}; known: ['edge', 'vertex']")
    a = (a + sp.identity(nf, format="csr")).tocsr()
    a.data[:] = 1.0
    return a


def neighbourhoods(F: np.ndarray, scales: int, adjacency: str = "edge") -> list[sp.csr_matrix]:
    """[N^2, ..., N^scales] as F x F 0/1 matrices (row u: the faces at most k-1 steps from u). N^k grows by one
    step per scale (sparse products, no loop over faces)."""
    step = step_matrix(F, adjacency)
    out, reach = [], sp.identity(len(F), format="csr")
    for _ in range(1, scales):
        reach = reach @ step
        reach.data[:] = 1.0  # membership, not path counts
        out.append(reach)
    return out


def ring_means(X: np.ndarray, F: np.ndarray, scales: int, adjacency: str = "edge") -> list[np.ndarray]:
    """[X^1, ..., X^scales], each (F, d) float32: X averaged over each N^k (`neighbourhoods`)."""
    out = [np.asarray(X, np.float32)]
    for reach in neighbourhoods(F, scales, adjacency):
        counts = np.asarray(reach.sum(axis=1)).ravel()
        out.append(np.asarray((reach.astype(np.float32) @ out[0]) / counts[:, None].astype(np.float32), np.float32))
    return out
