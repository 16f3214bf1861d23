"""Heat kernel signature (Sun, Ovsjanikov & Guibas 2009) and its scale-invariant version (Bronstein
& Kokkinos 2010), from the low end of the Laplace–Beltrami spectrum.

Eigenpairs solve L φ = λ M φ with `robust_laplacian.mesh_laplacian` (Sharp & Crane 2020): the
cotangent Laplacian of the intrinsic Delaunay triangulation of the mesh's tufted cover, with
lumped mass M. It is chosen over igl.cotmatrix because it stays a well-conditioned positive
semi-definite M-matrix on non-manifold edges, zero-area faces and needle triangles (cotangent
weights there are unbounded or negative); on a clean Delaunay-ish mesh the two agree.
Eigenvectors are M-orthonormal. A disconnected mesh has one zero eigenvalue per component; those
are set to exactly 0, and `n_eigen` counts the eigenpairs of a connected mesh, so (components − 1)
more are computed. `laplace_beltrami_eigenpairs` is a pure function; `hks` and `sihks` take the
eigenpairs from the mesh's shared `operators.MeshOperators` (argument `ops`), which computes them
once per mesh and `n_eigen` for both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import robust_laplacian
import scipy.linalg
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import LinearOperator, eigsh, splu
from threadpoolctl import threadpool_limits

from meshseg.errors import ConfigError
from meshseg.features.geometry import vertex_to_face
from meshseg.features.registry import register


def laplace_beltrami_eigenpairs(
    V: np.ndarray, F: np.ndarray, n_eigen: int = 100
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The smallest eigenpairs of L φ = λ M φ, ascending: (λ (k,), φ (n, k), faces (F, 3) re-indexed
    into the n referenced vertices, number of components). Not memoised: `MeshOperators.eigenpairs`
    is, per mesh."""
    V = np.ascontiguousarray(V, np.float64)
    F = np.ascontiguousarray(F, np.int64)
    return _eigenpairs(V, F, n_eigen)


