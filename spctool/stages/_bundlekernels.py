"""Numba kernels of the bundle adjustment's reduced camera system (private; used by
:mod:`spctool.stages._bundle_linalg`).

Both loop over the landmarks and, for each, over every pair of its measurements (i, j) — the pairs that
couple two pictures in the Schur complement (map-refinement.md §1):

* :func:`add_pair_blocks` — S −= G_i B_jᵀ at the pictures' (row, column) block of the lower triangle, in
  dense (row·n + column) or LAPACK banded ((row − column)·n + column) storage;
* :func:`add_landmark_pair_covariances` — C_l += G_iᵀ (S⁻¹)_{p(i) p(j)} G_j.

NumPy would build a (pairs, 6, 6) temporary for each (36 floats a pair, a million pairs and more on a
2,000-picture problem); these add each product where it belongs.
"""

from __future__ import annotations

from numba import njit


@njit(cache=True, nogil=True)
def add_pair_blocks(order, starts, counts, row6, g, b, acc, n, dense):
    """acc[(row, col)] −= (G_i B_jᵀ)[a, c] for every landmark's measurement pairs with row ≥ col.

    ``order`` lists the measurements grouped by landmark (``starts``/``counts`` per landmark), ``row6``
    the first row of each measurement's picture in the ordered system (6·rank), ``g`` and ``b`` (K, 6, 3).
    """
    for lm in range(counts.size):
        s0 = starts[lm]
        cnt = counts[lm]
        for ii in range(cnt):
            ki = order[s0 + ii]
            ri = row6[ki]
            for jj in range(cnt):
                kj = order[s0 + jj]
                rj = row6[kj]
                if ri < rj:
                    continue
                for a in range(6):
                    row = ri + a
                    for c in range(6):
                        col = rj + c
                        if row < col:
                            continue
                        v = g[ki, a, 0] * b[kj, c, 0] + g[ki, a, 1] * b[kj, c, 1] + g[ki, a, 2] * b[kj, c, 2]
                        if dense:
                            acc[row * n + col] -= v
                        else:
                            acc[(row - col) * n + col] -= v


@njit(cache=True, nogil=True)
def add_landmark_pair_covariances(order, starts, counts, col6, g, s_inv, out):
    """out[l] += G_iᵀ S⁻¹[p(i), p(j)] G_j over every pair of landmark l's measurements (``col6`` = 6·p)."""
    for lm in range(counts.size):
        s0 = starts[lm]
        cnt = counts[lm]
        for ii in range(cnt):
            ki = order[s0 + ii]
            pi = col6[ki]
            for jj in range(cnt):
                kj = order[s0 + jj]
                pj = col6[kj]
                for a in range(6):
                    for c in range(6):
                        m = s_inv[pi + a, pj + c]
                        if m == 0.0:
                            continue
                        for x in range(3):
                            ga = g[ki, a, x] * m
                            for y in range(3):
                                out[lm, x, y] += ga * g[kj, c, y]
