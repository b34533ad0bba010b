"""Slopes → heights with conditioning heights — SPC's SLP2HGT as one sparse direct solve.

Specification: ``map-refinement.md`` §2 "Integration" (bigmap.f and the SPC wiki's "Find heights"
page): the heights h (cells) of a maplet minimise

    Σ_edges (h_b − h_a − t̄)² + w Σ_{c∈C} (h_c − h̃_c)²

where an edge joins two valid neighbouring cells a → b along UX (axis 0, t̄ = the mean of the two
cells' t₁) or along UY (axis 1, t̄ = the mean of their t₂) — consistent with HGT2SLP's central
differences (:func:`spctool.geometry.heightfield.slopes`) — and C is a sparse random subset of
**conditioning cells** whose heights h̃ come from the starting maplet; w = 0.025 by default ("always
use .025"; 0.01 for a first pass).  SPC relaxes iteratively (20 SLP2HGT calls a round); the normal
equations (a sparse, symmetric positive-definite 5-point Laplacian plus the conditioning diagonal)
are solved here at once by SuperLU (:func:`scipy.sparse.linalg.splu`; the factorization depends on
the masks only, so a caller's ``cache`` keeps it across passes).

Cells may also be **fixed** (their height is known and kept, e.g. cells with too few pictures that keep
their prior): they are not unknowns, and their edges to free cells pull those toward them.  A tiny
ridge (``ridge``·w toward h̃ on every free cell) keeps the system non-singular for an island of free
cells that touches neither a conditioning cell nor a fixed one; it is far below anything measurable
(1e-6 of the conditioning weight by default).

:func:`keep_plane` restores the starting map's best-fit plane (offset and tilt) — the relief's tilt is
the direction the λ ratios cannot fix (map-refinement.md §2, "Pitfalls").
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from spctool.errors import SpcUsageError

__all__ = ["conditioning_cells", "integrate_slopes", "keep_plane", "normal_system"]


def conditioning_cells(valid, fraction: float, seed: int = 0) -> np.ndarray:
    """A random subset (N, N) of ``valid`` cells, ⌈fraction·n_valid⌉ of them (at least one when any
    cell is valid), drawn by ``numpy.random.default_rng(seed)`` (bigmap.f's fraction ≈ 0.005)."""
    v = np.asarray(valid, dtype=bool)
    if not 0.0 <= fraction <= 1.0:
        raise SpcUsageError(f"conditioning fraction must lie in [0, 1], got {fraction}")
    idx = np.flatnonzero(v.reshape(-1))
    out = np.zeros(v.size, dtype=bool)
    if idx.size == 0 or fraction == 0.0:
        return out.reshape(v.shape)
    k = max(1, int(np.ceil(fraction * idx.size)))
    rng = np.random.default_rng(seed)
    out[rng.choice(idx, size=min(k, idx.size), replace=False)] = True
    return out.reshape(v.shape)


def _edges(valid):
    """Edges (a, b, axis) between valid neighbours, flat indices, a → b along +axis."""
    n0, n1 = valid.shape
    flat = np.arange(n0 * n1).reshape(n0, n1)
    e0 = valid[:-1, :] & valid[1:, :]
    e1 = valid[:, :-1] & valid[:, 1:]
    a = np.concatenate([flat[:-1, :][e0], flat[:, :-1][e1]])
    b = np.concatenate([flat[1:, :][e0], flat[:, 1:][e1]])
    axis = np.concatenate([np.zeros(int(e0.sum()), np.int8), np.ones(int(e1.sum()), np.int8)])
    return a, b, axis


def normal_system(t1, t2, valid, conditioning, targets, weight: float = 0.025, fixed=None,
                  ridge: float = 1e-6):
    """The least-squares system of the module docstring as a sparse design matrix and right side:
    (G, d, free) with G (rows, n_free) CSR, d (rows,), ``free`` the flat indices of the unknowns.
    Minimising |G h_free − d|² is the integration (used by :func:`integrate_slopes` and by the tests'
    dense brute force)."""
    t1 = np.asarray(t1, dtype=np.float64)
    t2 = np.asarray(t2, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    shape = valid.shape
    cond = np.asarray(conditioning, dtype=bool) & valid
    tgt = np.asarray(targets, dtype=np.float64).reshape(-1)
    fix = np.zeros(shape, dtype=bool) if fixed is None else (np.asarray(fixed, dtype=bool) & valid)
    free_mask = valid & ~fix
    free = np.flatnonzero(free_mask.reshape(-1))
    col = np.full(valid.size, -1, dtype=np.int64)
    col[free] = np.arange(free.size)

    a, b, axis = _edges(valid)
    slope = np.where(axis == 0, 0.5 * (t1.reshape(-1)[a] + t1.reshape(-1)[b]),
                     0.5 * (t2.reshape(-1)[a] + t2.reshape(-1)[b]))
    ca, cb = col[a], col[b]
    keep = (ca >= 0) | (cb >= 0)  # an edge between two fixed cells says nothing
    a, b, ca, cb, slope = a[keep], b[keep], ca[keep], cb[keep], slope[keep]
    # h_b − h_a = t̄ ; a known (fixed) height moves to the right side
    rhs = slope + np.where(ca < 0, tgt[a], 0.0) - np.where(cb < 0, tgt[b], 0.0)
    ne = a.size
    rows = np.concatenate([np.arange(ne)[cb >= 0], np.arange(ne)[ca >= 0]])
    cols = np.concatenate([cb[cb >= 0], ca[ca >= 0]])
    vals = np.concatenate([np.ones(int(np.sum(cb >= 0))), -np.ones(int(np.sum(ca >= 0)))])

    cfree = np.flatnonzero((cond & free_mask).reshape(-1))
    sw = np.sqrt(float(weight))
    rr = np.sqrt(float(weight) * float(ridge))
    n_c = cfree.size
    rows = np.concatenate([rows, ne + np.arange(n_c), ne + n_c + np.arange(free.size)])
    cols = np.concatenate([cols, col[cfree], np.arange(free.size)])
    vals = np.concatenate([vals, np.full(n_c, sw), np.full(free.size, rr)])
    d = np.concatenate([rhs, sw * tgt[cfree], rr * tgt[free]])
    g = sp.csr_matrix((vals, (rows, cols)), shape=(ne + n_c + free.size, free.size))
    return g, d, free


def integrate_slopes(t1, t2, valid, conditioning, targets, weight: float = 0.025, fixed=None,
                     ridge: float = 1e-6, cache: dict | None = None) -> np.ndarray:
    """Heights (N, N) in cells from the slopes ``t1`` (along UX, axis 0) and ``t2`` (along UY, axis 1)
    of the ``valid`` cells, conditioned at ``conditioning`` cells toward ``targets`` with weight
    ``weight``; ``fixed`` cells keep ``targets``.  Invalid cells are 0.  One sparse direct solve of
    the normal equations (module docstring).

    ``cache``: a dict kept by the caller across calls (the outer loop's passes).  The normal matrix
    depends only on the masks and the weights, not on the slopes or targets, so its SuperLU
    factorization (minimum-degree ordering of AᵀA + A) is made once per set of masks and kept there;
    each later call is a back-substitution."""
    if not float(weight) > 0.0:
        raise SpcUsageError(f"conditioning weight must be > 0, got {weight}")
    valid = np.asarray(valid, dtype=bool)
    tgt = np.asarray(targets, dtype=np.float64)
    g, d, free = normal_system(t1, t2, valid, conditioning, tgt, weight, fixed, ridge)
    out = np.where(valid, tgt, 0.0).reshape(-1).copy()
    if free.size:
        gt = g.T.tocsr()
        key = None
        if cache is not None:
            fix = np.zeros(valid.shape, dtype=bool) if fixed is None else np.asarray(fixed, dtype=bool)
            cond = np.asarray(conditioning, dtype=bool)
            key = (valid.shape, valid.tobytes(), cond.tobytes(), fix.tobytes(), float(weight), float(ridge))
        lu = cache.get(key) if cache is not None else None
        if lu is None:
            lu = splu((gt @ g).tocsc(), permc_spec="MMD_AT_PLUS_A")
            if cache is not None:
                cache.clear()  # one set of masks at a time
                cache[key] = lu
        out[free] = lu.solve(gt @ d)
    return out.reshape(valid.shape)


def keep_plane(heights, reference, mask) -> np.ndarray:
    """``heights`` with its best-fit plane over ``mask`` replaced by that of ``reference``: the
    least-squares plane c₀ + c₁x + c₂y of (heights − reference) is subtracted on the whole grid."""
    h = np.asarray(heights, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    if np.count_nonzero(m) < 3:
        return h.copy()
    r, c = np.nonzero(m)
    design = np.stack([np.ones(r.size), r.astype(float), c.astype(float)], axis=1)
    diff = (h - np.asarray(reference, dtype=np.float64))[m]
    coef, *_ = np.linalg.lstsq(design, diff, rcond=None)
    rr, cc = np.indices(h.shape)
    return h - (coef[0] + coef[1] * rr + coef[2] * cc)
