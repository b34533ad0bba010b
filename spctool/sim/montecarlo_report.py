"""The Monte Carlo study's report in S16 Table 3's layout: statistics, text, JSON, CSV and figures.

Specification: spc-algorithms.md §12.5 (Table 3 and the checklist's "dominant error sources"); S16
Table 3 and Fig. 8.  Error statistics are over the successful samples of
:class:`spctool.sim.montecarlo.MonteCarloResult`; the figures are drawn with pillow alone.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from spctool import __version__
from spctool.jsonsafe import json_safe
from spctool.sim.montecarlo import (
    PARAMETERS,
    S16_SAMPLES,
    S16_TABLE3,
    MonteCarloResult,
    status_class,
)

__all__ = [
    "IMAGE_TARGETS",
    "LANDMARK_TARGETS",
    "sensitivity",
    "summarise",
    "format_report",
    "report_document",
    "write_samples_csv",
    "write_figures",
]


# --------------------------------------------------------------------------------------------------
# statistics (S16 Table 3 layout)


def _stats(err: np.ndarray) -> tuple[float, float, float, float]:
    if err.shape[0] == 0:
        return (math.nan,) * 4
    mean = err.mean(axis=0)
    std = err.std(axis=0, ddof=1) if err.shape[0] > 1 else np.full(2, math.nan)
    return float(mean[0]), float(mean[1]), float(std[0]), float(std[1])


def _row(name, status, err, rho, floor=None) -> dict:
    cls = np.array([status_class(s) for s in status])
    ok = cls == "ok"
    e = err[ok]
    sm, lm, ss, ls = _stats(e)
    counts: dict[str, int] = {}
    for s in status:
        counts[str(s)] = counts.get(str(s), 0) + 1
    finite = np.isfinite(rho)
    return {
        "name": name,
        "samples": int(len(status)),
        "ok": int(ok.sum()),
        "sample_mean": sm,
        "line_mean": lm,
        "sample_std": ss,
        "line_std": ls,
        "not_found": int((cls == "not-found").sum()),
        "below_threshold": int((cls == "below").sum()),
        "success_rate": float(ok.mean()) if len(status) else math.nan,
        "mean_max_rho": float(rho[finite].mean()) if finite.any() else math.nan,
        "rho_defined": int(finite.sum()),
        "status_counts": dict(sorted(counts.items())),
        # the zero-perturbation floor and the bias beyond it (LANDMARK_TARGETS)
        **_excess(sm, lm, ss, ls, int(ok.sum()), floor),
    }


#: the issue's per-landmark targets, both spaces: the bias beyond the zero-perturbation floor
#: (|mean − floor|, max over the axes), the 1σ (max over the axes) and the success rate
LANDMARK_TARGETS = {"excess_px": 0.01, "std_px": 0.04, "success_rate": 0.995}


def _excess(sm, lm, ss, ls, n_ok, floor) -> dict:
    """A landmark's bias read against its floor, per axis.

    * ``*_floor`` — truth − measured with every perturbation at zero (one registration in the same photo
      as the samples: its photo noise is theirs too, so it cancels in the difference);
    * ``*_excess`` = |mean − floor|: the bias the perturbations add.  Not |mean| − |floor|: that is
      never larger (triangle inequality) and hides a shift when the two have opposite signs (mean
      −0.05, floor +0.05 px: |mean| − |floor| = 0, the perturbations moved the mean by 0.10 px);
    * ``*_mean_se`` = σ/√n over the successful samples: the sampling uncertainty of the mean, and so of
      the excess (the floor itself is not sampled);
    * ``excess`` / ``excess_se`` — the larger axis' excess and its uncertainty; ``excess_z`` =
      excess / se: how many standard errors the shift from the floor is (≤ 2: not distinguishable
      from sampling noise)."""
    nan = math.nan
    out = {k: nan for k in ("sample_floor", "line_floor", "sample_excess", "line_excess")}
    se = [s / math.sqrt(n_ok) if n_ok > 1 and math.isfinite(s) else nan for s in (ss, ls)]
    out.update(sample_mean_se=se[0], line_mean_se=se[1], excess=nan, excess_se=nan, excess_z=nan)
    if floor is None:
        return out
    f = (float(floor[0]), float(floor[1]))
    ex = (abs(sm - f[0]), abs(lm - f[1]))
    out.update(sample_floor=f[0], line_floor=f[1], sample_excess=ex[0], line_excess=ex[1])
    fin = [k for k in (0, 1) if math.isfinite(ex[k])]
    if len(fin) == 2:  # both axes measured (a lost floor or no successful sample: NaN, a miss)
        k = 0 if ex[0] >= ex[1] else 1
        out.update(excess=ex[k], excess_se=se[k])
        out["excess_z"] = ex[k] / se[k] if se[k] > 0 else nan
    return out


def _verdicts(row) -> dict:
    """PASS/MISS of one landmark against :data:`LANDMARK_TARGETS` (NaN: a miss — nothing measured)."""
    t = LANDMARK_TARGETS
    std = float(np.max([row["sample_std"], row["line_std"]]))  # NaN stays NaN
    return {
        "excess": bool(row["excess"] <= t["excess_px"]),
        "std": bool(std <= t["std_px"]),
        "success": bool(row["success_rate"] >= t["success_rate"]),
    }


def _s16_aggregate() -> dict:
    t = np.array([v for v in S16_TABLE3.values()], float)
    n = S16_SAMPLES * len(S16_TABLE3)
    succ = S16_SAMPLES * len(S16_TABLE3) - t[:, 4].sum() - t[:, 5].sum()
    return {
        "success_rate": float(succ / n),
        "min_success_rate": float(t[:, 6].min()),
        "max_abs_sample_mean": float(np.abs(t[:, 0]).max()),
        "max_abs_line_mean": float(np.abs(t[:, 1]).max()),
        "max_sample_std": float(t[:, 2].max()),
        "max_line_std": float(t[:, 3].max()),
        "median_abs_sample_mean": float(np.median(np.abs(t[:, 0]))),
        "median_abs_line_mean": float(np.median(np.abs(t[:, 1]))),
        "median_sample_std": float(np.median(t[:, 2])),
        "median_line_std": float(np.median(t[:, 3])),
        "mean_max_rho": float(t[:, 7].mean()),
    }


#: targets of the issue: image space (success, |mean|, 1σ per axis)
IMAGE_TARGETS = {"success_rate": 0.995, "abs_mean_px": 0.05, "std_px": 0.08}


def sensitivity(result: MonteCarloResult) -> list[dict]:
    """Linear sensitivity of the errors to each design dimension over the successful samples (pooled):
    least-squares coefficients of (s_err, l_err) on the standard-normal design, i.e. px per 1σ of that
    perturbation (the checklist's "dominant error sources", §12.5).  Per-cell fields are not dimensions."""
    ok = result.ok.reshape(-1)
    d = len(result.dimensions)
    if d == 0 or ok.sum() <= d + 1:
        return []
    z = result.z.reshape(-1, d)[ok]
    e = result.error.reshape(-1, 2)[ok]
    # per-landmark means removed (each landmark has its own bias)
    lm = np.repeat(np.arange(len(result.names)), result.config.samples)[ok]
    for i in np.unique(lm):
        sel = lm == i
        e[sel] -= e[sel].mean(axis=0)
        z[sel] -= z[sel].mean(axis=0)
    coef, *_ = np.linalg.lstsq(z, e, rcond=None)
    out = []
    for (name, k, sigma), c in zip(result.dimensions, coef):
        out.append(
            {
                "parameter": name,
                "component": int(k),
                "sigma": sigma,
                "sample_px_per_sigma": float(c[0]),
                "line_px_per_sigma": float(c[1]),
            }
        )
    return out


def summarise(result: MonteCarloResult) -> dict:
    """Table 3 rows per landmark, the pooled ("all") row, the S16 comparison and the target checks."""
    err = result.error
    fl = result.floor
    rows = [
        _row(n, result.status[i], err[i], result.rho[i], None if fl is None else fl[i])
        for i, n in enumerate(result.names)
    ]
    overall = _row("all", result.status.reshape(-1), err.reshape(-1, 2), result.rho.reshape(-1))
    if rows:
        overall["min_success_rate"] = min(r["success_rate"] for r in rows)
        for key in ("sample_mean", "line_mean"):
            vals = [abs(r[key]) for r in rows if math.isfinite(r[key])]
            overall[f"max_abs_{key}"] = max(vals) if vals else math.nan
        for key in ("sample_std", "line_std", "sample_excess", "line_excess"):
            vals = [r[key] for r in rows if math.isfinite(r[key])]
            overall[f"max_{key}"] = max(vals) if vals else math.nan
    for r in rows:
        r["targets"] = (
            _verdicts(r) if fl is not None else {k: v for k, v in _verdicts(r).items() if k != "excess"}
        )
        r["verdict"] = "PASS" if all(r["targets"].values()) else "MISS"
    worst = _worst_landmarks(rows) if rows else {}
    overall["worst_landmarks"] = worst
    if rows and fl is not None:
        overall["max_excess"] = worst["excess"]["value"]
    s16 = _s16_aggregate()
    ours = overall
    checks = {}
    if rows:
        # S16 Table 3 (maplet space): at least as good on success and on the worst landmark per axis
        checks["s16_table3"] = {
            "success_rate": ours["success_rate"] >= s16["success_rate"],
            "max_abs_sample_mean": ours["max_abs_sample_mean"] <= s16["max_abs_sample_mean"],
            "max_abs_line_mean": ours["max_abs_line_mean"] <= s16["max_abs_line_mean"],
            "max_sample_std": ours["max_sample_std"] <= s16["max_sample_std"],
            "max_line_std": ours["max_line_std"] <= s16["max_line_std"],
        }
        t = IMAGE_TARGETS
        checks["image_targets"] = {
            "success_rate": ours["success_rate"] >= t["success_rate"],
            "abs_sample_mean": abs(ours["sample_mean"]) <= t["abs_mean_px"],
            "abs_line_mean": abs(ours["line_mean"]) <= t["abs_mean_px"],
            "sample_std": ours["sample_std"] <= t["std_px"],
            "line_std": ours["line_std"] <= t["std_px"],
        }
        # the same limits for every landmark on its own (informative: not part of --check)
        checks["image_targets_per_landmark"] = {
            "min_success_rate": ours["min_success_rate"] >= t["success_rate"],
            "max_abs_sample_mean": ours["max_abs_sample_mean"] <= t["abs_mean_px"],
            "max_abs_line_mean": ours["max_abs_line_mean"] <= t["abs_mean_px"],
            "max_sample_std": ours["max_sample_std"] <= t["std_px"],
            "max_line_std": ours["max_line_std"] <= t["std_px"],
        }
        # the per-landmark targets, both spaces (LANDMARK_TARGETS): every landmark on its own
        checks["landmark_targets"] = {
            {"excess": "max_excess", "std": "max_std", "success": "min_success_rate"}[k]: all(
                r["targets"][k] for r in rows
            )
            for k in rows[0]["targets"]
        }
        for v in checks.values():
            for k in v:
                v[k] = bool(v[k])
    return {"landmarks": rows, "overall": overall, "s16": s16, "checks": checks}


def _worst_landmarks(rows) -> dict:
    """Per target, the landmark that is furthest from it: ``{"excess"|"std"|"success": {"name", "value",
    "pass"}}`` (a NaN — nothing measured — counts as the worst)."""
    out = {}

    def pick(key, value, higher_is_worse):
        vals = [value(r) for r in rows]
        bad = [i for i, v in enumerate(vals) if not math.isfinite(v)]
        if bad:
            i = bad[0]
        else:
            i = int(np.argmax(vals) if higher_is_worse else np.argmin(vals))
        r = rows[i]
        out[key] = {"name": r["name"], "value": vals[i], "pass": bool(r["targets"].get(key, False))}

    if "excess" in rows[0]["targets"]:
        pick("excess", lambda r: r["excess"], True)
    pick("std", lambda r: float(np.max([r["sample_std"], r["line_std"]])), True)
    pick("success", lambda r: r["success_rate"], False)
    return out


def _f(x, fmt="{:+.3f}") -> str:
    return "nan" if x is None or not math.isfinite(x) else fmt.format(x)


def _target_lines(summary: dict, has_floor: bool) -> list[str]:
    """The per-landmark verdict against :data:`LANDMARK_TARGETS`: each landmark's floor, excess
    (|mean − floor| per axis, ± the mean's σ/√n), largest 1σ, success and PASS/MISS; then the worst
    landmark per target."""
    t = LANDMARK_TARGETS
    rows, ov = summary["landmarks"], summary["overall"]
    out = [""]
    if has_floor:
        out.append(
            "per-landmark targets (px): excess = |mean - floor| per axis, floor = the landmark registered "
            "with every Table 2 sigma at zero; +- = the mean's sigma/sqrt(n)"
        )
        out.append(
            f"{'L-map':8s} {'s floor':>8s} {'l floor':>8s} {'s excess':>15s} {'l excess':>15s} "
            f"{'1 sigma':>7s} {'success':>8s} {'verdict':>7s}"
        )
    else:
        out.append("per-landmark targets (no zero-perturbation floor in this result: excess not judged)")
        out.append(f"{'L-map':8s} {'1 sigma':>7s} {'success':>8s} {'verdict':>7s}")
    for r in rows:
        std = float(np.max([r["sample_std"], r["line_std"]]))
        tail = f"{_f(std, '{:.3f}'):>7s} {_f(r['success_rate'], '{:.3f}'):>8s} {r['verdict']:>7s}"
        if has_floor:
            sx = f"{_f(r['sample_excess'], '{:.4f}')} +-{_f(r['sample_mean_se'], '{:.4f}')}"
            lx = f"{_f(r['line_excess'], '{:.4f}')} +-{_f(r['line_mean_se'], '{:.4f}')}"
            out.append(
                f"{r['name']:8s} {_f(r['sample_floor']):>8s} {_f(r['line_floor']):>8s} {sx:>15s} {lx:>15s} "
                + tail
            )
        else:
            out.append(f"{r['name']:8s} " + tail)
    w = ov["worst_landmarks"]
    parts = []
    if "excess" in w:
        parts.append(
            f"excess <= {t['excess_px']:g} px: {w['excess']['name']} "
            f"{_f(w['excess']['value'], '{:.4f}')} {'PASS' if w['excess']['pass'] else 'MISS'}"
        )
    parts.append(
        f"1 sigma <= {t['std_px']:g} px: {w['std']['name']} {_f(w['std']['value'], '{:.3f}')} "
        f"{'PASS' if w['std']['pass'] else 'MISS'}"
    )
    parts.append(
        f"success >= {100 * t['success_rate']:g} %: {w['success']['name']} "
        f"{_f(100 * w['success']['value'], '{:.1f}')} % {'PASS' if w['success']['pass'] else 'MISS'}"
    )
    n_pass = sum(r["verdict"] == "PASS" for r in rows)
    out.append(f"worst landmark per target: {'; '.join(parts)}")
    out.append(f"landmarks meeting every target: {n_pass} of {len(rows)}")
    return out


def format_report(result: MonteCarloResult, summary: dict | None = None) -> str:
    """The text report: settings, Table 3 layout (ours, then S16's), comparison and target checks."""
    summary = summary or summarise(result)
    c = result.config
    out = []
    src = result.scene_info.get("preset") or result.scene_info.get("workdir") or "scene"
    out.append(f"# spctool {__version__} montecarlo: {src}, picture {result.picture}")
    out.append(
        f"# space {c.space}, steps L = {', '.join(str(n) for n in c.steps)}, "
        f"{c.samples} {c.sampling.upper()} samples per landmark, seed {c.seed}, "
        f"terrain errors {'per cell' if c.fields == 'cell' else 'as one bias'}, "
        f"sigma scale {c.sigma_scale:g}"
    )
    out.append("# perturbations (1 sigma, S16 Table 2):")
    for p in PARAMETERS:
        on = p.name in c.parameters
        mode = ""
        if p.field:
            mode = " per cell" if c.fields == "cell" else " bias"
        out.append(f"#   {p.name:10s} {p.shown:>32s}{mode:9s} {'' if on else '(off) '}{p.label}")
    out.append("")
    head = (
        f"{'L-map':8s} {'s mean':>8s} {'l mean':>8s} {'s std':>7s} {'l std':>7s} {'not found':>9s} "
        f"{'below 0.3':>9s} {'success':>8s} {'mean max rho':>12s}"
    )
    out.append("Table 3 layout (pixels; errors = truth - measured, over successful samples)")
    out.append(head)
    for r in summary["landmarks"] + [summary["overall"]]:
        out.append(
            f"{r['name']:8s} {_f(r['sample_mean']):>8s} {_f(r['line_mean']):>8s} "
            f"{_f(r['sample_std'], '{:.3f}'):>7s} {_f(r['line_std'], '{:.3f}'):>7s} "
            f"{r['not_found']:9d} {r['below_threshold']:9d} "
            f"{_f(r['success_rate'], '{:.3f}'):>8s} {_f(r['mean_max_rho'], '{:.2f}'):>12s}"
        )
    ov = summary["overall"]
    if summary["landmarks"]:
        out.append(
            f"worst landmark: |s mean| {_f(ov['max_abs_sample_mean'], '{:.3f}')}, |l mean| "
            f"{_f(ov['max_abs_line_mean'], '{:.3f}')}, s std {_f(ov['max_sample_std'], '{:.3f}')}, l std "
            f"{_f(ov['max_line_std'], '{:.3f}')}, success {_f(ov['min_success_rate'], '{:.3f}')}"
        )
    if summary["landmarks"]:
        out.extend(_target_lines(summary, result.floor is not None))
    out.append("")
    out.append("S16 Table 3 (maplet space, 50 m, 500 LHS samples each; different terrain, same names)")
    out.append(head)
    for name, t in S16_TABLE3.items():
        out.append(
            f"{name:8s} {t[0]:+8.3f} {t[1]:+8.3f} {t[2]:7.3f} {t[3]:7.3f} {t[4]:9d} {t[5]:9d} "
            f"{t[6]:8.2f} {t[7]:12.2f}"
        )
    s = summary["s16"]
    out.append(
        f"worst landmark: |s mean| {s['max_abs_sample_mean']:.3f}, |l mean| {s['max_abs_line_mean']:.3f}, "
        f"s std {s['max_sample_std']:.3f}, l std {s['max_line_std']:.3f}, "
        f"success {s['min_success_rate']:.2f}; "
        f"overall success {s['success_rate']:.3f}"
    )
    out.append("")
    for group, checks in summary["checks"].items():
        title = {
            "s16_table3": "at least as good as S16 Table 3 (overall success, worst landmark per axis)",
            "image_targets": "image-space targets, all samples (success >= 99.5 %, |mean| <= 0.05 px, "
            "1 sigma <= 0.08 px per axis)",
            "image_targets_per_landmark": "the same for the worst landmark (informative)",
            "landmark_targets": "per-landmark targets, every landmark (excess <= 0.01 px, 1 sigma <= "
            "0.04 px, success >= 99.5 %)",
        }[group]
        marks = ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in checks.items())
        out.append(f"{title}: {marks}")
    sens = sensitivity(result)
    if sens:
        out.append("")
        out.append(
            "error sensitivity (px per 1 sigma; least squares over successful samples, "
            "landmark means removed)"
        )
        groups: dict[str, list] = {}
        for r in sens:
            groups.setdefault(r["parameter"], []).append(r)
        ranked = sorted(
            groups.items(),
            key=lambda kv: (
                -math.sqrt(sum(r["sample_px_per_sigma"] ** 2 + r["line_px_per_sigma"] ** 2 for r in kv[1]))
            ),
        )
        for name, rs in ranked:
            tot = math.sqrt(sum(r["sample_px_per_sigma"] ** 2 + r["line_px_per_sigma"] ** 2 for r in rs))
            comps = " ".join(f"({r['sample_px_per_sigma']:+.4f}, {r['line_px_per_sigma']:+.4f})" for r in rs)
            out.append(f"  {name:10s} {tot:.4f}  {comps}")
    tm = result.timing
    if tm:
        out.append("")
        out.append(
            f"time: {tm.get('run_s', math.nan):.1f} s for {tm.get('samples', 0)} registrations "
            f"({tm.get('per_sample_ms', math.nan):.1f} ms each, {tm.get('jobs', 1)} job(s); "
            f"{tm.get('cpu_per_sample_ms', math.nan):.1f} ms of CPU per registration)"
            + (f"; scene {tm['scene_s']:.1f} s" if "scene_s" in tm else "")
        )
    return "\n".join(out) + "\n"


