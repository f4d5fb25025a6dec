"""The reduced camera system with its gauge constraints, dense or sparse.

After the heights are eliminated the camera block A (n x n: 6 per image and
the refined intrinsics) couples two images only where they see the same
facades, so in a large block most of it is zero: a 1000-image block keeps
a few per cent. Its KKT system ``[[A, G^T], [G, 0]] [x; y] = [b; 0]`` (G the
gauge rows) is solved densely below :data:`SPARSE_MIN_UNKNOWNS` (LAPACK is
faster there, and small blocks keep their bit-exact results) and by a
sparse LU (SuperLU, COLAMD ordering) above, where the dense solve's n^3
made the adjustment grow with the cube of the number of images.

The covariance needs the top-left block Q of the KKT system's inverse.
Above the same size it comes from a Cholesky inverse of ``B = A + G^T G``
(positive definite where the gauge rows fix A's null space):
``Q = B^-1 - B^-1 G^T (G B^-1 G^T)^-1 G B^-1``, exact for any such B since
``G x = 0`` makes ``B x = A x``; half the flops of the KKT's LU inverse.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla_dense
import scipy.sparse as sp
import scipy.sparse.linalg as sla

__all__ = ["SPARSE_MIN_UNKNOWNS", "kkt_inverse", "kkt_solve"]

#: Camera-block size from which the sparse LU is used (measured on the
#: synthetic blocks of scripts/bench/scale.py: at 400 images, 2412 unknowns,
#: the sparse solve takes 0.12 s against the dense 0.26 s; at 200 images
#: both are about equal).
SPARSE_MIN_UNKNOWNS = 1500


def _kkt_dense(A: np.ndarray, G: np.ndarray) -> np.ndarray:
    n, ng = len(A), len(G)
    kkt = np.zeros((n + ng, n + ng))
    kkt[:n, :n] = A
    kkt[:n, n:] = G.T
    kkt[n:, :n] = G
    return kkt


def _kkt_sparse(A, G: np.ndarray) -> sp.csc_matrix:
    Gs = sp.csr_matrix(G)
    return sp.bmat([[sp.csr_matrix(A), Gs.T], [Gs, None]], format="csc")


def kkt_solve(A, G: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) x of ``[[A, G^T], [G, 0]] [x; y] = [b; 0]``.

    Parameters
    ----------
    A : (n, n) symmetric camera block (damped): a dense array, or a scipy
        sparse matrix (then always the sparse LU).
    G : (ng, n) gauge rows (ng may be 0: then ``A x = b``).
    b : (n,) right-hand side.

    Raises
    ------
    numpy.linalg.LinAlgError
        The system is singular.
    """
    n, ng = A.shape[0], len(G)
    rhs = np.concatenate([b, np.zeros(ng)])
    if n < SPARSE_MIN_UNKNOWNS and not sp.issparse(A):
        if not ng:
            return np.linalg.solve(A, b)
        return np.linalg.solve(_kkt_dense(A, G), rhs)[:n]
    K = _kkt_sparse(A, G)
    x = _symmetric_lu_solve(K, rhs)
    if x is not None:
        return x[:n]
    try:
        lu = sla.splu(K, permc_spec="COLAMD")
    except RuntimeError as exc:  # SuperLU: "Factor is exactly singular"
        raise np.linalg.LinAlgError(str(exc)) from exc
    return lu.solve(rhs)[:n]


def _symmetric_lu_solve(K: sp.csc_matrix, rhs: np.ndarray) -> np.ndarray | None:
    """``K^-1 rhs`` by SuperLU in symmetric mode (a minimum-degree ordering
    of K + K^T, pivots on the diagonal), or None where that fails.

    The damped camera block is positive definite, so its pivots need no
    search, and the symmetric ordering fills in ~25 % less than COLAMD's
    (6012 unknowns: 0.19 s against 0.30 s). The gauge rows' zero diagonal
    is not positive, so a pivot can vanish or grow: the residual is checked
    and the caller falls back to the pivoting LU.
    """
    try:
        lu = sla.splu(
            K,
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
    except RuntimeError:
        return None
    x = lu.solve(rhs)
    err = np.linalg.norm(K @ x - rhs)
    if not np.isfinite(err) or err > 1e-10 * max(np.linalg.norm(rhs), 1e-300):
        return None
    return x


def kkt_inverse(A: np.ndarray, G: np.ndarray) -> np.ndarray:
    """(n, n) top-left block of ``[[A, G^T], [G, 0]]^-1`` (A (n, n)
    symmetric positive semi-definite, G (ng, n) gauge rows).

    Raises
    ------
    numpy.linalg.LinAlgError
        The system is singular.
    """
    n, ng = len(A), len(G)
    if n < SPARSE_MIN_UNKNOWNS:
        return np.linalg.inv(_kkt_dense(A, G))[:n, :n]
    B = A + G.T @ G
    c, info = sla_dense.lapack.dpotrf(B, lower=True, clean=True, overwrite_a=True)
    if info != 0:
        raise np.linalg.LinAlgError(f"not positive definite (dpotrf info {info})")
    B_inv, info = sla_dense.lapack.dpotri(c, lower=True, overwrite_c=True)
    if info != 0:
        raise np.linalg.LinAlgError(f"singular (dpotri info {info})")
    B_inv = np.tril(B_inv) + np.tril(B_inv, -1).T  # dpotri fills one triangle
    if not ng:
        return B_inv
    BG = B_inv @ G.T  # (n, ng)
    return B_inv - BG @ np.linalg.solve(G @ BG, BG.T)
