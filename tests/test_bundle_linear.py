"""The reduced camera system's dense and sparse routes agree (issue 29)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from obliq_colmap.bundle import linear


def _gauged_system(n: int, seed: int = 0):
    """A sparse symmetric PSD (n, n) A with a one-dimensional null space v
    (like the free vertical datum), one gauge row g with g v != 0, and b."""
    rng = np.random.default_rng(seed)
    J = rng.normal(size=(3 * n, n)) * (rng.random((3 * n, n)) < 0.05)
    v = np.ones(n) / np.sqrt(n)
    J -= np.outer(J @ v, v)  # J v = 0
    A = J.T @ J
    g = np.zeros((1, n))
    g[0, : n // 3] = 1.0 / (n // 3)
    return A, g, rng.normal(size=n)


@pytest.mark.parametrize("with_gauge", [True, False])
def test_sparse_solve_and_inverse_equal_the_dense_ones(monkeypatch, with_gauge):
    A, g, b = _gauged_system(60)
    if not with_gauge:
        A, g = A + np.eye(60), g[:0]
    x_dense = linear.kkt_solve(A, g, b)
    q_dense = linear.kkt_inverse(A, g)
    monkeypatch.setattr(linear, "SPARSE_MIN_UNKNOWNS", 1)
    x_sparse = linear.kkt_solve(A, g, b)
    q_chol = linear.kkt_inverse(A, g)
    # Exact up to rounding on a well-conditioned system (cond ~1e3).
    scale = np.abs(x_dense).max()
    np.testing.assert_allclose(x_sparse, x_dense, atol=1e-9 * scale)
    np.testing.assert_allclose(q_chol, q_dense, atol=1e-9 * np.abs(q_dense).max())
    if with_gauge:
        assert abs((g @ x_sparse).item()) < 1e-9 * scale  # the gauge holds
        # A x - b = -g^T y: in the span of the gauge row.
        r = A @ x_sparse - b
        r_off = r - g[0] * (g[0] @ r) / (g[0] @ g[0])
        np.testing.assert_allclose(r_off, 0.0, atol=1e-9 * np.abs(b).max())
        q_max = np.abs(q_dense).max()
        np.testing.assert_allclose(q_chol @ g.T, 0.0, atol=1e-9 * q_max)


def test_a_singular_system_raises(monkeypatch):
    A, g, b = _gauged_system(40)
    A[:, -1] = A[-1, :] = 0.0  # an unknown without any observation
    monkeypatch.setattr(linear, "SPARSE_MIN_UNKNOWNS", 1)
    with pytest.raises(np.linalg.LinAlgError):
        linear.kkt_solve(A, g, b)
    with pytest.raises(np.linalg.LinAlgError):
        linear.kkt_inverse(A, g)


def test_tiny_diagonal_pivots_fall_back_to_the_pivoting_lu():
    """The sparse route factors without pivot search first (the damped camera
    block is positive definite); where the diagonal pivots are tiny (here
    1e-17 beside 1) that factorisation is refused by its residual and the
    pivoting LU solves the system."""
    M = np.array([[1e-17, 1.0, 0.0], [1.0, 1e-17, 1.0], [0.0, 1.0, 1.0]])
    b = np.ones(3)
    A = sp.csr_matrix(M)
    assert linear._symmetric_lu_solve(sp.csc_matrix(M), b) is None
    x = linear.kkt_solve(A, np.zeros((0, 3)), b)
    np.testing.assert_allclose(M @ x, b, atol=1e-12)
