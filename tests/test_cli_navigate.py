"""``spctool navigate``: its --help examples run as written on the shipped demo (fixtures/demo), the
JSON reports both passes, --output writes the SUM, and exit codes (1 without a pose / too few)."""

from __future__ import annotations

import json
import shlex


def _examples():
    from spctool.cli.navigate import navigate_cmd

    lines = navigate_cmd.help.split("Example:")[1].splitlines()
    return [ln.strip() for ln in lines if ln.strip().startswith("spctool ")]


def test_help_examples_run_on_the_demo(run_cli, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    examples = _examples()
    assert len(examples) >= 3 and all(ex.startswith("spctool -C demo navigate") for ex in examples)
    assert run_cli("demo", "--copy-to", "demo").exit_code == 0  # as spctool --help's first example
    for line in examples:
        res = run_cli(*shlex.split(line)[1:])
        assert res.exit_code == 0, (line, res.stderr)
    doc = json.loads((tmp_path / "demo" / "nav.json").read_text())  # -C demo: paths inside demo/
    assert len(doc["passes"]) == 2
    p1, p2 = doc["passes"]
    assert p1["found"] == p2["found"] == doc["registered"] == len(doc["landmarks"])
    assert {"sample_1", "line_1", "status_1", "residual_sample", "pose_status"} <= set(doc["landmarks"][0])
    assert p2["rms_after_px"] <= p1["rms_after_px"] + 0.005  # both passes end converged
    assert doc["pose"]["converged"] is True
    from spctool.formats.sumfile import read_sum

    new = read_sum(tmp_path / "demo" / "new.SUM")
    old = read_sum(tmp_path / "demo" / "SUMFILES" / "P000000001A1.SUM")
    assert len(new.landmarks) == p2["found"]
    assert not (new.scobj == old.scobj).all()


def test_demo_truth_is_met(run_cli, tmp_path, monkeypatch):
    """On the demo, the solved pose reproduces the true pose's landmark pixels to a fraction of a pixel,
    and pass 2 is at least as close as pass 1."""
    import numpy as np

    from spctool.formats.landmark import read_lmk
    from spctool.formats.sumfile import read_sum
    from spctool.geometry.camera import Camera

    monkeypatch.chdir(tmp_path)
    assert run_cli("demo", "--copy-to", "demo").exit_code == 0
    truth = json.loads((tmp_path / "demo" / "TRUTH.json").read_text())
    true = next(p for p in truth["pictures"] if p["name"] == "P000000001A1")["true"]
    res = run_cli("-C", "demo", "navigate", "P000000001A1", "--output", "new.SUM")
    assert res.exit_code == 0, res.stderr
    cam = Camera.from_picture(read_sum(tmp_path / "demo" / "new.SUM"))  # -C works like git -C
    true_cam = cam.with_pose(scobj=np.array(true["scobj"]), rotation=np.array(true["rotation"]))
    v = np.array([read_lmk(p).vlm for p in sorted((tmp_path / "demo" / "LMKFILES").glob("*.LMK"))])
    s1, l1, f1 = cam.project_with_mask(v)
    s0, l0, f0 = true_cam.project_with_mask(v)
    inside = f0 & f1 & (s0 > 1) & (s0 < cam.npx) & (l0 > 1) & (l0 < cam.nln)
    assert inside.sum() >= 3
    d = np.hypot(s1 - s0, l1 - l0)[inside]
    assert np.max(d) < 0.5


def test_no_landmarks_found_is_exit_1(run_cli, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert run_cli("demo", "--copy-to", "demo").exit_code == 0
    res = run_cli("-C", "demo", "navigate", "P000000001A1", "--min-landmarks", "1000")
    assert res.exit_code == 1
    assert "no-pose" in res.stderr and "Traceback" not in res.stderr


def test_calibrated_and_surface_weights_report_the_model_error_and_cover_the_truth(
    run_cli, tmp_path, monkeypatch
):
    """The default (--weights calibrated), --weights surface and uniform: the pose's 3σ holds the demo's
    true pose; calibrated keeps uniform's pose with another covariance; surface's final pass
    re-registers every landmark with the other photometric law and its maplet smoothed (the JSON's
    pass "model_error"), pass 1 does not."""
    import numpy as np

    from spctool.geometry.frames import rotvec_from_rot

    monkeypatch.chdir(tmp_path)
    assert run_cli("demo", "--copy-to", "demo").exit_code == 0
    true = next(p for p in json.loads((tmp_path / "demo" / "TRUTH.json").read_text())["pictures"]
                if p["name"] == "P000000001A1")["true"]  # fmt: skip
    poses = {}
    for weights in ("calibrated", "surface", "uniform"):
        extra = [] if weights == "calibrated" else ["--weights", weights]
        res = run_cli("-C", "demo", "navigate", "P000000001A1", *extra, "--json", "-o", f"{weights}.json")
        assert res.exit_code == 0, res.stderr
        doc = json.loads((tmp_path / "demo" / f"{weights}.json").read_text())
        p1, p2 = doc["passes"]
        assert doc["options"]["weights"] == weights and p1["model_error"] is None
        if weights != "surface":
            assert p2["model_error"] is None
        else:
            assert p2["model_error"]["patterns"] == ["photometry lambert", "heights smoothed"]
            assert p2["model_error"]["landmarks"] == [p2["found"]] * 2
        pose = poses[weights] = doc["pose"]
        e = np.concatenate(
            [
                -np.asarray(true["scobj"]) - np.asarray(pose["position"]),
                -rotvec_from_rot(np.asarray(true["rotation"]) @ np.asarray(pose["rotation"]).T),
            ]
        )
        assert np.all(np.abs(e) <= 3.0 * np.sqrt(np.diag(np.asarray(pose["covariance"])))), (weights, e)
    assert poses["calibrated"]["position"] == poses["uniform"]["position"]
    assert poses["calibrated"]["covariance"] != poses["uniform"]["covariance"]


def test_threads_give_the_same_outputs_to_the_byte(run_cli, tmp_path, monkeypatch):
    """navigate and register in maplet space with --threads 2 (landmarks shared with a forked worker)
    write what --threads 1 writes: the table byte for byte, the JSON but for its timings and the
    --threads setting it echoes."""
    import spctool.workers as wmod

    monkeypatch.setattr(wmod, "can_fork_tasks", lambda: True)  # also under pytest-xdist's threads
    monkeypatch.chdir(tmp_path)
    assert run_cli("demo", "--copy-to", "demo").exit_code == 0
    docs, tables = {}, {}
    for n in ("1", "2"):
        res = run_cli("-C", "demo", "navigate", "P000000001A1", "--json", "--threads", n)
        assert res.exit_code == 0, res.stderr
        doc = json.loads(res.stdout)
        assert doc["options"]["register"]["threads"] == int(n)
        doc["options"]["register"]["threads"] = None
        for p in doc["passes"]:
            p.pop("seconds")
        docs[n] = doc
        res = run_cli("-C", "demo", "register", "P000000001A1", "--threads", n)
        assert res.exit_code == 0, res.stderr
        tables[n] = res.stdout
    assert docs["1"] == docs["2"] and docs["1"]["registered"] >= 10
    assert tables["1"] == tables["2"] and tables["1"].count(" ok") >= 10
