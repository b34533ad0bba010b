"""Calibration of the measurement and pose covariances on the independent worlds (issue #39).

Four worlds ray-traced by trimesh + Embree (:mod:`spctool.sim.independent`, the world of
``bench_accuracy``: 16 maplets 99×99 at 5 cm, six pictures at 200 m, a-priori errors 6–20 px): a
faceted and a smooth truth, each with the views' own Sun (38–60° from the zenith, ``high``) and with a
low Sun (70°, ``low``).  Every picture is navigated (two passes, the default options, maplet and image
space); against the truth pixels and poses this prints, per world × space:

* ``d2`` / ``cov95`` — per landmark, mean d² = eᵀ(Cᵢ + τ²I)⁻¹e and the fraction inside the 95 % ellipse
  (target 2 ± 0.5 and 0.90–0.98), e = measured − true pixel, Cᵢ the registration's covariance, τ the
  model error the surface-weighted pose solve estimates;
* ``d2c`` / ``cov95c`` — the same with the marginal covariance of ``--weights surface``: each
  landmark's share of the shading model's error patterns (:mod:`spctool.stages.model_error`) and the
  model error with its common part, Cᵢ + Σₖ δᵢ⁽ᵏ⁾δᵢ⁽ᵏ⁾ᵀ + τ²I + τ²I;
* ``d2nav`` / ``cov95nav`` — the same with navigate's own per-landmark covariance (``--weights``):
  Cᵢ + τ²I + the common part of its pose solve (+ the patterns' share with ``surface``);
* ``common`` — rms over the pictures of the picture's common error ē (mean of e over its landmarks), and
  ``along`` the rms of its component along the Sun's direction in the image; ``sigc`` the rms of the
  patterns' mean shifts (what the sensitivity says the common error is);
* ``NEES uni`` / ``sur`` / ``sur+C`` / ``nav`` — mean pose NEES (χ²₆: 6) of the final pose solved with
  uniform weights (σ = 0.1 px), with the registration covariances plus τ, and with these plus the error
  patterns as correlated modes (Woodbury), over the pictures; ``nav`` is navigate's own final pose (with
  ``--weights``); ``>99.9`` the count of pictures beyond χ²₆'s 99.9 % quantile (22.5) for each;
* ``pos_m`` / ``att_urad`` — rms over the pictures of the pose error (position m, attitude µrad) with
  uniform weights and of navigate's pose; ``cpu_s`` navigate's CPU seconds for the six pictures.

Run: ``python benchmarks/calibration.py [--root DIR] [--worlds facet-high,...] [--spaces maplet,image]
[--json FILE]`` (worlds are built once into DIR, ~1 min each on one core).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

WORLDS = ("facet-high", "facet-low", "smooth-high", "smooth-low")
NEES_999 = 22.458  # χ²₆ 99.9 % quantile


def world_spec(name):
    """The independent world NAME ("facet-high", …): bench_accuracy's worlds, the same specification."""
    from bench_accuracy import _spec

    truth, sun = name.split("-")
    return _spec(truth, sun)


def world(root, name):
    """(directory, truth document) of world ``name``, built into ``root/name`` unless already there."""
    from spctool.sim.independent import build_world

    d = Path(root) / name
    doc = d / "TRUTH.json"
    if doc.exists():
        return d, json.loads(doc.read_text())
    return d, build_world(d, world_spec(name))


def sun_direction_px(cam, v, sun):
    """Unit (sample, line) direction of the Sun's azimuth in the image at the landmarks ``v`` (N, 3)."""
    s0, l0 = cam.project(v)
    s1, l1 = cam.project(v + 1e-3 * np.asarray(sun, float))
    d = np.stack([s1 - s0, l1 - l0], axis=-1).mean(axis=0)
    return d / np.linalg.norm(d)


def pose_error(truth_doc, pose):
    from spctool.geometry.frames import rotvec_from_rot

    ep = -np.asarray(truth_doc["scobj"]) - pose.position
    eth = -rotvec_from_rot(np.asarray(truth_doc["rotation"]) @ pose.rotation.T)
    return np.concatenate([ep, eth])


def nees(truth_doc, pose):
    e = pose_error(truth_doc, pose)
    return float(e @ np.linalg.solve(pose.covariance, e))


