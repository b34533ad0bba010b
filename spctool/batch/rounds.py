"""SPC's cycle in a batch: measure every picture → refine the map (GEOMETRY) → measure again.

map-refinement.md §1 "Batch" and S16 Fig. 3: measuring is per picture and parallel (:func:`spctool.
batch.run_batch`, local workers or Dask); the landmark/pose refinement is one reduction over all the
measurements (:func:`spctool.stages.bundle.solve_bundle` through :mod:`spctool.batch.refine`).  The
input working directory is never written: each refined map is a working directory of its own under
``--out-dir``:

    OUT/ROUND1/         the first measuring batch (SUMFILES/, TABLES/, BATCH_SUMMARY.*) on WORKDIR
    OUT/MAP2/           WORKDIR refined from ROUND1: SUMFILES/ (the batch's SUMs, refined poses),
                        LMKFILES/ and MAPFILES/ (refined VLMs and headers; real files), GEOMETRY.json;
                        every other entry of WORKDIR (IMAGEFILES, SHAPEFILES, INIT_LITHOS.TXT, the
                        lists, ...) a symbolic link to it
    OUT/ROUND2/         the second batch, on OUT/MAP2
    ...

With ``lithos`` the refinement goes on, as SPC's cycle does, with the maplets' heights and albedo
(:mod:`spctool.batch.heights`: LITHOS "Find heights" on every refined landmark, in parallel over
maplets) before the next round measures; each maplet's outcome is in ``GEOMETRY.json``.

The LMK and MAP files of a round are written once, by the reduction.  A killed run resumes: each
round's batch skips the pictures its done-markers cover, and a refined map is built in a temporary
folder renamed into place when complete (a half-built one is removed and built again), so nothing is
lost or done twice.  A refined map records what it was built from (``GEOMETRY.json``'s ``inputs``: a
digest of the working directory's SUM, LMK and MAP files, of the round's SUMs and tables, and of the
refinement's options) and is reused only while those are unchanged (``force``: never); a map built
from other inputs — a landmark moved, a round measured again, ``--lithos`` added — is built again.  A
refinement whose solve is implausible (``geometry``'s χ² gate) is not written and ends the cycle
(:class:`~spctool.errors.SpcResultError`); an inconsistent one is written and said.
The last round's outputs are the batch's result.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from spctool.errors import SpcResultError, SpcUsageError
from spctool.formats import atomic

__all__ = ["RoundsResult", "inputs_digest", "run_rounds", "refined_workdir"]

#: entries of a working directory that a refined map holds as real files (refined or rewritten)
_OWN = ("SUMFILES", "LMKFILES", "MAPFILES", "EXTFILES")


@dataclass
class RoundsResult:
    """The batch of every round and the refinement between them."""

    batches: list = field(default_factory=list)  # BatchResult per round
    refinements: list = field(default_factory=list)  # summary dict per refinement
    workdirs: list = field(default_factory=list)  # the working directory each round measured on

    @property
    def last(self):
        return self.batches[-1]


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def inputs_digest(workdir: Path, round_dir: Path, refine_kw: dict) -> str:
    """SHA-256 over what a refined map is built from: the working directory's SUM, LMK and MAP files
    (EXTFILES too) and its INIT_LITHOS.TXT, the round's SUMs and register tables (names and contents,
    in name order) and the refinement's options (``refine_kw``)."""
    h = hashlib.sha256(json.dumps(refine_kw, sort_keys=True, default=str).encode("utf-8"))
    src, rdir = Path(workdir).resolve(), Path(round_dir)
    groups = [(src / d, "*") for d in ("SUMFILES", "LMKFILES", "MAPFILES", "EXTFILES")]
    groups += [(src, "INIT_LITHOS.TXT"), (rdir / "SUMFILES", "*.SUM"), (rdir / "TABLES", "*.register.txt")]
    for folder, pattern in groups:
        if not folder.is_dir():
            continue
        for f in sorted(folder.glob(pattern)):
            if f.is_file() and not f.name.endswith(".bak"):
                h.update(f"{folder.name}/{f.name}\0".encode())
                with open(f, "rb") as fh:
                    h.update(hashlib.file_digest(fh, "sha256").digest())
    return h.hexdigest()


