"""The converged full-resolution stage of a registration (:mod:`spctool.stages.register`, its module
docstring: "converged full-resolution stage"): the spacing-1 step repeated from the current estimate
until it moves by less than ``converge_tol``, by secant (Broyden) steps on F(c) = (where the step puts
V) − c, with cycle detection and, in image space, draft templates first.

Why the stage exists (S16's schedule ends on one spacing-1 step, whose estimate stays 0.3–1 px off on
tilted peaks) and what it measured: ``docs/benchmarks.md``, "converged stage"; the estimator it reads
each step with (``converge_peak``, the least-squares alignment at the grid peak):
:mod:`spctool.stages.alignment`.
"""

from __future__ import annotations

import math

import numpy as np

from spctool.stages.registrar import LandmarkStep, Registrar

__all__ = ["_broyden_step", "_converge", "_converges", "_drafts", "_record"]


def _record(result, last, i, st: LandmarkStep, keep_images: bool):
    if keep_images:
        last[i] = st
    else:  # a shallow copy without the extraction and template (dataclasses.replace re-runs __init__)
        bare = object.__new__(LandmarkStep)
        bare.__dict__.update(st.__dict__)
        bare.extraction = bare.template = None
        last[i] = bare
    result.iterations[i] += 1
    result.spacing[i] = st.correlation.spacing
    result.correlation[i] = st.correlation.peak


def _converges(steps, opts) -> bool:
    """The final full-resolution stage runs when the last align step is at spacing 1."""
    last_align = [v for k, v in steps if k == "align"][-1]
    return opts.converge_max > 0 and int(last_align) == 1


#: a cycle of the final stage (the estimate returns to where it was some steps before) whose
#: diameter is below this many converge_tol (0.1 px at the default 0.005 px: about the 1σ of an image-space
#: measurement) is resolved to the mean of its places
_CYCLE_FACTOR = 20.0


def _broyden_step(jac, f, dc, df):
    """The secant (Broyden) update of the final stage's Jacobian estimate ``jac`` of F(c) = (where the
    step says V is) − c, given the last move ``dc`` and the change ``df`` of F; then the step −jac⁻¹·F.
    Falls back to the plain step F (jac = −I) when the update leaves the Jacobian far from −I (a gain
    outside 0.2–5 on an axis, a turn, or a singular matrix): the secant then measured noise, not gain.

    On Python floats (a 2 × 2 system: the eigenvalues of G = −jac from its trace and determinant, the
    step by Cramer's rule; what ``np.linalg.eigvals``/``solve`` give to a few ulp, at a fiftieth of
    their call overhead — twice per image-space sample)."""
    (j00, j01), (j10, j11) = jac.tolist()
    if dc is not None:
        (c0, c1), (d0, d1) = dc.tolist(), df.tolist()
        den = c0 * c0 + c1 * c1
        if den > 0.0:
            r0 = d0 - (j00 * c0 + j01 * c1)
            r1 = d1 - (j10 * c0 + j11 * c1)
            j00, j01 = j00 + r0 * c0 / den, j01 + r0 * c1 / den
            j10, j11 = j10 + r1 * c0 / den, j11 + r1 * c1 / den
    f0, f1 = f.tolist()
    g00, g01, g10, g11 = -j00, -j01, -j10, -j11
    half = 0.5 * (g00 + g11)
    det = g00 * g11 - g01 * g10
    disc = half * half - det  # eigenvalues half ± √disc (a complex pair where disc < 0)
    usable = math.isfinite(half) and math.isfinite(disc)
    if usable and disc >= 0.0:  # real: imaginary parts 0
        root = math.sqrt(disc)
        usable = half - root >= 0.2 and half + root <= 5.0
    elif usable:  # a complex pair: not a turn (|imaginary| ≤ ½ |real|), real part within the gains
        usable = math.sqrt(-disc) <= 0.5 * abs(half) and 0.2 <= half <= 5.0
    if not usable:
        return -np.eye(2), f.copy()
    # G·x = f by Cramer's rule (det = λ₁λ₂ ≥ 0.04: not singular)
    x0 = (f0 * g11 - g01 * f1) / det
    x1 = (g00 * f1 - g10 * f0) / det
    return np.array([[j00, j01], [j10, j11]]), np.array([x0, x1])


def _drafts(opts) -> bool:
    """The converged stage starts with draft steps: image space, whose coarse templates have fewer rays."""
    return (
        bool(opts.converge_draft)
        and opts.space == "image"
        and int(opts.supersample_coarse) < int(opts.supersample)
    )


