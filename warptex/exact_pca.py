"""Principal component analysis that gives the same bits on every CPU, for the quantized
PCA bases of the candidates (Dong 2008, section 4; appearance space after Lefebvre and
Hoppe 2006).

LAPACK and a BLAS sum in the order of the kernels a CPU selects, and a last-bit difference
turns the eigenvectors of nearly equal eigenvalues (isotropic or gray exemplars have many)
into another quantized basis, hence other candidates and another texture. Here every sum
is either exact (integers below 2^53, any order) or taken in index order, and eigenvectors
come from elementwise IEEE operations only (BENCHMARKS.md, "Candidates identical on every
CPU").
"""

from __future__ import annotations

import numpy as np

# Jacobi rotations find every eigenvector at a cost of D^3 per sweep: up to 4 channels' 5 x 5
# neighbourhoods (RGB and a feature channel, or RGBA). Wider ones get only their leading
# axes, by at most _ITERATIONS rounds of orthogonal iteration.
JACOBI_MAX_DIMS = 100
_ITERATIONS = 300
_SETTLED = 1e-5  # largest residual of a leading Ritz pair, relative to the top eigenvalue
_CHECK_EVERY = 5
_MAX_SWEEPS = 60  # a bound only: the convergence test in symmetric_eigen ends the sweeps


def covariance(vec: np.ndarray) -> np.ndarray:
    """Covariance of integer neighbourhood vectors, the same bits on every machine (see the
    module's documentation): products of features below 2^10 summed over fewer than 2^33
    pixels are integers below 2^53, exact in float64 in any order; the centring is done in
    Python integers.
    """
    rows = len(vec)
    values = vec.astype(np.float64)
    scatter = (values.T @ values).astype(np.int64).astype(object)
    sums = vec.sum(axis=0).astype(object)
    centred = scatter * rows - np.outer(sums, sums)  # rows * (rows - 1) * covariance
    return centred.astype(np.float64) / float(rows * max(rows - 1, 1))


def principal_axes(cov: np.ndarray, most: int) -> tuple[np.ndarray, np.ndarray, float]:
    """At least the ``most`` leading variances (descending, clipped at 0) and axes
    (columns) of a covariance, and the total variance, the same bits on every machine."""
    if len(cov) > JACOBI_MAX_DIMS:
        values, vectors = _leading_eigen(cov, most)
        values = np.clip(values, 0, None)
        return values, vectors, max(float(np.cumsum(np.diagonal(cov))[-1]), 0.0)
    values, vectors = symmetric_eigen(cov)
    order = np.argsort(-values, kind="stable")
    values = np.clip(values[order], 0, None)
    return values, vectors[:, order], float(np.cumsum(values)[-1])