def report_document(result: MonteCarloResult, summary: dict | None = None) -> dict:
    """The JSON document (cli-contract.md shape): per-landmark Table 3 rows and success rates, the
    overall row, S16's table, checks, sensitivity, settings, timing."""
    summary = summary or summarise(result)
    rows = []
    for i, r in enumerate(summary["landmarks"]):
        r = dict(r)
        r["truth_sample"], r["truth_line"] = (float(v) for v in result.truth[i])
        if r["name"] in S16_TABLE3:
            r["s16"] = dict(
                zip(
                    (
                        "sample_mean",
                        "line_mean",
                        "sample_std",
                        "line_std",
                        "not_found",
                        "below_threshold",
                        "success_rate",
                        "mean_max_rho",
                    ),
                    S16_TABLE3[r["name"]],
                )
            )
        rows.append(r)
    info = {k: v for k, v in result.scene_info.items() if k != "spec"}
    doc = {
        "command": "montecarlo",
        "picture": result.picture,
        "spctool_version": __version__,
        "scene": info,
        "config": result.config.as_dict(),
        "perturbations": [
            {
                "name": p.name,
                "sigma": list(p.sigma),
                "unit": p.unit,
                "label": p.label,
                "s16": p.shown,
                "enabled": p.name in result.config.parameters,
                "mode": (result.config.fields if p.field else "design"),
            }
            for p in PARAMETERS
        ],
        "dimensions": [{"parameter": n, "component": k, "sigma": s} for n, k, s in result.dimensions],
        "landmarks": rows,
        "overall": summary["overall"],
        "s16_table3": {"landmarks": {k: list(v) for k, v in S16_TABLE3.items()}, "aggregate": summary["s16"]},
        "checks": summary["checks"],
        "sensitivity": sensitivity(result),
        "timing": result.timing,
    }
    return json_safe(doc)