def _converge(reg: Registrar, i, camera, c, moved, result, last, factor, seed=None, draft=False):
    """Repeat the spacing-1 step of landmark ``i`` from pixel ``c`` until the estimate moves by less
    than ``converge_tol`` (``moved``: the move of the step that produced ``c``; the stage runs at least
    once when its estimator ``converge_peak`` is not the schedule's ``peak``, unless ``seed`` = (c, F)
    says the schedule's last step was already read with it).  Returns
    ``(status, c, step)``: ``"ok"``; a failed step's status; or ``"not-converged"`` after
    ``converge_max`` extra steps (``c`` is then the last estimate).  ``step`` is the last ok step.

    The moves are secant (Broyden) steps on F(c) = (where the step puts V) − c, whose zero is the
    converged estimate: the first divides F by the starting Jacobian (−I: the plain step F, unless
    ``result.converge_jacobian[i]`` holds one, e.g. the previous pass's; with a ``seed``, already a
    secant step), later ones by the gain the previous steps measured (a least-squares alignment whose
    central-difference gradients underestimate a sharp template's slope overshoots by up to 1.7×,
    which plain steps would turn into a slow oscillation).  The Jacobian each step leaves is kept in
    ``result.converge_jacobian[i]``.  The zero, and so the result, does not depend on the steps
    taken; ``halve_shift`` keeps plain half steps.

    A cycle — the estimate goes round two, three or four places, as an image-space template
    re-rendered at each sub-pixel placement can make it (0.01–0.09 px in the s16-50m Monte Carlo) —
    is detected when a step returns within ``converge_tol`` of an estimate two or more steps before;
    if the places of the cycle are less than ``_CYCLE_FACTOR``·``converge_tol`` apart, their mean is
    the converged estimate (``ok``).

    ``draft`` (``converge_draft``, image space): the steps render their templates at
    ``supersample_coarse`` until one moves by less than ``converge_draft_tol`` (or
    ``converge_draft_max`` drafts, the seed's included, have run); from then on at
    ``supersample``, with the secant Jacobian kept but no secant across the change of template (a
    draft and a full template read slightly different zeros).  ``draft`` says whether ``seed`` came
    from a draft step.  The stage ends only on a full step: the first one already when it moves by
    less than ``converge_accept`` (its secant move taken)."""
    opts = reg.options
    tol = opts.converge_tol
    draft_tol, draft_max = opts.converge_draft_tol, opts.converge_draft_max
    if opts.converge_peak != opts.peak and seed is None:
        moved = math.inf  # at least one step reads the estimate with the stage's own estimator
    st_ok = None
    hist = [np.asarray(c, dtype=np.float64)]
    jac = result.converge_jacobian[i]
    jac = jac.copy() if np.all(np.isfinite(jac)) else -np.eye(2)  # a start from a previous pass, else −I
    prev = seed  # (c, F) of the previous step (``seed``: the schedule's last step, read the same way)
    drafts = int(bool(draft) and seed is not None)  # draft steps run (the seed's)
    if draft and (moved < draft_tol or (draft_max and drafts >= draft_max)):
        draft, prev, moved = False, None, math.inf  # the seed's draft already came close: full templates now
    full = 0  # full-template steps run
    k = 0
    while not moved < tol:
        if k >= opts.converge_max:
            return "not-converged", c, st_ok
        st = reg.step(i, camera, c, 1, final=True, draft=draft)
        _record(result, last, i, st, opts.keep_images)
        k += 1
        if not st.ok:
            return st.status, c, st_ok
        f = st.center + st.shift - c
        if factor != 1.0:
            move = factor * f
        else:
            dc, df = (None, None) if prev is None else (c - prev[0], f - prev[1])
            jac, move = _broyden_step(jac, f, dc, df)
            result.converge_jacobian[i] = jac
            scale = float(np.hypot(*move))
            if scale > 1.0:  # never more than a pixel per step (the linear range of the estimator)
                move = move / scale
        prev = (c, f)
        new = c + move
        moved = float(np.hypot(*(new - c)))
        if draft:
            drafts += 1
            if moved < draft_tol or (draft_max and drafts >= draft_max):
                draft, prev, moved = False, None, math.inf  # close: full templates from here
                hist = []
            c = new
            hist.append(c)
            continue
        st_ok = st
        full += 1
        if full == 1 and moved < opts.converge_accept:  # close enough on the first full template
            return "ok", new, st_ok
        back = [j for j in range(len(hist) - 1) if np.hypot(*(new - hist[j])) < tol]
        if back and moved >= tol:
            cycle = np.array(hist[back[-1] :])
            span = np.max(np.hypot(*(cycle[:, None, :] - cycle[None, :, :]).transpose(2, 0, 1)))
            if span < _CYCLE_FACTOR * tol:
                return "ok", cycle.mean(axis=0), st_ok
        c = new
        hist.append(c)
    return "ok", c, st_ok
