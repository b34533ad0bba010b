"""The reduced camera system of the bundle adjustment: assembly, factorisation and covariance.

After each landmark's 3×3 block D_l is eliminated (map-refinement.md §1, "landmarks eliminated as 3×3
blocks by the Schur complement"), the poses satisfy S δx = g − B D⁻¹ g_V with

    S = A − Σ_l Σ_{i,j ∈ obs(l)} G_i B_jᵀ,     G_k = B_k D_l⁻¹,

A the 6×6 pose blocks (data and priors), B_k = J_x,kᵀ W_k J_V,k the 6×3 cross block of measurement k.
Two pictures are coupled only when they measured a common landmark, so S is block-sparse; its pattern
is that of the pictures' co-visibility graph.  The pictures are put in reverse Cuthill–McKee order
(scipy.sparse.csgraph), which gathers the coupling near the diagonal; S is then assembled directly in
LAPACK's banded storage (one ``bincount`` over the pair blocks, no sparse-matrix product) and
factorised by banded Cholesky (``scipy.linalg.cholesky_banded``, cost n·b²).  When the band is wide
(co-visibility as dense as the pictures: global views) it is the dense Cholesky, cost n³/3.

With camera terms (global unknowns coupled to every picture) the system is assembled as a sparse matrix
and factorised densely (calibration problems are small; a limit says so).

Landmark covariances (the joint ones): D_l⁻¹ + Σ_{i,j ∈ obs(l)} G_iᵀ (S⁻¹)_{p(i) p(j)} G_j, the pair
sums again, from the dense S⁻¹.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

from spctool.errors import SpcResultError
from spctool.stages._bundlekernels import add_landmark_pair_covariances, add_pair_blocks

__all__ = ["PairStructure", "ReducedSystem", "sum_blocks", "inv3", "block_diag3"]

_I6 = np.arange(6)
_I3 = np.arange(3)


class ReducedSystemError(SpcResultError):
    """The reduced normal matrix is not positive definite (exit code 1)."""


def sum_blocks(x, idx, n) -> np.ndarray:
    """Σ over rows of ``x`` grouped by ``idx`` into ``n`` groups (any trailing shape)."""
    out = np.zeros((n,) + x.shape[1:])
    flat = out.reshape(n, -1)
    xf = x.reshape(x.shape[0], -1)
    for c in range(xf.shape[1]):  # one bincount per entry (≤ 36): vectorised over the rows
        flat[:, c] = np.bincount(idx, weights=xf[:, c], minlength=n)
    return out


def inv3(d) -> np.ndarray:
    """Inverses of 3×3 blocks (L, 3, 3)."""
    return d.copy() if d.shape[0] == 0 else np.linalg.inv(d)


def block_diag3(blocks) -> sp.csr_matrix:
    n = blocks.shape[0]
    rows = (3 * np.arange(n))[:, None, None] + _I3[None, :, None] + 0 * _I3[None, None, :]
    cols = (3 * np.arange(n))[:, None, None] + _I3[None, None, :] + 0 * _I3[None, :, None]
    return sp.csr_matrix((blocks.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * n, 3 * n))


class PairStructure:
    """Which measurements share a landmark (the pairs), the pictures' order and the band they span.

    Built once per set of used measurements (it changes only when outliers are flagged).
    """

    def __init__(self, pj, lv, n_pic: int, n_lmk: int):
        self.n_pic = n_pic
        k = pj.size
        order = np.argsort(lv, kind="stable")
        counts = np.bincount(lv, minlength=n_lmk)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        self.order, self.starts, self.counts = order.astype(np.int64), starts, counts.astype(np.int64)
        # the co-visibility graph: pictures that share a landmark (the pairs' picture indices)
        rep = counts[lv[order]]
        total = int(rep.sum())
        ki = np.repeat(order, rep)
        offset = np.arange(total) - np.repeat(np.cumsum(rep) - rep, rep)
        kj = order[np.repeat(starts[lv[order]], rep) + offset]
        graph = sp.csr_matrix((np.ones(total, np.int8), (pj[ki], pj[kj])), shape=(n_pic, n_pic))
        graph.sum_duplicates()
        perm = reverse_cuthill_mckee(graph, symmetric_mode=True) if n_pic else np.zeros(0, np.int64)
        rank = np.empty(n_pic, dtype=np.int64)
        rank[perm] = np.arange(n_pic)
        gc = graph.tocoo()
        self.rank = rank
        self.band_pictures = int(np.max(np.abs(rank[gc.row] - rank[gc.col]), initial=0))
        self.n_pairs = total
        self.n_obs = k


class ReducedSystem:
    """S (banded or dense lower Cholesky) and its right-hand side for one damping."""

    def __init__(self, n: int, factor, kind: str, band: int):
        self.n, self.factor, self.kind, self.band = n, factor, kind, band

    @classmethod
    def assemble(cls, pairs: PairStructure, pj, lv, a, b, dinv, dense_limit_band: float = 0.25):
        """Factorise S = A − Σ pairs G_i B_jᵀ over the poses only (no camera terms)."""
        n_p = pairs.n_pic
        n = 6 * n_p
        rank = pairs.rank
        band = 6 * pairs.band_pictures + 5
        kind = "dense" if (band + 1) > dense_limit_band * max(n, 1) else "banded"
        width = n if kind == "dense" else band + 1
        g = np.einsum("kij,kjl->kil", b, dinv[lv])  # G_k = B_k D_l⁻¹ (K, 6, 3)
        acc = np.zeros(width * n)
        # A: block diagonal
        r = (6 * rank)[:, None, None] + _I6[None, :, None] + 0 * _I6[None, None, :]
        c = (6 * rank)[:, None, None] + _I6[None, None, :] + 0 * _I6[None, :, None]
        _scatter_lower(acc, r.ravel(), c.ravel(), a.ravel(), n, kind)
        add_pair_blocks(
            pairs.order,
            pairs.starts,
            pairs.counts,
            np.ascontiguousarray(6 * rank[pj]),
            np.ascontiguousarray(g),
            np.ascontiguousarray(b),
            acc,
            n,
            kind == "dense",
        )
        try:
            if kind == "dense":
                m = acc.reshape(n, n)
                factor = sla.cholesky(m, lower=True, check_finite=False)
            else:
                ab = acc.reshape(width, n)
                factor = sla.cholesky_banded(ab, lower=True, check_finite=False)
        except (np.linalg.LinAlgError, ValueError):
            raise ReducedSystemError(
                "the reduced normal matrix is not positive definite: the poses are not determined "
                "(a picture with too few landmarks and no prior)"
            ) from None
        out = cls(n, factor, kind, band)
        out.rank = rank
        return out

    def solve(self, rhs_pictures) -> np.ndarray:
        """δx (P·6, picture order) for a right-hand side in picture order."""
        n = self.n
        perm_rhs = np.empty(n)
        idx = (6 * self.rank)[:, None] + _I6[None, :]
        perm_rhs[idx.ravel()] = rhs_pictures
        if self.kind == "dense":
            y = sla.cho_solve((self.factor, True), perm_rhs, check_finite=False)
        else:
            y = sla.cho_solve_banded((self.factor, True), perm_rhs, check_finite=False)
        return y[idx.ravel()]

    def inverse(self) -> np.ndarray:
        """S⁻¹ (dense, picture order)."""
        n = self.n
        eye = np.eye(n)
        if self.kind == "dense":
            inv = sla.cho_solve((self.factor, True), eye, check_finite=False)
        else:
            inv = sla.cho_solve_banded((self.factor, True), eye, check_finite=False)
        idx = ((6 * self.rank)[:, None] + _I6[None, :]).ravel()
        out = inv[np.ix_(idx, idx)]
        return 0.5 * (out + out.T)


def _scatter_lower(acc, rows, cols, vals, n, kind) -> None:
    """Add ``vals`` at (rows, cols) of the lower triangle into dense (row·n + col) or banded
    ((row − col)·n + col) storage; entries above the diagonal are dropped (the matrix is symmetric)."""
    keep = rows >= cols
    r, c, v = rows[keep], cols[keep], vals[keep]
    flat = r * n + c if kind == "dense" else (r - c) * n + c
    acc += np.bincount(flat, weights=v, minlength=acc.size)


def landmark_covariances(pairs: PairStructure, pj, lv, b, dinv, s_inv, n_lmk) -> np.ndarray:
    """D_l⁻¹ + Σ_{i,j ∈ obs(l)} G_iᵀ (S⁻¹)_{p(i) p(j)} G_j for every landmark (module docstring)."""
    g = np.ascontiguousarray(np.einsum("kij,kjl->kil", b, dinv[lv]))
    out = dinv.copy()
    add_landmark_pair_covariances(
        pairs.order,
        pairs.starts,
        pairs.counts,
        np.ascontiguousarray(6 * pj),
        g,
        np.ascontiguousarray(s_inv),
        out,
    )
    return 0.5 * (out + np.swapaxes(out, 1, 2))
