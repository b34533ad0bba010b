"""Batch runs: many pictures × the navigation stages, in local processes or on a Dask cluster.

A mission measures thousands of pictures against thousands of landmarks.  For each picture of a
PICTLIST (spc-formats.md §7.1) :func:`navigate_picture` runs the stages the way the command chain of
cli-contract.md does::

    lithos-select PIC  →  register PIC --landmarks sel  →  solve-pose PIC --measurements reg

* **select** (Stage A, :func:`spctool.stages.select.select_maplets`): the candidates of LMRKLIST.TXT
  (else LMKFILES/*.LMK) at their LMK VLM (else the MAP's V), options from INIT_LITHOS
  (:meth:`SelectOptions.from_settings`), the occlusion test when the working directory has a shape;
* **register** (Stage H): the selected landmarks, starting at their selected pixels, with the MAPFILES/
  maplets.  By default **two-pass navigation** (:func:`spctool.stages.navigate.navigate`, issue #15:
  a coarse-to-fine acquisition reaching ±25 px, a pose solve, every landmark registered again from the
  solved pose, a second pose solve), because a single pass from the a-priori pose loses pictures whose
  a-priori error exceeds its first search (SPC's AUTOREGISTER seed searches ±10 cells at spacing 2 and
  lost a whole picture with a 14 px error on the independent world, :mod:`spctool.sim.independent`).
  ``BatchOptions(two_pass=None)`` runs the single pass of :func:`spctool.stages.register.register`
  with ``register.schedule`` (default SPC's AUTOREGISTER, spc-algorithms.md §9.2–9.3, what SPC's own
  batch seeds ``make_scriptA.seed`` run);
* **solve-pose** (Stage I, :func:`spctool.stages.pose.solve_pose`): the landmarks registered ``ok`` at
  their LMK VLM, from the SUM's a-priori pose with SIGMA_VSO / SIGMA_PTG as prior (spc-algorithms.md
  §10.3).

Outputs (under ``out_dir``, SPC layout; every file written atomically, see :mod:`spctool.formats.atomic`):

* ``SUMFILES/<PIC>.SUM`` — a copy of the input SUM with the registered landmarks in its LANDMARKS section
  (new pixels for ``ok`` landmarks, added when absent, other rows kept) and, when the pose solve
  converged, the solved SCOBJ, CX, CY, CZ, SIGMA_VSO and SIGMA_PTG; every other line is byte-identical
  (``formats.sumfile`` rewrites changed lines only);
* ``TABLES/<PIC>.select.txt``, ``TABLES/<PIC>.register.txt``, ``TABLES/<PIC>.pose.txt`` — the landmark
  tables of the three stages (cli-contract.md "Landmark tables");
* ``TABLES/<PIC>.done.json`` — the done-marker, written **last**: the picture's summary row, its timings,
  the options fingerprint, the spctool version and the SHA-256 of every input the result depends on
  (:func:`picture_inputs`): its SUM, its photo, the MAP of each maplet it selected (a missing one
  too), and the shared inputs — INIT_LITHOS, LMRKLIST.TXT, every candidate's LMK (or MAP), the shape
  model.  A picture counts as done only when its marker exists and every fingerprint matches, so a
  batch interrupted at any instant resumes safely and a new photo, a changed INIT_LITHOS, LMRKLIST or
  maplet redoes the pictures it affects: a picture is redone (its old outputs, its marker and any
  temporary file a killed rename left removed first) unless ``force`` is False and it is done with
  the same options and the same inputs.  Failed pictures get no marker (they are retried);
* ``BATCH_SUMMARY.txt`` / ``BATCH_SUMMARY.json`` — the summary of the last run, written by the driver.

Status of a picture (the summary's ``status`` column): ``ok`` (pose solved and converged, SUM updated);
``no-pose: <reason>`` (the stages ran but the pose could not be solved — too few landmarks registered,
degenerate geometry or no convergence; the SUM copy holds the registered landmarks, pose unchanged;
this is a result, not a failure); ``failed: <one line>`` (the picture could not be processed — a
missing or malformed file, an internal error; nothing is marked done).  A failure never stops the
batch.

Parallelism (:func:`run_batch`) never changes a result: each picture is computed from its own input
files by the same function with fixed options (no random draws), results are collected by picture
index and the summary is in picture order, and every picture runs its numba kernels on one thread
whatever the back end (one worker = one core: more cores are used by more workers), so ``jobs=1``,
``jobs=N`` (a :class:`~concurrent.futures.ProcessPoolExecutor` of forked or spawned workers,
:func:`start_method`), a :class:`WorkerPool` kept alive across batches and a Dask cluster
(``scheduler``; ``pip install 'spctool[dask]'``; the workers must see the working and output
directories at the same paths) write byte-identical files.

Data shared by every picture — the settings, the candidate landmark geometry, the shape model and a
bounded cache of maplets — is loaded once per worker process (:class:`SharedData`), not once per
picture, and a long-lived worker (a Dask worker, a :class:`WorkerPool`) keeps it from one batch to
the next while the files it was read from are unchanged (:func:`inputs_stamp`).  One process computes
one picture at a time (a process-wide lock: several threads of one Dask worker would otherwise launch
numba's parallel kernels concurrently), so give Dask workers one thread each.

Not done here: LMK ``PICTURES`` sections are not updated — several pictures would write the same LMK
file concurrently; SPC's own batch updates them in a separate serial step.

The rooms: :mod:`spctool.batch.inputs` (options, the data shared by a worker's pictures, the input
fingerprints), :mod:`spctool.batch.picture` (one picture: the stages, its outputs, the done-marker),
:mod:`spctool.batch.driver` (the run over a PICTLIST: local processes, a kept pool, a Dask cluster),
:mod:`spctool.batch.lock` (one batch at a time per output directory), :mod:`spctool.batch.scheduler`
(a ``--scheduler`` address checked before any work).
"""

#: where each public name lives; imported on first use (PEP 562), so that ``spctool.batch.refine``
#: (``spctool geometry``) does not pay for the drivers, numba kernels and shape code of a batch
_LAZY = {
    "BatchResult": "driver",
    "WorkerPool": "driver",
    "batch_pictures": "driver",
    "run_batch": "driver",
    "start_method": "driver",
    "BatchOptions": "inputs",
    "SharedData": "inputs",
    "inputs_stamp": "inputs",
    "PictureOutcome": "picture",
    "PictureSummary": "picture",
    "done_summary": "picture",
    "navigate_picture": "picture",
    "output_paths": "picture",
    "process_picture": "picture",
    "write_outcome": "picture",
}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(f"spctool.batch.{_LAZY[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'spctool.batch' has no attribute {name!r}")


__all__ = [
    "BatchOptions",
    "BatchResult",
    "PictureOutcome",
    "PictureSummary",
    "SharedData",
    "WorkerPool",
    "batch_pictures",
    "done_summary",
    "inputs_stamp",
    "navigate_picture",
    "output_paths",
    "process_picture",
    "run_batch",
    "start_method",
    "write_outcome",
]