def write_samples_csv(result: MonteCarloResult, path) -> Path:
    """One row per sample: landmark, sample, status, rho, iterations, a-priori, measured, error, design."""
    from spctool.formats.atomic import write_text

    dims = [f"z_{n}{k}" for n, k, _ in result.dimensions]
    head = [
        "landmark",
        "sample",
        "status",
        "rho",
        "iterations",
        "apriori_sample",
        "apriori_line",
        "measured_sample",
        "measured_line",
        "err_sample",
        "err_line",
    ] + dims
    lines = [",".join(head)]
    err = result.error
    for i, name in enumerate(result.names):
        for j in range(result.config.samples):
            vals = [
                name,
                str(j),
                str(result.status[i, j]),
                repr(float(result.rho[i, j])),
                str(int(result.iterations[i, j])),
            ]
            vals += [repr(float(x)) for x in (*result.apriori[i, j], *result.measured[i, j], *err[i, j])]
            vals += [repr(float(x)) for x in result.z[i, j]]
            lines.append(",".join(vals))
    path = Path(path)
    write_text(path, "\n".join(lines) + "\n")
    return path


# --------------------------------------------------------------------------------------------------
# figures (pillow; no plotting library needed)


def _nice_step(span: float, target: int = 5) -> float:
    if not span > 0:
        return 1.0
    raw = span / target
    mag = 10.0 ** math.floor(math.log10(raw))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        if raw <= m * mag:
            return m * mag
    return 10.0 * mag