def _eigenpairs(V: np.ndarray, F: np.ndarray, n_eigen: int):
    used, Fc = np.unique(F, return_inverse=True)  # unreferenced vertices would have zero mass
    Fc = Fc.reshape(F.shape)
    L, M = robust_laplacian.mesh_laplacian(V[used], Fc)
    L, n = L.tocsc(), L.shape[0]
    g = L.copy()
    g.setdiag(0)
    g.eliminate_zeros()
    n_comp = connected_components(g, directed=False)[0]
    k = min(n_eigen + n_comp - 1, n)
    m = M.diagonal()
    if n <= 2 * k + 1:  # too small for ARPACK's Krylov space: dense solver
        lam, phi = scipy.linalg.eigh(L.toarray(), np.diag(m), subset_by_index=[0, k - 1])
    else:
        # Shift-invert Lanczos on the standard form A = M^-1/2 L M^-1/2 (M is diagonal), with a
        # symmetric-ordering LU of L − σM: the k eigenvalues nearest a negative σ are the k smallest.
        # σ scales with the spectrum (so results are scale-equivariant) and keeps L − σM invertible.
        sigma = -1e-8 * np.median(L.diagonal() / m)
        lu = splu((L - sigma * sp.diags(m)).tocsc(), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
        r = np.sqrt(m)
        op = LinearOperator((n, n), matvec=lambda y: r * lu.solve(r * np.ravel(y)), dtype=np.float64)
        A = sp.diags(1 / r) @ L @ sp.diags(1 / r)
        v0 = np.random.default_rng(0).standard_normal(n)  # fixed start: deterministic results
        # ARPACK's BLAS calls are small: threads only add overhead, ruinous on a busy machine
        with threadpool_limits(limits=1, user_api="blas"):
            lam, psi = eigsh(A, k, sigma=sigma, which="LM", OPinv=op, v0=v0)
        phi = psi / r[:, None]
    order = np.argsort(lam)
    lam, phi = lam[order], phi[:, order]
    lam[:n_comp] = 0.0  # the constants per component: exact zeros, not rounding noise
    return np.maximum(lam, 0.0), phi, Fc, n_comp


def heat_kernel_signature(lam: np.ndarray, phi: np.ndarray, t: np.ndarray) -> np.ndarray:
    """HKS(x, t) = Σ_i exp(−λ_i t) φ_i(x)², (n, len(t))."""
    return (phi**2) @ np.exp(-np.outer(lam, t))


def _shared_eigenpairs(V: np.ndarray, F: np.ndarray, n_eigen: int, ops) -> tuple:
    """The eigenpairs from the mesh's shared operators, or computed here when called without them."""
    return laplace_beltrami_eigenpairs(V, F, n_eigen) if ops is None else ops.eigenpairs(n_eigen)


def hks_times(lam: np.ndarray, n_times: int) -> np.ndarray:
    """Sun et al.'s times: n_times log-spaced from 4 ln10 / λ_max to 4 ln10 / λ_1 (first non-zero)."""
    positive = lam[lam > 0]
    if len(positive) == 0:  # no non-zero eigenvalue at all (degenerate input): any positive range
        positive = np.ones(1)
    return np.geomspace(4 * np.log(10) / positive[-1], 4 * np.log(10) / positive[0], n_times)


@register("hks", 100, columns=[f"hks{i}" for i in range(100)], shared=True)
def hks(V: np.ndarray, F: np.ndarray, *, n_eigen: int = 100, ops=None) -> np.ndarray:
    """HKS at 100 times (Sun et al. 2009), one column per time, short to long.

    Column j is Σ_i exp(−λ_i t_j) φ_i(x)² over the `n_eigen` smallest eigenpairs (the constant
    mode included), t_j log-spaced from 4 ln10/λ_max to 4 ln10/λ_1. Small t: local curvature;
    large t: how far out on a limb x lies (the first eigenfunctions peak at extremities).
    No normalisation: values scale as 1/area (×1/9 when the mesh is scaled by 3) while the t range
    follows the spectrum. Per vertex, then per face the mean of its three vertices.
    """
    lam, phi, Fc, _ = _shared_eigenpairs(V, F, n_eigen, ops)
    h = heat_kernel_signature(lam, phi, hks_times(lam, 100))
    return vertex_to_face(h, Fc)


@dataclass(frozen=True)
class SIHKSSettings:
    """The `sihks` group's parameters: the eigenpairs and the log-time grid t_0 α^τ (see `sihks`)."""

    n_eigen: int = 100
    alpha: float = 2.0
    tau_step: float = 0.5
    tau_start: float = -24.0
    n_tau: int = 201


@register("sihks", 100, columns=[f"sihks{i}" for i in range(100)], shared=True, settings=SIHKSSettings)
def sihks(V: np.ndarray, F: np.ndarray, settings: SIHKSSettings | None = None, ops=None) -> np.ndarray:
    """Scale-invariant HKS (Bronstein & Kokkinos 2010): the first 100 |DFT| frequencies of
    d/dτ log h(α^τ), one column per frequency, 0 (the DC term) first.

    h is the HKS (all `n_eigen` eigenpairs) at t = t_0 α^τ for τ = tau_start + j·tau_step,
    j < n_tau. Differencing log h along τ removes the 1/scale² factor of h, and the DFT magnitude
    removes the shift in τ that a scaling causes. t_0 = 4 ln10/λ_max (HKS's first time) anchors
    the window: with the defaults it runs from 24 octaves below t_0, where the derivative is below
    1e-6 of its peak (about 3e-7 on L-PSB), to 76 octaves above, far past the end of the signal
    (it is exactly 0 beyond about 12 octaves above t_0 on L-PSB). As the whole signal lies inside
    the window, the magnitudes are those of Bronstein & Kokkinos' fixed, absolute τ grid, but
    exactly rather than approximately scale invariant and independent of the mesh's units.
    Half-octave steps over 100 octaves make the 100 kept frequencies span 0..1 cycle per octave
    in steps of 0.01; the magnitude falls from the DC term to about 1e-5 of it at the last
    (L-PSB), so every column carries signal; finer steps would put most columns above the band
    where the signal has content. Per vertex, then per face the mean of its three vertices.
    """
    s = settings or SIHKSSettings()
    if (s.n_tau - 1) // 2 + 1 < 100:
        raise ConfigError(f"sihks: n_tau={s.n_tau} gives fewer than 100 frequencies; use n_tau >= 199")
    lam, phi, Fc, _ = _shared_eigenpairs(V, F, s.n_eigen, ops)
    t0 = hks_times(lam, 2)[0]
    t = t0 * s.alpha ** (s.tau_start + s.tau_step * np.arange(s.n_tau))
    h = heat_kernel_signature(lam, phi, t)
    logh = np.log(np.maximum(h, np.finfo(np.float64).tiny))
    spectrum = np.abs(np.fft.rfft(np.diff(logh, axis=1), axis=1))[:, :100]
    return vertex_to_face(spectrum, Fc)