def refined_workdir(
    workdir: Path, round_dir: Path, target: Path, settings, refine_kw: dict, *, force: bool = False
) -> dict:
    """Build ``target`` (module docstring) from ``workdir`` and the batch output ``round_dir``; returns
    the refinement's summary (also written as ``target/GEOMETRY.json``).  A ``target`` built before from
    the same inputs (:func:`inputs_digest`) is kept, unless ``force``."""
    from spctool.batch import refine
    from spctool.formats.workdir import WorkDir
    from spctool.jsonsafe import json_safe
    from spctool.stages.bundle import BundleOptions, solve_bundle

    target = Path(target)
    digest = inputs_digest(workdir, round_dir, refine_kw)
    if not force and (target / "GEOMETRY.json").exists():
        try:
            done = json.loads((target / "GEOMETRY.json").read_text())
        except (OSError, ValueError):
            done = None
        if isinstance(done, dict) and done.get("inputs") == digest:
            return done
    tmp = target.with_name(target.name + ".partial")
    if tmp.exists():
        shutil.rmtree(tmp)  # a build killed half-way: start again
    if target.exists():
        shutil.rmtree(target)
    tmp.mkdir(parents=True)
    src = Path(workdir).resolve()
    out = target.parent.resolve()
    for entry in src.iterdir():  # the working directory's entries: links, or copies of the refined ones
        if entry.name in _OWN or entry.name.startswith("."):
            continue
        if entry.resolve() == out or entry.resolve() in out.parents:
            continue  # the output folder inside the working directory: no link back into itself
        os.symlink(entry, tmp / entry.name)
    for name in ("LMKFILES", "MAPFILES", "EXTFILES"):
        folder = src / name
        if folder.is_dir():
            (tmp / name).mkdir()
            for f in folder.iterdir():
                if f.is_file() and not f.name.endswith(".bak"):
                    _link_or_copy(f, tmp / name / f.name)
    (tmp / "SUMFILES").mkdir()
    measured = {p.name for p in (Path(round_dir) / "SUMFILES").glob("*.SUM")}
    for f in (src / "SUMFILES").glob("*.SUM"):
        origin = Path(round_dir) / "SUMFILES" / f.name if f.name in measured else f
        shutil.copy2(origin, tmp / "SUMFILES" / f.name)
    wd = WorkDir(tmp)
    inputs = refine.gather(wd, settings, tables=round_dir, **refine_kw.get("gather", {}))
    result = solve_bundle(inputs.problem, BundleOptions(**refine_kw.get("options", {})))
    if result.verdict == "implausible":  # geometry's rule: nothing written, and no round measures on it
        shutil.rmtree(tmp)
        raise SpcResultError(f"{target.name} (refined from {Path(round_dir).name}): {result.verdict_reason}; "
                             "not written, the cycle stops here")
    # new files: the hard links to the working directory's are replaced, the originals untouched
    refine.write_back(refine.updated_files(inputs, result, wd), backup=False)
    heights = None
    if refine_kw.get("lithos"):
        from spctool.batch.heights import refine_heights

        refined = [n for n, st in zip(result.landmark_names, result.landmark_status) if st == "ok"]
        heights = refine_heights(tmp, refined, jobs=int(refine_kw.get("jobs", 1)))
    summary = {
        "inputs": digest,
        "round_dir": str(round_dir),
        "pictures": len(inputs.problem.picture_names),
        "landmarks": len(inputs.problem.landmark_names),
        "landmarks_refined": sum(s == "ok" for s in result.landmark_status),
        "measurements": result.counts(),
        "reduced_chi2": result.reduced_chi2,
        "verdict": result.verdict,
        "verdict_reason": result.verdict_reason,
        "converged": result.converged,
        "warnings": list(result.warnings) + list(inputs.notes),
    }
    if heights is not None:
        summary["heights"] = heights
    atomic.write_bytes(
        tmp / "GEOMETRY.json", (json.dumps(json_safe(summary), indent=1) + "\n").encode("utf-8")
    )
    os.replace(tmp, target)
    return summary


def run_rounds(
    workdir, pictures, options, *, out_dir, rounds: int, settings=None, refine_kw=None, **batch_kw
):
    """``rounds`` batches with a refinement between each two (module docstring); ``batch_kw`` go to
    :func:`spctool.batch.run_batch` (jobs, scheduler, force, on_result, …)."""
    from spctool.batch.driver import run_batch

    if rounds < 1:
        raise SpcUsageError(f"--rounds must be at least 1, got {rounds}")
    out = Path(out_dir)
    work = Path(workdir)
    res = RoundsResult()
    for r in range(1, rounds + 1):
        rdir = out / f"ROUND{r}" if rounds > 1 else out
        res.workdirs.append(work)
        res.batches.append(run_batch(work, pictures, options, out_dir=rdir, **batch_kw))
        if r == rounds:
            break
        nxt = out / f"MAP{r + 1}"
        force = bool(batch_kw.get("force"))
        res.refinements.append(refined_workdir(work, rdir, nxt, settings, refine_kw or {}, force=force))
        work = nxt
    return res