class _Axes:
    """A minimal plot panel drawn with PIL.ImageDraw: data → pixel mapping, frame, ticks, labels."""

    def __init__(self, draw, box, xlim, ylim, *, title="", xlabel="", ylabel="", font=None, small=None):
        self.d = draw
        self.x0, self.y0, self.x1, self.y1 = box
        self.xlim, self.ylim = xlim, ylim
        self.font, self.small = font, small
        self._frame(title, xlabel, ylabel)

    def X(self, x):
        a, b = self.xlim
        return self.x0 + (np.asarray(x, float) - a) / (b - a) * (self.x1 - self.x0)

    def Y(self, y):
        a, b = self.ylim
        return self.y1 - (np.asarray(y, float) - a) / (b - a) * (self.y1 - self.y0)

    def _frame(self, title, xlabel, ylabel):
        d = self.d
        d.rectangle((self.x0, self.y0, self.x1, self.y1), outline=(0, 0, 0))
        for lim, axis in ((self.xlim, "x"), (self.ylim, "y")):
            step = _nice_step(lim[1] - lim[0])
            t = math.ceil(lim[0] / step - 1e-9) * step
            while t <= lim[1] + 1e-9 * step:
                label = f"{t:.10g}" if abs(t) > 1e-12 * step else "0"
                if axis == "x":
                    px = float(self.X(t))
                    d.line((px, self.y1, px, self.y1 + 4), fill=(0, 0, 0))
                    d.line((px, self.y0, px, self.y1), fill=(232, 232, 232))
                    d.text((px, self.y1 + 6), label, fill=(0, 0, 0), font=self.small, anchor="ma")
                else:
                    py = float(self.Y(t))
                    d.line((self.x0 - 4, py, self.x0, py), fill=(0, 0, 0))
                    d.line((self.x0, py, self.x1, py), fill=(232, 232, 232))
                    d.text((self.x0 - 6, py), label, fill=(0, 0, 0), font=self.small, anchor="rm")
                t += step
        d.rectangle((self.x0, self.y0, self.x1, self.y1), outline=(0, 0, 0))
        if title:
            d.text(((self.x0 + self.x1) / 2, self.y0 - 6), title, fill=(0, 0, 0), font=self.font, anchor="md")
        if xlabel:
            d.text(
                ((self.x0 + self.x1) / 2, self.y1 + 22), xlabel, fill=(0, 0, 0), font=self.small, anchor="ma"
            )
        if ylabel:
            d.text(
                (self.x0 - 44, (self.y0 + self.y1) / 2), ylabel, fill=(0, 0, 0), font=self.small, anchor="rm"
            )

    def inside(self, x, y):
        x, y = np.asarray(x, float), np.asarray(y, float)
        return (x >= self.xlim[0]) & (x <= self.xlim[1]) & (y >= self.ylim[0]) & (y <= self.ylim[1])

    def points(self, x, y, color, r=1.5):
        keep = self.inside(x, y)
        for px, py in zip(self.X(np.asarray(x)[keep]), self.Y(np.asarray(y)[keep])):
            self.d.ellipse((px - r, py - r, px + r, py + r), fill=color)
        return int((~keep).sum())

    def polyline(self, x, y, color, width=2):
        pts = [
            (float(a), float(b))
            for a, b in zip(self.X(x), self.Y(y))
            if math.isfinite(a) and math.isfinite(b)
        ]
        if len(pts) > 1:
            self.d.line(pts, fill=color, width=width)

    def bars(self, edges, heights, color):
        for a, b, h in zip(edges[:-1], edges[1:], heights):
            if h > 0:
                self.d.rectangle(
                    (float(self.X(a)), float(self.Y(h)), float(self.X(b)), float(self.Y(0))),
                    fill=color,
                    outline=(80, 80, 80),
                )

    def vline(self, x, color=(0, 0, 0)):
        self.d.line((float(self.X(x)), self.y0, float(self.X(x)), self.y1), fill=color)

    def hline(self, y, color=(0, 0, 0)):
        self.d.line((self.x0, float(self.Y(y)), self.x1, float(self.Y(y))), fill=color)