def _leading_eigen(matrix: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` largest eigenvalues (descending) and their eigenvectors of a symmetric
    positive semi-definite matrix, by orthogonal iteration on twice as many vectors and a
    Rayleigh-Ritz step (Golub and Van Loan, 8.2.4), with sums that no BLAS can reorder.

    The iterated product runs on integers (the matrix and the vectors scaled and rounded)
    small enough that their products and sums over ``n`` terms stay below 2^53: exact in
    float64 in any order, so BLAS may compute it. The rounding perturbs the axes by about
    2^-21, far below the basis's 127 steps.
    """
    n = len(matrix)
    unit = float(1 << ((53 - n.bit_length()) // 2))
    scale = unit / max(float(np.abs(matrix).max()), 1e-300)
    fixed = np.rint(matrix * scale)
    width = min(n, 2 * count)
    # Integers: a float generator's logarithms may round otherwise on other machines.
    start = np.random.default_rng(0).integers(-8, 9, (n, width)).astype(np.float64)
    basis = _orthonormal(start)
    for step in range(1, _ITERATIONS + 1):
        image = fixed @ np.rint(basis * unit)
        if step % _CHECK_EVERY == 0 or step == _ITERATIONS:
            # Converged when the leading Ritz pairs are eigenpairs; vectors within a cluster
            # of nearly equal eigenvalues keep turning long after their span has settled.
            values, vectors, residual = _ritz(basis, image / (scale * unit), count)
            if residual <= _SETTLED * max(float(np.abs(values).max()), 1e-300):
                break
        basis = _orthonormal(image)
    return values, vectors


def _ritz(basis: np.ndarray, image: np.ndarray,
          count: int) -> tuple[np.ndarray, np.ndarray, float]:
    """The ``count`` leading Ritz pairs of a matrix on an orthonormal ``basis`` whose
    ``image`` under it is given, and their largest residual."""
    small = _product(basis.T, image)
    values, axes = symmetric_eigen((small + small.T) / 2)
    order = np.argsort(-values, kind="stable")[:count]
    values, axes = values[order], axes[:, order]
    vectors = _product(basis, axes)
    residual = _product(image, axes) - vectors * values
    return values, vectors, float(np.abs(residual).max())


def _product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` with each sum taken in index order (a cumulative sum), where a BLAS would
    sum in its CPU kernel's order."""
    out = np.empty((a.shape[0], b.shape[1]))
    for j in range(b.shape[1]):
        out[:, j] = np.cumsum(a * b[:, j], axis=1)[:, -1]
    return out


def _orthonormal(columns: np.ndarray) -> np.ndarray:
    """Modified Gram-Schmidt on the columns, sums in index order; a column left without a
    direction of its own (a matrix of lower rank) becomes zero."""
    out = np.zeros_like(columns)
    for j in range(columns.shape[1]):
        v = columns[:, j].copy()
        for i in range(j):
            v -= _dot(out[:, i], v) * out[:, i]
        norm = np.sqrt(_dot(v, v))
        if norm > 1e-12 * max(np.sqrt(_dot(columns[:, j], columns[:, j])), 1e-300):
            out[:, j] = v / norm
    return out


def _dot(x: np.ndarray, y: np.ndarray) -> float:
    """``x . y`` summed in index order, as :func:`_product` sums."""
    return np.cumsum(x * y)[-1]


def symmetric_eigen(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues and eigenvectors (columns) of a symmetric matrix by cyclic Jacobi
    rotations, in elementwise IEEE operations only, so the result is a function of the
    matrix's bits alone; LAPACK's depends on the BLAS kernels a CPU selects.

    Each round rotates n/2 disjoint index pairs at once (round-robin ordering), which keeps
    the work in whole-array numpy operations.
    """
    n = len(matrix)
    m = n + n % 2  # an even size: the padding index pairs with each index once per sweep
    # The matrix above its eigenvectors: a rotation turns the columns of both.
    stacked = np.zeros((2 * m, m))
    stacked[:n, :n] = matrix
    stacked[m:] = np.eye(m)
    a = stacked[:m]
    players = np.arange(m)
    rounds = []
    for _ in range(m - 1):
        rounds.append((players[: m // 2], players[m // 2 :][::-1]))
        players = np.concatenate([players[:1], players[-1:], players[1:-1]])
    for _ in range(_MAX_SWEEPS):
        diag = np.abs(np.diagonal(a)).max()
        off = np.abs(a - np.diag(np.diagonal(a))).max()
        if off <= 1e-13 * diag:  # eigenvectors far finer than the basis's 127 steps
            break
        for p, q in rounds:
            _rotate(stacked, m, p, q)
    return np.diagonal(a)[:n].copy(), stacked[m:m + n, :n].copy()


def _rotate(stacked: np.ndarray, m: int, p: np.ndarray, q: np.ndarray) -> None:
    """One Jacobi rotation per pair (p, q), zeroing a[p, q] of the matrix ``a``, the first
    ``m`` rows of ``stacked`` (Numerical Recipes, 11.1)."""
    a = stacked[:m]
    apq = a[p, q]
    rotating = apq != 0.0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        theta = np.where(rotating, (a[q, q] - a[p, p]) / (2.0 * apq), 0.0)
        t = np.where(theta >= 0, 1.0, -1.0) / (np.abs(theta) + np.sqrt(theta * theta + 1.0))
    t = np.where(rotating & np.isfinite(theta), t, 0.0)
    c = 1.0 / np.sqrt(t * t + 1.0)
    s = t * c
    x, y = stacked[:, p], stacked[:, q]
    stacked[:, p], stacked[:, q] = x * c - y * s, x * s + y * c
    x, y, c, s = a[p], a[q], c[:, None], s[:, None]
    a[p], a[q] = x * c - y * s, x * s + y * c
