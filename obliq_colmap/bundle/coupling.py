"""Layout of the height-camera coupling E and its products (for the Schur step).

Every residual touches at most one height, so the height block of the
normal equations is diagonal and E (heights x camera columns) is sparse with
one (L,) block per residual row. :class:`Coupling` keeps E's pattern and
forms ``E^T D E``, ``E^T y`` and ``E x`` from the per-row blocks F.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def runs(key: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) of the runs of equal values of ``key`` (N,)."""
    edge = np.flatnonzero(np.diff(key, prepend=-1, append=-1) != 0)
    return [(int(a), int(b)) for a, b in zip(edge[:-1], edge[1:], strict=False)]


class Coupling:
    """Static layout of the height-camera coupling E (heights x camera columns).

    Residual row i with a height adds its (L,) block ``F_i = w_i Jh_i Jc_i``
    to ``E[hidx_i, cols_i]``; ``cols_i`` are its image's columns (6 pose,
    then the camera's intrinsics, shared by the camera's images; padding
    column ``n_red``). Kept: the CSR pattern of E (with duplicates), and
    for ``E^T D E = sum_j D_j e_j e_j^T`` every pair of blocks (a, b) of one
    height with ``img[a] <= img[b]``, grouped by image pair, so that the term
    is one L x L product per image pair (a few hundred) instead of a sparse
    matrix product.

    Parameters
    ----------
    img, hidx : (Nh,) int arrays, image and height of each row with a height.
    cols : (Nh, L) int array, camera-block columns of each such row.
    n_heights, n_red : int, the numbers of heights and camera-block columns.
    sparse : bool, :meth:`gram` returns CSR (a large camera block) instead of
        a dense array.
    """

    def __init__(
        self, img, hidx, cols, n_heights: int, n_red: int, sparse: bool = False
    ) -> None:
        Nh, L = cols.shape
        n1 = n_red + 1
        self.hidx, self.cols = hidx, cols
        self.sparse = sparse
        self._csr = None  # the CSR pattern of gram, made on first use
        self.shape, self.L = (n_heights, n_red), L
        order = np.argsort(hidx, kind="stable")
        counts = np.bincount(hidx, minlength=n_heights)
        # Pairs (a, a) need no gather: each run of rows of one image adds
        # F_run^T F_run to its diagonal block. The other ordered pairs of
        # rows of one height (rows sorted by height, each paired with every
        # row of its group): those of two images once (img[a] < img[b]), both
        # orders of those of one image.
        self.runs = runs(img)
        self.run_cols = cols[[a for a, _ in self.runs]].reshape(-1, L)
        start = np.cumsum(counts) - counts
        size = counts[hidx[order]]
        first_of = np.repeat(np.cumsum(size) - size, size)
        a = np.repeat(np.arange(Nh), size)
        b = np.repeat(start[hidx[order]], size) + np.arange(len(a)) - first_of
        a, b = order[a], order[b]
        ok = (img[a] < img[b]) | ((img[a] == img[b]) & (a != b))
        a, b = a[ok], b[ok]
        pair = img[a] * (int(img.max(initial=0)) + 1) + img[b]
        o = np.argsort(pair, kind="stable")
        self.a, self.b, pair = a[o], b[o], pair[o]
        first = np.flatnonzero(np.diff(pair, prepend=-1))
        self.bounds = np.append(first, len(o))
        # Where each block goes in the padded (n1, n1) term: the runs', then
        # the image pairs'; a pair of two images also, transposed, to
        # (cols_b, cols_a).
        ca = np.concatenate([self.run_cols, cols[self.a[first]]])
        cb = np.concatenate([self.run_cols, cols[self.b[first]]])
        off = np.concatenate(
            [np.zeros(len(self.runs), bool), img[self.a[first]] != img[self.b[first]]]
        )
        self.offdiag = off
        self.flat = np.concatenate(
            [
                (ca[:, :, None] * n1 + cb[:, None, :]).ravel(),
                (ca[off][:, :, None] + cb[off][:, None, :] * n1).ravel(),
            ]
        )

    def matrix(self, F: np.ndarray) -> sp.csr_matrix:
        """E (n_heights, n_red) from the (Nh, L) blocks (for diagnostics)."""
        rows = np.broadcast_to(self.hidx[:, None], self.cols.shape)
        valid = self.cols < self.shape[1]  # not the padding column
        E = sp.coo_matrix((F[valid], (rows[valid], self.cols[valid])), self.shape)
        return E.tocsr()

    def rmatvec(self, F: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(n_red,) ``E^T y`` for (n_heights,) ``y``."""
        yr = y[self.hidx]
        per_run = np.empty((len(self.runs), self.L))
        for p, (a, b) in enumerate(self.runs):
            np.matmul(yr[a:b], F[a:b], out=per_run[p])
        n1 = self.shape[1] + 1
        return np.bincount(self.run_cols.ravel(), per_run.ravel(), n1)[:-1]

    def matvec(self, F: np.ndarray, x: np.ndarray) -> np.ndarray:
        """(n_heights,) ``E x`` for (n_red,) ``x``."""
        xp = np.append(x, 0.0)  # the padding column
        per_row = np.empty(len(F))
        for (a, b), cols in zip(self.runs, self.run_cols, strict=True):
            np.matmul(F[a:b], xp[cols], out=per_row[a:b])
        return np.bincount(self.hidx, per_row, self.shape[0])

    def dense_rows(self, F: np.ndarray, heights: np.ndarray) -> np.ndarray:
        """(len(heights), n_red) the rows ``E[heights]``, dense (a few)."""
        pos = np.full(self.shape[0], -1)
        pos[heights] = np.arange(len(heights))
        sel = np.flatnonzero(pos[self.hidx] >= 0)
        out = np.zeros((len(heights), self.shape[1] + 1))
        np.add.at(out, (pos[self.hidx[sel]][:, None], self.cols[sel]), F[sel])
        return out[:, :-1]

    def gram(self, F: np.ndarray, scale: np.ndarray):
        """(n_red, n_red) ``E^T diag(scale^2) E`` for per-height ``scale``:
        dense, or CSR where the coupling is ``sparse``."""
        Fs = F * scale[self.hidx][:, None]
        nr = len(self.runs)
        blocks = np.empty((nr + len(self.bounds) - 1, self.L, self.L))
        for p, (s, e) in enumerate(self.runs):
            np.matmul(Fs[s:e].T, Fs[s:e], out=blocks[p])
        for p in range(len(self.bounds) - 1):
            # Gathered per image pair: small, in cache.
            s, e = self.bounds[p], self.bounds[p + 1]
            FA = np.take(Fs, self.a[s:e], axis=0)
            FB = np.take(Fs, self.b[s:e], axis=0)
            np.matmul(FA.T, FB, out=blocks[nr + p])
        vals = np.concatenate([blocks.ravel(), blocks[self.offdiag].ravel()])
        n1 = self.shape[1] + 1
        if not self.sparse:
            out = np.bincount(self.flat, vals, minlength=n1 * n1)
            return out.reshape(n1, n1)[:-1, :-1]
        slot, indices, indptr = self._pattern()
        data = np.bincount(slot, vals, len(indices) + 1)[:-1]
        n = self.shape[1]
        return sp.csr_matrix((data, indices, indptr), (n, n))

    def _pattern(self):
        """The CSR pattern of :meth:`gram`'s cells: each block entry's slot
        (the dropped padding cells at the last slot), column indices and row
        pointers; the same for every linearisation, so formed once."""
        if self._csr is None:
            n = self.shape[1]
            cells, slot = np.unique(self.flat, return_inverse=True)
            row, col = np.divmod(cells, n + 1)  # sorted by row, then column
            keep = (row < n) & (col < n)
            to_kept = np.full(len(cells), int(keep.sum()))
            to_kept[keep] = np.arange(int(keep.sum()))
            indptr = np.searchsorted(row[keep], np.arange(n + 1))
            self._csr = (to_kept[slot], col[keep], indptr)
        return self._csr