def _fonts():
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=15), ImageFont.load_default(size=12)
    except TypeError:  # very old Pillow: bitmap font only
        f = ImageFont.load_default()
        return f, f


def _symmetric_limit(values, floor=0.1) -> float:
    v = np.abs(np.asarray(values, float))
    v = v[np.isfinite(v)]
    if v.size == 0:
        return floor
    lim = 1.15 * float(np.percentile(v, 99.5))
    step = _nice_step(lim, 4)
    return max(floor, math.ceil(lim / step) * step)


_OK, _NF, _LOW = (30, 90, 200), (210, 40, 40), (240, 150, 0)


def figure_scatter(result: MonteCarloResult, path) -> Path:
    """S16 Fig. 8: (s, l)_err of the successful samples, one panel per landmark, common axes."""
    from PIL import Image, ImageDraw

    n = len(result.names)
    ncol = min(4, max(n, 1))
    nrow = max(1, math.ceil(n / ncol))
    pw, ph = 300, 300
    W, H = 80 + ncol * (pw + 80), 60 + nrow * (ph + 90)
    im = Image.new("RGB", (W, H), "white")
    d = ImageDraw.Draw(im)
    font, small = _fonts()
    err = result.error
    lim = _symmetric_limit(err[result.ok])
    c = result.config
    d.text(
        (W / 2, 12),
        f"(s, l) error = truth - measured [px]: {c.space} space, {c.samples} {c.sampling.upper()} "
        f"samples per landmark",
        fill=(0, 0, 0),
        font=font,
        anchor="ma",
    )
    for i, name in enumerate(result.names):
        r, q = divmod(i, ncol)
        x0, y0 = 90 + q * (pw + 80), 60 + r * (ph + 90)
        ok = result.ok[i]
        ax = _Axes(
            d,
            (x0, y0, x0 + pw, y0 + ph),
            (-lim, lim),
            (-lim, lim),
            title=f"{name}: {int(ok.sum())}/{c.samples} ok",
            xlabel="sample error [px]",
            ylabel="line",
            font=font,
            small=small,
        )
        ax.hline(0.0, (150, 150, 150))
        ax.vline(0.0, (150, 150, 150))
        outside = ax.points(err[i, ok, 0], err[i, ok, 1], _OK, r=1.6)
        if ok.any():
            m = err[i, ok].mean(axis=0)
            ax.points([m[0]], [m[1]], (220, 0, 0), r=4)
        if outside:
            d.text((x0 + pw - 4, y0 + 4), f"{outside} off axes", fill=(200, 0, 0), font=small, anchor="ra")
    path = Path(path)
    _save_png(im, path)
    return path


