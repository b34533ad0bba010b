"""A frozen reference for the correlation's NCC kernel: ``_k_ncc`` as it was at bd3e756 (issue 17), with
the run finder ``_k_runs`` of the same version, before their rewrite with unsigned indices and one array
per prefix and box sum, which was to keep every sum's operations and order.  ``tests/test_correlate.py``
holds the rewritten kernel to this one bit for bit (surfaces and counts); the dense correlation
``_k_dense`` is shared, unchanged.  Not used by spctool."""

from __future__ import annotations

import math

import numba
import numpy as np

from spctool.stages.correlate import _k_dense


@numba.njit(cache=True)
def _k_runs(mask_row, lo, hi, out):
    """Write the [start, stop) runs of True in mask_row[lo:hi] to out (k, 2); return k."""
    k = 0
    j = lo
    while j < hi:
        if mask_row[j]:
            s = j
            while j < hi and mask_row[j]:
                j += 1
            out[k, 0] = s
            out[k, 1] = j
            k += 1
        else:
            j += 1
    return k


@numba.njit(cache=True)
def k_ncc_bd3e756(e, me, p, mp, o0, o1, half, min_valid, surf, cnts):
    """C[a, b] (a = u + k, b = v + k) = Pearson over E[i, j] ↔ P[i − o0 − u, j − o1 − v], both valid.

    Work in P's frame: E' = E[i + o0 − k, j + o1 − k] is the (Hp + 2k)×(Wp + 2k) part of E that can
    pair with P at some offset, so pair (P[i, j], E'[i + a, j + b]).  The six Pearson sums split into

    * Σ p·e — a dense correlation (:func:`_k_dense`), values centred and zero where invalid;
    * N, Σe, Σe² (over P-valid pixels) and Σp, Σp² (over E-valid pixels) — masked box sums, taken from
      row prefix sums at the ends of each run of valid pixels (two look-ups per run and offset), so
      their cost depends on the number of runs, not on the number of pixels.

    All sums are float64; the result equals the brute-force Pearson to rounding (≈ 1e-15).
    """
    he, we = e.shape
    hp, wp = p.shape
    g = 2 * half + 1
    h2 = hp + g - 1
    w2 = wp + g - 1
    # rows/columns of E' that are real E pixels
    r0 = max(0, half - o0)
    r1 = max(r0, min(h2, he + half - o0))
    c0 = max(0, half - o1)
    c1 = max(c0, min(w2, we + half - o1))
    # centring constants: Pearson is shift-invariant; centring keeps the one-pass sums well conditioned
    ce = 0.0
    ne = 0
    for i in range(r0, r1):
        for j in range(c0, c1):
            if me[i + o0 - half, j + o1 - half]:
                ce += e[i + o0 - half, j + o1 - half]
                ne += 1
    ce = ce / ne if ne > 0 else 0.0
    cp = 0.0
    npv = 0
    for i in range(hp):
        for j in range(wp):
            if mp[i, j]:
                cp += p[i, j]
                npv += 1
    cp = cp / npv if npv > 0 else 0.0
    # E': validity, centred values, row prefixes of (valid, v, v²): rpe[r, 3c + q] = Σ_{j<c}
    mv = np.zeros((h2, w2), np.bool_)
    ez = np.zeros((h2, w2))
    rpe = np.zeros((h2, 3 * (w2 + 1)))
    for i in range(r0, r1):
        n_ = 0.0
        s_ = 0.0
        s2_ = 0.0
        row = rpe[i]
        for j in range(w2):
            if j >= c0 and j < c1 and me[i + o0 - half, j + o1 - half]:
                v = e[i + o0 - half, j + o1 - half] - ce
                ez[i, j] = v
                mv[i, j] = True
                n_ += 1.0
                s_ += v
                s2_ += v * v
            row[3 * j + 3] = n_
            row[3 * j + 4] = s_
            row[3 * j + 5] = s2_
    # P: centred values, row prefixes of (v, v²) for columns c = −pad … w2: rpp[i, 2(c + pad) + q]
    pad = g - 1
    pz = np.zeros((hp, wp))
    wpp = w2 + pad + 1
    rpp = np.zeros((hp, 2 * wpp))
    for i in range(hp):
        s_ = 0.0
        s2_ = 0.0
        row = rpp[i]
        for c in range(w2 + 1):
            if c > 0 and c - 1 < wp and mp[i, c - 1]:
                v = p[i, c - 1] - cp
                pz[i, c - 1] = v
                s_ += v
                s2_ += v * v
            row[2 * (c + pad)] = s_
            row[2 * (c + pad) + 1] = s2_
    acc = np.zeros((g, g, 5))  # N, Σe, Σe², Σp, Σp²
    runs = np.empty((w2 + 1, 2), np.int64)
    for i in range(hp):  # runs of valid P pixels: sums of E' over them
        k = _k_runs(mp[i], 0, wp, runs)
        for q in range(k):
            s = runs[q, 0]
            t = runs[q, 1]
            for a in range(g):
                row = rpe[i + a]
                for b in range(g):
                    acc[a, b, 0] += row[3 * (t + b)] - row[3 * (s + b)]
                    acc[a, b, 1] += row[3 * (t + b) + 1] - row[3 * (s + b) + 1]
                    acc[a, b, 2] += row[3 * (t + b) + 2] - row[3 * (s + b) + 2]
    for r in range(r0, r1):  # runs of valid E' pixels: sums of P over them (P column = E' column − b)
        k = _k_runs(mv[r], c0, c1, runs)
        a_lo = max(0, r - hp + 1)
        a_hi = min(g, r + 1)
        for q in range(k):
            s = runs[q, 0]
            t = runs[q, 1]
            for a in range(a_lo, a_hi):
                row = rpp[r - a]
                for b in range(g):
                    acc[a, b, 3] += row[2 * (t - b + pad)] - row[2 * (s - b + pad)]
                    acc[a, b, 4] += row[2 * (t - b + pad) + 1] - row[2 * (s - b + pad) + 1]
    sep = np.zeros((g, g))
    _k_dense(ez, pz, g, sep)
    for a in range(g):
        for b in range(g):
            n = float(round(acc[a, b, 0]))
            se = acc[a, b, 1]
            see = acc[a, b, 2]
            sp = acc[a, b, 3]
            spp = acc[a, b, 4]
            cnts[a, b] = n
            if n < min_valid:
                surf[a, b] = np.nan
                continue
            de = n * see - se * se
            dp = n * spp - sp * sp
            # a constant image over the overlap (zero variance up to rounding) has no correlation
            if de <= 1e-12 * n * see or dp <= 1e-12 * n * spp:
                surf[a, b] = np.nan
                continue
            c = (n * sep[a, b] - se * sp) / math.sqrt(de * dp)
            surf[a, b] = min(1.0, max(-1.0, c))
