"""The camera block of the normal equations, dense or gathered sparse.

Below :data:`~.linear.SPARSE_MIN_UNKNOWNS` the block (6 per image and the
refined intrinsics) is a dense (n, n) array: LAPACK is faster there and the
small blocks keep their results bit for bit. Above it, a block couples two
images only where they see the same facades or tie points (a 1000-image
block keeps a few per cent of its n^2 entries), and forming, damping and
converting the dense array was most of each step; there every term is
gathered as COO triplets (:class:`SparseTerms`) and summed once into CSR.

The terms are added through :func:`add_block` and :func:`add_entries`, which
take either form, so each kind of row (map rows, observed poses, VPs, tie
points) writes its terms once for both.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = [
    "SparseTerms",
    "add_block",
    "add_entries",
    "diagonal",
    "empty",
    "finish",
    "to_dense",
]


class SparseTerms:
    """Terms of an (n, n) matrix gathered as COO triplets; indices >= n
    (the camera block's padding column) are dropped when summed."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.rows: list[np.ndarray] = []
        self.cols: list[np.ndarray] = []
        self.vals: list[np.ndarray] = []

    def add(self, rows, cols, vals) -> None:
        """Add ``vals`` at (``rows``, ``cols``), all three broadcast together."""
        r, c, v = np.broadcast_arrays(rows, cols, vals)
        self.rows.append(r.ravel())
        self.cols.append(c.ravel())
        self.vals.append(v.ravel())

    def tocsr(self) -> sp.csr_matrix:
        """The (n, n) sum of the terms (duplicates summed)."""
        if not self.rows:
            return sp.csr_matrix((self.n, self.n))
        r, c, v = (np.concatenate(a) for a in (self.rows, self.cols, self.vals))
        keep = (r < self.n) & (c < self.n)
        m = sp.coo_matrix((v[keep], (r[keep], c[keep])), (self.n, self.n))
        return m.tocsr()


CameraBlock = np.ndarray | SparseTerms


def empty(n: int, sparse: bool) -> CameraBlock:
    """An empty camera block of ``n`` unknowns plus the padding column:
    gathered terms (``sparse``) or a dense (n + 1, n + 1) array."""
    return SparseTerms(n) if sparse else np.zeros((n + 1, n + 1))


def add_block(H: CameraBlock, rows: np.ndarray, cols: np.ndarray, block) -> None:
    """``H[np.ix_(rows, cols)] += block`` for (a,) ``rows``, (b,) ``cols``
    (each without repeats) and (a, b) ``block``."""
    if isinstance(H, SparseTerms):
        H.add(np.asarray(rows)[:, None], np.asarray(cols)[None, :], block)
    else:
        H[np.ix_(rows, cols)] += block


def add_entries(H: CameraBlock, rows, cols, vals) -> None:
    """``H[rows, cols] += vals`` (broadcast; no (row, col) pair repeated)."""
    if isinstance(H, SparseTerms):
        H.add(rows, cols, vals)
    else:
        H[rows, cols] += vals


def finish(H: CameraBlock) -> np.ndarray | sp.csr_matrix:
    """The assembled block: the dense array as it is, the terms summed to CSR."""
    return H.tocsr() if isinstance(H, SparseTerms) else H


def diagonal(H: np.ndarray | sp.spmatrix) -> np.ndarray:
    """(n,) diagonal of an assembled block."""
    return H.diagonal() if sp.issparse(H) else np.diag(H)


def to_dense(H: np.ndarray | sp.spmatrix) -> np.ndarray:
    """The assembled block as a dense array (for its inverse)."""
    return H.toarray() if sp.issparse(H) else H