def figure_histograms(result: MonteCarloResult, path) -> Path:
    """Histograms of the sample and line errors (successful samples, all landmarks) with the normal
    density of the same mean and standard deviation."""
    from PIL import Image, ImageDraw

    im = Image.new("RGB", (1000, 430), "white")
    d = ImageDraw.Draw(im)
    font, small = _fonts()
    e = result.error[result.ok]
    lim = _symmetric_limit(e)
    edges = np.linspace(-lim, lim, 41)
    for k, axis in enumerate(("sample", "line")):
        v = e[:, k] if e.size else np.zeros(0)
        h, _ = np.histogram(v, edges)
        dens = h / max(v.size, 1) / (edges[1] - edges[0])
        top = max(float(dens.max()) if dens.size else 1.0, 1e-9)
        mu, sd = (float(v.mean()), float(v.std(ddof=1))) if v.size > 1 else (0.0, math.nan)
        if math.isfinite(sd) and sd > 0:
            top = max(top, 1.0 / (sd * math.sqrt(2 * math.pi)))
        x0 = 90 + k * 480
        ax = _Axes(
            d,
            (x0, 50, x0 + 380, 360),
            (-lim, lim),
            (0.0, 1.1 * top),
            title=f"{axis} error: mean {mu:+.3f}, std {sd:.3f} px (n = {v.size})",
            xlabel=f"{axis} error = truth - measured [px]",
            ylabel="density",
            font=font,
            small=small,
        )
        ax.bars(edges, dens, (150, 180, 230))
        if math.isfinite(sd) and sd > 0:
            xs = np.linspace(-lim, lim, 200)
            ax.polyline(xs, np.exp(-0.5 * ((xs - mu) / sd) ** 2) / (sd * math.sqrt(2 * math.pi)), (200, 0, 0))
        ax.vline(0.0, (120, 120, 120))
    path = Path(path)
    _save_png(im, path)
    return path