def picture_figures(root, p, space, weights="uniform"):
    """Per-landmark and per-picture figures of one navigated picture (module docstring)."""
    from spctool.sim.independent import load_picture, navigate_picture
    from spctool.stages.navigate import NavigateOptions
    from spctool.stages.pose import PoseOptions, solve_pose
    from spctool.stages.register import RegisterOptions

    loaded = load_picture(root, p)
    pic, cam, photo, names, maplets, tp = loaded
    t = time.process_time()
    res = navigate_picture(loaded, NavigateOptions(register=RegisterOptions(space=space), weights=weights))
    cpu = time.process_time() - t
    reg = res.passes[-1].register
    ok = reg.ok & np.all(np.isfinite(reg.covariance), axis=(1, 2))
    pos = np.array([np.asarray(m.v, float) for m in maplets])
    e = (reg.measured - tp)[ok]
    sun_px = sun_direction_px(cam, pos[ok], pic.sz)
    pkw = dict(prior_sigma_position=pic.sigma_vso, prior_sigma_attitude=pic.sigma_ptg)
    args = (cam, pos[ok], reg.measured[ok])
    uni = solve_pose(*args, PoseOptions(), **pkw)
    sur = solve_pose(*args, PoseOptions(), pixel_covariances=reg.covariance[ok], **pkw)
    sens = res.passes[-1].sensitivity
    if sens is None:  # navigated with uniform weights: the patterns measured here
        from spctool.stages.navigate import _sensitivity

        ro = RegisterOptions(space=space)
        base = dataclasses.replace(ro, schedule="retina_s16", steps=None, fail_fast=True, cap_spacing=False)
        nkw = {"names": names, "positions": pos, "patch_cache": {}}
        p1 = res.passes[0].pose
        cam1 = cam.with_pose(scobj=p1.scobj, rotation=p1.rotation)  # pass 2 registered with it
        sens = _sensitivity(
            photo, cam1, pic.sz, maplets, tuple(pic.thrsh), base, NavigateOptions(), reg, nkw, []
        )
    modes = sens.modes[ok]
    surc = solve_pose(*args, PoseOptions(), pixel_covariances=reg.covariance[ok], error_modes=modes, **pkw)
    c_i = reg.covariance[ok] + (sur.model_error_px**2 + PoseOptions().sigma_floor_px ** 2) * np.eye(2)
    d2 = np.einsum("mi,mij,mj->m", e, np.linalg.inv(c_i), e)
    common = np.zeros((2, 2)) if surc.common_covariance is None else surc.common_covariance
    c_ic = (
        sens.landmark_covariances(reg.covariance)[ok]
        + (surc.model_error_px**2 + PoseOptions().sigma_floor_px ** 2) * np.eye(2)
        + common
    )
    d2c = np.einsum("mi,mij,mj->m", e, np.linalg.inv(c_ic), e)
    # navigate's own: its pose's model error and common part (and patterns, if it measured them)
    nav_sens = res.passes[-1].sensitivity
    d2n = np.full(e.shape[0], np.nan)
    if res.pose is not None:
        pn = res.pose
        cn = reg.covariance if nav_sens is None else nav_sens.landmark_covariances(reg.covariance)
        common_n = np.zeros((2, 2)) if pn.common_covariance is None else pn.common_covariance
        c_n = cn[ok] + (pn.model_error_px**2 + PoseOptions().sigma_floor_px ** 2) * np.eye(2) + common_n
        d2n = np.einsum("mi,mij,mj->m", e, np.linalg.inv(c_n), e)
    sc = sens.common()  # (2, k) each pattern's mean shift
    eb = e.mean(axis=0)
    return {
        "d2": d2,
        "d2c": d2c,
        "d2n": d2n,
        "common": eb,
        "along": float(eb @ sun_px),
        "sigc": float(np.sqrt(np.sum(sc * sc))),
        "tau": float(sur.model_error_px),
        "nees_uni": nees(p, uni),
        "nees_sur": nees(p, sur),
        "nees_surc": nees(p, surc),
        "nees_nav": nees(p, res.pose) if res.pose is not None else math_nan(),
        "err_uni": pose_error(p, uni),
        "err_nav": pose_error(p, res.pose) if res.pose is not None else np.full(6, np.nan),
        "status": res.status if res.pose is None else res.pose.verdict,
        "cpu_s": cpu,
        "rms": float(np.sqrt(np.mean(np.sum(e * e, axis=1)))),
    }


def math_nan():
    return float("nan")


