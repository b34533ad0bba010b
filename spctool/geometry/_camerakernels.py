"""The camera model's numba kernels: the distortion chain (x̄, ȳ) → (sample, line) per point with its
2×2 derivative, and the loops over points that :class:`spctool.geometry.camera.Camera` calls (projection,
camera Jacobian, the damped-Newton inverse, its polish and the cubic grid's exactness test).

The equations, their SPC order and the sources (spc-formats.md §2.5, §6.4, §8; spc-algorithms.md §1.3–1.4;
L15 Eq. 2.24–2.27 with errata 2–3) are in :mod:`spctool.geometry.camera`'s docstring.  Every constant
reaches a kernel as one tuple of floats ``q`` (``camera._NQ`` entries: MMFL, CTR, the K matrix, the
legacy D1…D4, then the model's P0…P20), and the model as its code (``camera.MODELS``).  Compiled on first
use and cached (``cache=True``); ``nogil``: the callers' threads run them side by side.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from spctool.geometry._cubicgrid import _cubic_at, _cubic_weights, focal_direction, rotation_tuple

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@numba.njit(forceinline=True, **_JIT)
def _cubic(q, o, x, y, x2, xy, y2):
    """One axis of the CUBIC model (§6.4): Σ q[o … o+9] · (1, x, y, x², xy, y², x³, x²y, xy², y³)."""
    return (
        q[o]
        + q[o + 1] * x
        + q[o + 2] * y
        + q[o + 3] * x2
        + q[o + 4] * xy
        + q[o + 5] * y2
        + q[o + 6] * x2 * x
        + q[o + 7] * x2 * y
        + q[o + 8] * x * y2
        + q[o + 9] * y2 * y
    )


@numba.njit(forceinline=True, **_JIT)
def _cubic_gradient(q, o, x, y, x2, xy, y2):
    """(∂/∂x, ∂/∂y) of :func:`_cubic`, term by term."""
    dx = q[o + 1] + 2.0 * q[o + 3] * x + q[o + 4] * y + 3.0 * q[o + 6] * x2 + 2.0 * q[o + 7] * xy
    dx = dx + q[o + 8] * y2
    dy = q[o + 2] + q[o + 4] * x + 2.0 * q[o + 5] * y + q[o + 7] * x2 + 2.0 * q[o + 8] * xy
    dy = dy + 3.0 * q[o + 9] * y2
    return dx, dy


@numba.njit(forceinline=True, **_JIT)
def _focal_value(model, q, xn, yn):
    """(x̄, ȳ) → distorted focal plane (x, y) in mm (value only; see :func:`_focal_jac`)."""
    mmfl = q[0]
    if model == 0:
        return mmfl * xn, mmfl * yn
    c = (1.0 + q[13]) * mmfl
    x = c * xn
    y = c * yn
    if model == 1:  # OWEN, SPC order P1…P6 = q[14…19]
        r2 = x * x + y * y
        r = math.sqrt(r2)
        a = q[15] * r2 + q[17] * r2 * r2  # radial P2 r² + P4 r⁴
        b = q[14] * r + q[16] * r2 * r  # pinwheel P1 r + P3 r³
        return (
            x + x * a - y * b + q[18] * x * y + q[19] * x * x,
            y + y * a + x * b + q[18] * y * y + q[19] * x * y,
        )
    if model == 2:  # RADIAL
        r2 = x * x + y * y
        g = 1.0 + q[14] * r2 + q[15] * r2 * r2
        return x * g, y * g
    if model == 3:  # CUBIC: x' = Σ P1…P10 · m, y' = Σ P11…P20 · m
        x2 = x * x
        y2 = y * y
        xy = x * y
        return _cubic(q, 14, x, y, x2, xy, y2), _cubic(q, 24, x, y, x2, xy, y2)
    if model == 4:  # APOLLO
        rho = x * x + y * y
        g = 1.0 + q[14] * rho + q[15] * rho * rho + q[16] * rho * rho * rho
        t = q[17] * rho + q[18] * rho * rho
        return g * x + t * math.sin(q[19]), g * y - t * math.cos(q[19])
    if model == 5:  # HIRISE
        return x - q[14], y - q[15]
    # model 6, LINESCAN (focal plane only): y' = MMFL·ȳ, unscaled
    rr2 = x * x + q[14] * q[14]
    return x * (1.0 + q[15] * rr2 + q[16] * rr2 * math.sqrt(rr2)), mmfl * yn


@numba.njit(forceinline=True, **_JIT)
def _focal_jac(model, q, xn, yn):
    """(x̄, ȳ) → (x, y) mm and a = ∂(x, y)/∂(x̄, ȳ), differentiated term by term from §6.4."""
    mmfl = q[0]
    if model == 0:
        return mmfl * xn, mmfl * yn, mmfl, 0.0, 0.0, mmfl
    c = (1.0 + q[13]) * mmfl
    x = c * xn
    y = c * yn
    if model == 1:  # OWEN
        p1, p2, p3, p4, p5, p6 = q[14], q[15], q[16], q[17], q[18], q[19]
        r2 = x * x + y * y
        r = math.sqrt(r2)
        a = p2 * r2 + p4 * r2 * r2  # radial factor A(r)
        b = p1 * r + p3 * r2 * r  # pinwheel factor B(r)
        da = 2.0 * p2 + 4.0 * p4 * r2  # ∂A/∂x = da·x, ∂A/∂y = da·y
        # ∂B/∂x = B'(r)·x/r with B' = P1 + 3·P3·r²; at r = 0 the products y·B, x·B have zero derivative
        if r > 0.0:
            bp = p1 + 3.0 * p3 * r2
            dbx = bp * (x / r)  # |x/r| ≤ 1: no overflow even for subnormal r
            dby = bp * (y / r)
        else:
            dbx = 0.0
            dby = 0.0
        xd = x + x * a - y * b + p5 * x * y + p6 * x * x
        yd = y + y * a + x * b + p5 * y * y + p6 * x * y
        j11 = 1.0 + a + x * da * x - y * dbx + p5 * y + 2.0 * p6 * x
        j12 = x * da * y - b - y * dby + p5 * x
        j21 = y * da * x + b + x * dbx + p6 * y
        j22 = 1.0 + a + y * da * y + x * dby + 2.0 * p5 * y + p6 * x
        return xd, yd, c * j11, c * j12, c * j21, c * j22
    if model == 2:  # RADIAL
        r2 = x * x + y * y
        g = 1.0 + q[14] * r2 + q[15] * r2 * r2
        dg = 2.0 * q[14] + 4.0 * q[15] * r2  # ∂g/∂x = dg·x
        return x * g, y * g, c * (g + x * dg * x), c * (x * dg * y), c * (y * dg * x), c * (g + y * dg * y)
    if model == 3:  # CUBIC
        x2 = x * x
        y2 = y * y
        xy = x * y
        xd = _cubic(q, 14, x, y, x2, xy, y2)
        yd = _cubic(q, 24, x, y, x2, xy, y2)
        j11, j12 = _cubic_gradient(q, 14, x, y, x2, xy, y2)
        j21, j22 = _cubic_gradient(q, 24, x, y, x2, xy, y2)
        return xd, yd, c * j11, c * j12, c * j21, c * j22
    if model == 4:  # APOLLO
        rho = x * x + y * y
        g = 1.0 + q[14] * rho + q[15] * rho * rho + q[16] * rho * rho * rho
        dg = 2.0 * (q[14] + 2.0 * q[15] * rho + 3.0 * q[16] * rho * rho)  # ∂g/∂x = dg·x
        t = q[17] * rho + q[18] * rho * rho
        dt = 2.0 * (q[17] + 2.0 * q[18] * rho)  # ∂t/∂x = dt·x
        s6 = math.sin(q[19])
        c6 = math.cos(q[19])
        j11 = g + x * dg * x + s6 * dt * x
        j12 = x * dg * y + s6 * dt * y
        j21 = y * dg * x - c6 * dt * x
        j22 = g + y * dg * y - c6 * dt * y
        return g * x + t * s6, g * y - t * c6, c * j11, c * j12, c * j21, c * j22
    if model == 5:  # HIRISE
        return x - q[14], y - q[15], c, 0.0, 0.0, c
    # LINESCAN
    rr2 = x * x + q[14] * q[14]
    rr = math.sqrt(rr2)
    g = 1.0 + q[15] * rr2 + q[16] * rr2 * rr
    dgx = (2.0 * q[15] + 3.0 * q[16] * rr) * x  # ∂g/∂x
    return x * g, mmfl * yn, c * (g + x * dgx), 0.0, 0.0, mmfl


@numba.njit(inline="always", **_JIT)
def _pixel_value(model, q, xn, yn):
    """(x̄, ȳ) → (sample, line): distortion model, legacy D terms (MMPX), K-matrix with x·y column."""
    x, y = _focal_value(model, q, xn, yn)
    f = 1.0 + q[9]
    x *= f
    y *= f
    s = 1.0 + q[10] * (x * x + y * y) + q[11] * y + q[12] * x  # exactly 1 when D2…D4 = 0
    x *= s
    y *= s
    return q[1] + q[3] * x + q[4] * y + q[5] * x * y, q[2] + q[6] * x + q[7] * y + q[8] * x * y


@numba.njit(inline="always", **_JIT)
def _pixel_jac(model, q, xn, yn):
    """(x̄, ȳ) → (sample, line) and the chained 2×2 derivative ∂(sample, line)/∂(x̄, ȳ)."""
    x, y, a11, a12, a21, a22 = _focal_jac(model, q, xn, yn)
    # legacy D terms: ×(1 + D1), then ×s with s = 1 + D2 r² + D3 y + D4 x
    f = 1.0 + q[9]
    x *= f
    y *= f
    d2, d3, d4 = q[10], q[11], q[12]
    s = 1.0 + d2 * (x * x + y * y) + d3 * y + d4 * x
    sx = 2.0 * d2 * x + d4
    sy = 2.0 * d2 * y + d3
    m11 = f * (s + x * sx)
    m12 = f * (x * sy)
    m21 = f * (y * sx)
    m22 = f * (s + y * sy)
    b11 = m11 * a11 + m12 * a21
    b12 = m11 * a12 + m12 * a22
    b21 = m21 * a11 + m22 * a21
    b22 = m21 * a12 + m22 * a22
    x *= s
    y *= s
    k11, k12, k13, k21, k22, k23 = q[3], q[4], q[5], q[6], q[7], q[8]
    q11 = k11 + k13 * y
    q12 = k12 + k13 * x
    q21 = k21 + k23 * y
    q22 = k22 + k23 * x
    return (
        q[1] + k11 * x + k12 * y + k13 * x * y,
        q[2] + k21 * x + k22 * y + k23 * x * y,
        q11 * b11 + q12 * b21,
        q11 * b12 + q12 * b22,
        q21 * b11 + q22 * b21,
        q21 * b12 + q22 * b22,
    )


@numba.njit(**_JIT)
def _k_project_body(points, rot, scobj, q, model, smp, lin, front):
    r00, r01, r02 = rot[0, 0], rot[0, 1], rot[0, 2]
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    r20, r21, r22 = rot[2, 0], rot[2, 1], rot[2, 2]
    s0, s1, s2 = scobj[0], scobj[1], scobj[2]
    for i in range(points.shape[0]):
        u0 = points[i, 0] + s0
        u1 = points[i, 1] + s1
        u2 = points[i, 2] + s2
        z0 = r00 * u0 + r01 * u1 + r02 * u2
        z1 = r10 * u0 + r11 * u1 + r12 * u2
        z2 = r20 * u0 + r21 * u1 + r22 * u2
        smp[i], lin[i] = _pixel_value(model, q, z0 / z2, z1 / z2)
        front[i] = z2 > 0.0


@numba.njit(**_JIT)
def _k_jac_camera(zc, q, model, smp, lin, jac):
    """Pixel and ∂(sample, line)/∂x_C (2×3) of camera-frame points."""
    for i in range(zc.shape[0]):
        w = 1.0 / zc[i, 2]
        xn = zc[i, 0] * w
        yn = zc[i, 1] * w
        s, l, j11, j12, j21, j22 = _pixel_jac(model, q, xn, yn)
        smp[i] = s
        lin[i] = l
        # ∂(x̄, ȳ)/∂x_C = (1/z)·[[1, 0, −x̄], [0, 1, −ȳ]]  (L15 Eq. 2.24 with erratum 2)
        jac[i, 0, 0] = j11 * w
        jac[i, 0, 1] = j12 * w
        jac[i, 0, 2] = -(j11 * xn + j12 * yn) * w
        jac[i, 1, 0] = j21 * w
        jac[i, 1, 1] = j22 * w
        jac[i, 1, 2] = -(j21 * xn + j22 * yn) * w


@numba.njit(**_JIT)
def _k_invert(smp, lin, q, model, guess, tol, max_iter, rot, xn_out, yn_out, dirs, niter_out):
    """Newton on (x̄, ȳ) ↦ (sample, line), per point, with step halving.

    ``guess`` = (G11, G12, G21, G22, g) gives the start (x̄, ȳ) = g·G·(sample − CTR1, line − CTR2) (the
    inverse of the linear part).  Writes x̄, ȳ, the unit direction Rᵀ·(x̄, ȳ, 1)/‖·‖ and the Newton step
    count; NaN where the residual max(|Δsample|, |Δline|) does not reach ``tol`` within ``max_iter``
    steps.  The model is evaluated at one call site only (it is inlined; this keeps compile time low).
    """
    g11, g12, g21, g22, gs = guess
    rr = rotation_tuple(rot)
    for i in range(smp.shape[0]):
        ts = smp[i]
        tl = lin[i]
        ds = ts - q[1]
        dl = tl - q[2]
        xt = gs * (g11 * ds + g12 * dl)  # trial point
        yt = gs * (g21 * ds + g22 * dl)
        xn = xt  # last accepted point
        yn = yt
        err = np.inf
        dx = 0.0
        dy = 0.0
        step = 1.0
        halvings = 0
        it = 0
        ok = False
        while True:
            s, l, j11, j12, j21, j22 = _pixel_jac(model, q, xt, yt)
            fs = s - ts
            fl = l - tl
            e = max(abs(fs), abs(fl))
            if e < err or e <= tol:  # accept the trial point
                xn = xt
                yn = yt
                err = e
                if e <= tol:
                    ok = True
                    break
                if it >= max_iter:
                    break
                det = j11 * j22 - j12 * j21
                if det == 0.0 or det != det:
                    break
                dx = (j12 * fl - j22 * fs) / det
                dy = (j21 * fs - j11 * fl) / det
                step = 1.0
                halvings = 0
                it += 1
            else:  # residual grew (or is NaN): halve the step
                halvings += 1
                if halvings > 30:
                    break
                step *= 0.5
            xt = xn + step * dx
            yt = yn + step * dy
        niter_out[i] = it
        if not ok:
            xn = np.nan
            yn = np.nan
        xn_out[i] = xn
        yn_out[i] = yn
        dirs[i, 0], dirs[i, 1], dirs[i, 2] = focal_direction(xn, yn, rr)


@numba.njit(**_JIT)
def _k_polish(smp, lin, q, model, gxn, gyn, s0, l0, step, max_move, rot, dirs, redo):
    """One Newton step per point from a seed bilinearly interpolated on a grid of exact inverses.

    ``gxn``, ``gyn`` (ns, nl): x̄, ȳ of the grid nodes (sample s0 + a·step, line l0 + b·step).  The seed's
    residual is corrected by one step of Newton on the full 2×2 map; where the step moves the pixel by
    more than ``max_move`` (a seed too poor for one step to be exact), where a node is NaN or the point
    lies off the grid, ``redo`` is set and the caller runs the full iteration there.
    """
    rr = rotation_tuple(rot)
    ns = gxn.shape[0]
    nl = gxn.shape[1]
    inv = 1.0 / step
    for i in range(smp.shape[0]):
        ts = smp[i]
        tl = lin[i]
        u = (ts - s0) * inv
        w = (tl - l0) * inv
        a = int(math.floor(u))
        b = int(math.floor(w))
        redo[i] = True
        if not (0 <= a < ns - 1 and 0 <= b < nl - 1):
            continue
        fu = u - a
        fw = w - b
        w00 = (1.0 - fu) * (1.0 - fw)
        w10 = fu * (1.0 - fw)
        w01 = (1.0 - fu) * fw
        w11 = fu * fw
        xn = w00 * gxn[a, b] + w10 * gxn[a + 1, b] + w01 * gxn[a, b + 1] + w11 * gxn[a + 1, b + 1]
        yn = w00 * gyn[a, b] + w10 * gyn[a + 1, b] + w01 * gyn[a, b + 1] + w11 * gyn[a + 1, b + 1]
        s, l, j11, j12, j21, j22 = _pixel_jac(model, q, xn, yn)
        fs = s - ts
        fl = l - tl
        if not (abs(fs) <= max_move and abs(fl) <= max_move):
            continue
        det = j11 * j22 - j12 * j21
        if det == 0.0 or det != det:
            continue
        xn += (j12 * fl - j22 * fs) / det
        yn += (j21 * fs - j11 * fl) / det
        redo[i] = False
        dirs[i, 0], dirs[i, 1], dirs[i, 2] = focal_direction(xn, yn, rr)


@numba.njit(**_JIT)
def _k_cubic_cells(q, model, gxn, gyn, s0, l0, step, tol, good):
    """``good[a, b]``: the bicubic (tensor cubic Lagrange) interpolant of the grid's exact inverses may
    replace the Newton step in cell (a, b) (interior cells a, b = 1 … n − 3).  Its pixel residual
    max(|Δsample|, |Δline|) is measured at the cell's centre — where the error term (t+1)t(t−1)(t−2)
    peaks in both directions for a smooth map — and at its four quarter points (t = ¼, ¾); a cell is
    good when those residuals are ≤ ``tol`` in it and in every cell within two cells (the stencils
    sharing its nodes: a map that is not smooth there, e.g. OWEN's odd terms at the optical axis, spoils
    them all).  Returns the number of good cells."""
    ns = gxn.shape[0]
    nl = gxn.shape[1]
    bad = np.ones((ns, nl), dtype=np.bool_)
    for a in range(1, ns - 2):
        for b in range(1, nl - 2):
            worst = 0.0
            for k in range(5):
                tu = 0.5 if k == 0 else (0.25 if k < 3 else 0.75)
                tw = 0.5 if k == 0 else (0.25 if k % 2 == 1 else 0.75)
                xn = _cubic_at(gxn, a, b, _cubic_weights(tu), _cubic_weights(tw))
                yn = _cubic_at(gyn, a, b, _cubic_weights(tu), _cubic_weights(tw))
                sv, lv = _pixel_value(model, q, xn, yn)
                e = max(abs(sv - (s0 + (a + tu) * step)), abs(lv - (l0 + (b + tw) * step)))
                if not e <= worst:
                    worst = e if e == e else np.inf
            bad[a, b] = not worst <= tol
    count = 0
    for a in range(ns):
        for b in range(nl):
            ok = 1 <= a < ns - 2 and 1 <= b < nl - 2
            if ok:
                for i in range(max(a - 2, 0), min(a + 3, ns)):
                    for j in range(max(b - 2, 0), min(b + 3, nl)):
                        if bad[i, j] and 1 <= i < ns - 2 and 1 <= j < nl - 2:
                            ok = False
            good[a, b] = ok
            count += ok
    return count