def figure_success(result: MonteCarloResult, path) -> Path:
    """Success versus perturbation size: (left) the success, not-found and below-threshold fractions in
    bins of the a-priori pixel error |truth − a-priori|; (right) every sample at its a-priori error,
    coloured by outcome."""
    from PIL import Image, ImageDraw

    im = Image.new("RGB", (1040, 470), "white")
    d = ImageDraw.Draw(im)
    font, small = _fonts()
    ae = result.apriori_error.reshape(-1, 2)
    size = np.hypot(ae[:, 0], ae[:, 1])
    cls = np.array([status_class(s) for s in result.status.reshape(-1)])
    fin = np.isfinite(size)
    top = float(np.percentile(size[fin], 99.5)) if fin.any() else 1.0
    step = _nice_step(top, 12)
    xmax = max(step, math.ceil(top / step) * step)
    edges = np.arange(0.0, xmax + 0.5 * step, step)
    ax = _Axes(
        d,
        (90, 50, 470, 390),
        (0.0, float(edges[-1])),
        (0.0, 1.05),
        title="outcome versus a-priori pixel error",
        xlabel="|truth - a priori| [px]",
        ylabel="fraction",
        font=font,
        small=small,
    )
    idx = np.clip(np.digitize(size, edges) - 1, 0, len(edges) - 2)
    mids = 0.5 * (edges[:-1] + edges[1:])
    for label, color in (("ok", _OK), ("not-found", _NF), ("below", _LOW)):
        frac = np.full(len(mids), np.nan)
        for b in range(len(mids)):
            sel = fin & (idx == b)
            if sel.sum() >= 3:
                frac[b] = float(np.mean(cls[sel] == label))
        ax.polyline(mids, frac, color, width=2)
        ax.points(mids[np.isfinite(frac)], frac[np.isfinite(frac)], color, r=3)
    for k, (label, color) in enumerate((("success", _OK), ("not found", _NF), ("below 0.3", _LOW))):
        d.text((110 + 130 * k, 440), label, fill=color, font=font)
    lim = max(step, math.ceil(1.02 * float(np.abs(ae[fin]).max()) / step) * step) if fin.any() else 1.0
    ax2 = _Axes(
        d,
        (600, 50, 940, 390),
        (-lim, lim),
        (-lim, lim),
        title="samples at their a-priori pixel error",
        xlabel="sample: truth - a priori [px]",
        ylabel="line",
        font=font,
        small=small,
    )
    for label, color in (("ok", _OK), ("below", _LOW), ("not-found", _NF)):
        sel = fin & (cls == label)
        ax2.points(ae[sel, 0], ae[sel, 1], color, r=1.4)
    path = Path(path)
    _save_png(im, path)
    return path


def write_figures(result: MonteCarloResult, outdir, prefix: str = "montecarlo") -> list[Path]:
    """The PNG figures: ``<prefix>_scatter.png`` (S16 Fig. 8), ``<prefix>_histograms.png``,
    ``<prefix>_success.png`` (success versus perturbation size)."""
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    return [
        figure_scatter(result, out / f"{prefix}_scatter.png"),
        figure_histograms(result, out / f"{prefix}_histograms.png"),
        figure_success(result, out / f"{prefix}_success.png"),
    ]


def _save_png(im, path) -> None:
    """Write a figure atomically; a different picture already at ``path`` is kept as ``path.bak``."""
    import io

    from spctool.formats import atomic

    buf = io.BytesIO()
    im.save(buf, format="PNG")
    data = buf.getvalue()
    if Path(path).is_file() and Path(path).read_bytes() == data:
        return
    atomic.write_bytes(path, data, backup=True)