def summarise(rows):
    d2 = np.concatenate([r["d2"] for r in rows])
    d2c = np.concatenate([r["d2c"] for r in rows])
    d2n = np.concatenate([r["d2n"] for r in rows])
    eb = np.array([r["common"] for r in rows])
    out = {
        "landmarks": int(d2.size),
        "rms_px": float(np.sqrt(np.mean([r["rms"] ** 2 for r in rows]))),
        "d2": float(np.mean(d2)),
        "cov95": float(np.mean(d2 <= 5.991)),
        "d2c": float(np.mean(d2c)),
        "cov95c": float(np.mean(d2c <= 5.991)),
        "d2n": float(np.nanmean(d2n)),
        "cov95n": float(np.nanmean(d2n <= 5.991)),
        "common_rms_px": float(np.sqrt(np.mean(np.sum(eb * eb, axis=1)))),
        "along_rms_px": float(np.sqrt(np.mean([r["along"] ** 2 for r in rows]))),
        "sigc_rms_px": float(np.sqrt(np.mean([r["sigc"] ** 2 for r in rows]))),
        "tau_mean_px": float(np.mean([r["tau"] for r in rows])),
        "cpu_s": float(sum(r["cpu_s"] for r in rows)),
    }
    for k in ("uni", "sur", "surc", "nav"):
        v = np.array([r[f"nees_{k}"] for r in rows])
        out[f"nees_{k}"] = float(np.mean(v))
        out[f"nees_{k}_over"] = int(np.sum(v > NEES_999))
    for k in ("uni", "nav"):  # rms pose error over the pictures: position (m), attitude (µrad)
        e = np.array([r[f"err_{k}"] for r in rows])
        out[f"pos_{k}_m"] = float(np.sqrt(np.nanmean(np.sum(e[:, :3] ** 2, axis=1)))) * 1e3
        out[f"att_{k}_urad"] = float(np.sqrt(np.nanmean(np.sum(e[:, 3:] ** 2, axis=1)))) * 1e6
    out["verdicts"] = {s: sum(r["status"] == s for r in rows) for s in sorted({r["status"] for r in rows})}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", default=os.path.join(os.environ.get("TMPDIR", "/tmp"), "spctool_calibration"))
    ap.add_argument("--worlds", default=",".join(WORLDS))
    ap.add_argument("--spaces", default="maplet,image")
    ap.add_argument("--weights", default="uniform", help="navigate's weights (the final registration)")
    ap.add_argument("--json", default=None)
    ap.add_argument("-v", "--verbose", action="store_true", help="one line per picture too")
    a = ap.parse_args(argv)
    results = {}
    head = (
        f"{'world':12s} {'space':6s} {'rms':>6s} {'d2':>6s} {'cov95':>6s} {'d2c':>6s} {'cov95c':>6s} "
        f"{'common':>6s} {'along':>6s} {'sigc':>6s} {'tau':>6s} {'NEESuni':>7s} {'sur':>7s} {'sur+C':>7s} "
        f"{'nav':>7s} {'>99.9':>9s} {'d2nav':>6s} {'cov95nav':>8s} {'pos_m uni/nav':>14s}"
        f" {'att_urad uni/nav':>16s} {'cpu_s':>6s}"
    )
    print(head)
    for name in a.worlds.split(","):
        root, doc = world(a.root, name)
        for space in a.spaces.split(","):
            rows = [picture_figures(root, p, space, a.weights) for p in doc["pictures"]]
            for p, r in zip(doc["pictures"] if a.verbose else [], rows):
                print(
                    f"  {p['name']} rms {r['rms']:.4f} common ({r['common'][0]:+.4f}, {r['common'][1]:+.4f})"
                    f" along {r['along']:+.4f} sigc {r['sigc']:.4f} tau {r['tau']:.4f}"
                    f" d2 {np.mean(r['d2']):.2f}"
                    f" NEES uni {r['nees_uni']:.2f} sur {r['nees_sur']:.2f} sur+C {r['nees_surc']:.2f}"
                    f" {r['status']}"
                )
            s = summarise(rows)
            results[f"{name}/{space}"] = s
            print(
                f"{name:12s} {space:6s} {s['rms_px']:6.4f} {s['d2']:6.2f} {s['cov95']:6.3f} {s['d2c']:6.2f} "
                f"{s['cov95c']:6.3f} {s['common_rms_px']:6.4f} {s['along_rms_px']:6.4f} "
                f"{s['sigc_rms_px']:6.4f} {s['tau_mean_px']:6.4f} {s['nees_uni']:7.2f} {s['nees_sur']:7.2f} "
                f"{s['nees_surc']:7.2f} {s['nees_nav']:7.2f} "
                f"{s['nees_uni_over']}/{s['nees_sur_over']}/{s['nees_surc_over']}/{s['nees_nav_over']:<3d}"
                f" {s['d2n']:6.2f} {s['cov95n']:8.3f}"
                f" {s['pos_uni_m']:6.3f}/{s['pos_nav_m']:6.3f}"
                f" {s['att_uni_urad']:7.1f}/{s['att_nav_urad']:7.1f}"
                f" {s['cpu_s']:6.1f}",
                flush=True,
            )
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    sys.exit(0 if main() is not None else 1)
