"""The pipeline: reference -> calibrate -> gravity -> report, each stage cached by content.

A :class:`Stage` declares what it reads (scene sections, the mesh, upstream
files of the output folder, the code of its runner) and how it runs (its
runner, one module per stage in :mod:`pipelines.runners`);
:func:`run_pipeline` brings the requested stage and every stage before it up to
date, skipping those whose :class:`~pipelines.cache.StageInputs` and outputs
match their cache record (``<out>/cache/<stage>.json``), and says why each one
ran or was skipped.

Outputs in ``<out>/``: ``reference.h5`` (FE), ``params.h5`` (calibration),
``gravity.h5`` (particle gravity runs), ``report.json``, ``figures/*.png``,
``gravity_fe.xdmf`` / ``gravity_particle.xdmf`` (+ their ``.h5``).

Experiments: every stage reads only the experiments of the scene's
``experiments`` list it uses (:attr:`Stage.experiments`); they, the scene
sections they need and the part of ``reference.h5`` that holds them
(:func:`forcecal.h5io.reference_digest`) are its cache key, so adding an
experiment reruns only the stages that use it (the FE stage computes only its
work items), and a stage with none of its experiments in the list does not
run. A ``reference.h5`` holding more experiments than the scene asks for is
kept as it is (:func:`pipelines.runners.reference.adopt_reference`): removing
an experiment recomputes nothing upstream. When the FE gravity test failed, the
stages after the reference run as for a scene without the gravity experiments
(:func:`pipelines.runners.reference.scene_after_reference`).

MPI: run as ``mpirun -n K python -m pipelines ...``, rank 0 decides what to run
and broadcasts it; the FE reference spreads its work items over every rank,
the calibration uses ranks 1..K-1 as its workers, the other stages run on
rank 0. Outside MPI the reference is spawned as ``mpirun -n <ranks> python -m
reference_fe`` (``--ranks``, default 2) when ``mpirun`` exists, else computed
in-process.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from calibration.reach import check_experiment_depths
from forcecal.cost import check_cost
from forcecal.errors import DataFileError, SceneError
from forcecal.failures import collective, note_stage
from forcecal.h5io import reference_digest
from forcecal.problem import build_problem, check_second_support, load_mesh
from forcecal.provenance import STAGE_CODE, CodeDependencies, file_digest
from forcecal.scene import EXPERIMENTS, HELD_OUT_EXPERIMENTS, Scene
from forcecal.sections import FIT_SECTIONS, REFERENCE_SECTIONS
from pipelines.cache import Cache, StageInputs
from pipelines.runners.calibrate import run_calibrate
from pipelines.runners.common import GRAVITY, PARAMS, REFERENCE, Context
from pipelines.runners.gravity import run_gravity_stage
from pipelines.runners.reference import adopt_reference, run_reference, scene_after_reference
from pipelines.runners.report import run_report

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Stage:
    """One cached step of the pipeline.

    Attributes:
        name: CLI name.
        sections: scene sections it reads ("name": the scene's name).
        code: the code its outputs depend on, declared in
            :data:`forcecal.provenance.STAGE_CODE` (its runner and what it runs); that code
            is part of its cache key, nothing else: not this module.
        upstream: files of the output folder it reads.
        run: ``run(ctx) -> output file names`` (relative to ``ctx.out``); called on every
            rank under MPI, returns the outputs on rank 0.
        reads_mesh: the stage builds the mesh itself (its fingerprint is an input).
        experiments: the experiments it uses when the scene lists them; it does not run
            when the scene lists none of them.
    """
    name: str
    sections: tuple[str, ...]
    code: CodeDependencies
    upstream: tuple[str, ...]
    run: Callable[[Context], list[str]]
    reads_mesh: bool = False
    experiments: tuple[str, ...] = EXPERIMENTS

    def used(self, scene: Scene) -> tuple[str, ...]:
        """The experiments of ``scene`` this stage uses."""
        return tuple(e for e in scene.experiments if e in self.experiments)

    def upstream_files(self, scene: Scene) -> tuple[str, ...]:
        """The upstream files it reads for ``scene`` (no ``gravity.h5`` without gravity)."""
        return tuple(n for n in self.upstream
                     if n != GRAVITY or any(e in HELD_OUT_EXPERIMENTS
                                            for e in scene.experiments))

    def inputs(self, ctx: Context, checked: dict[str, Any] | None = None) -> StageInputs:
        """Fingerprints of everything this stage reads, now; the problem its checks built (a
        stage that reads the mesh) goes to ``checked["problem"]``."""
        used = self.used(ctx.scene)
        for name in self.upstream_files(ctx.scene):
            if not (ctx.out / name).is_file():
                raise DataFileError(f"stage {self.name} needs {ctx.out / name}, which does not "
                                    "exist")
        # an experiment's own section is read only when the experiment runs
        skipped = {"relaxation": "relaxation" not in used,
                   "gravity": not any(e in HELD_OUT_EXPERIMENTS or e == "body" for e in used),
                   "body": "body" not in used,
                   "second_support": "second_support" not in used}
        # "name" stands for the scene's top-level name (written into the report)
        scene = {s: (hashlib.sha256(ctx.scene.name.encode()).hexdigest() if s == "name"
                     else ctx.scene.fingerprint(s)) for s in self.sections
                 if not skipped.get(s, False)}
        scene["experiments"] = hashlib.sha256(json.dumps(used).encode()).hexdigest()
        code = self.code.digests()
        mesh = None
        if self.reads_mesh:  # the first stage: absurd work is refused before any is done
            mesh = load_mesh(ctx.scene)
            check_cost(ctx.scene, mesh.n_vertices, len(mesh.edges))
            # and depths the calibration would refuse after the FE (the linear network's),
            # and a second support that does not hold the body
            problem = build_problem(ctx.scene, mesh)
            check_experiment_depths(ctx.scene, problem)
            if ctx.scene.runs("second_support"):
                check_second_support(ctx.scene, problem)
            if checked is not None:
                checked["problem"] = problem
        return StageInputs(scene=scene,
                           mesh=mesh.fingerprint() if mesh is not None else None,
                           # of reference.h5, only the experiments it uses
                           upstream={n: (reference_digest(ctx.out / n, used) if n == REFERENCE
                                         else file_digest(ctx.out / n))
                                     for n in self.upstream_files(ctx.scene)},
                           code=code)


STAGES: dict[str, Stage] = {s.name: s for s in (
    Stage("reference", REFERENCE_SECTIONS,
          STAGE_CODE["reference"], (), run_reference, reads_mesh=True),
    # [particle]: the model fitted (volume) and the explicit gravity run of its gravity check
    # (dt, dt_safety, strain_margin, damping); [gravity] and the FE sag and release times of
    # reference.h5: that check and the release strain range the springs are kept stiff on
    # [body]: the load steps of the whole-body loads it fits (the experiment "body")
    Stage("calibrate", FIT_SECTIONS + ("gravity", "particle", "body"),
          STAGE_CODE["calibrate"], (REFERENCE,), run_calibrate,
          experiments=("indentation", "relaxation", "gravity_static", "gravity_dynamic",
                       "body")),
    # the gravity test and the second support's (its clamp is read from reference.h5)
    Stage("gravity", ("material", "gravity", "particle"), STAGE_CODE["gravity"],
          (REFERENCE, PARAMS), run_gravity_stage, experiments=HELD_OUT_EXPERIMENTS),
    # [verdict]: the goals the report judges against (a change reruns this stage alone);
    # [particle], [material], [indentation]: the real-time check's haptic session and drag
    Stage("report", ("name", "outputs", "verdict", "particle", "material", "indentation"),
          STAGE_CODE["report"], (REFERENCE, PARAMS, GRAVITY), run_report),
)}
ORDER = tuple(STAGES)


@dataclass(frozen=True)
class Outcome:
    """What happened to one stage: ``ran`` or skipped, and why (a skipped stage has no
    reasons when it is up to date, one when the scene's experiments leave it nothing to do)."""
    stage: str
    ran: bool
    reasons: tuple[str, ...]
    seconds: float


def run_pipeline(scene: Scene, out: str | Path, *, until: str = "report",
                 force: tuple[str, ...] = (), progress: bool = True,
                 ranks: int = 2, verbose: bool = False) -> list[Outcome]:
    """Bring ``until`` and every stage before it up to date in ``out``; see module docstring.

    ``force`` names stages to rerun even if their cache says they are up to date;
    ``verbose`` logs every optimiser iteration of the calibration.
    Returns one :class:`Outcome` per stage (on every MPI rank).
    """
    from calibration.pool import mpi_world

    if scene.path is None:
        raise SceneError("run_pipeline needs a scene loaded from a file (scene.path is None): "
                         "the FE stage may run in another process, which reads the file")
    unknown = sorted(set(force) - set(STAGES)) + ([until] if until not in STAGES else [])
    if unknown:
        raise ValueError(f"unknown stage(s) {unknown}; stages are {list(ORDER)}")
    ctx = Context(scene, Path(out), progress, ranks, mpi_world(), verbose)
    cache = Cache(ctx.out)
    lock = _lock_folder(ctx) if ctx.rank == 0 else None
    try:
        outcomes = []
        for stage in ORDER[:ORDER.index(until) + 1]:
            outcomes.append(_run_stage(ctx, cache, STAGES[stage], stage in force))
            if stage == "reference":  # a failed FE gravity test: the later stages skip gravity
                ctx = dataclasses.replace(ctx, scene=scene_after_reference(ctx))
        return outcomes
    finally:
        if lock is not None:
            lock.close()


LOCK = ".lock"


def _lock_folder(ctx: Context):
    """Hold ``<out>/.lock`` (an flock, released when this process ends however it ends) so
    two runs on one output folder cannot both run a stage; then delete the temporary files
    an earlier killed run left. Returns the open lock file.

    Raises:
        DataFileError: another live run holds the folder, or it cannot be created.
    """
    import fcntl
    from forcecal.h5io import remove_stale_temporaries
    try:
        ctx.out.mkdir(parents=True, exist_ok=True)
        fh = open(ctx.out / LOCK, "a+")
    except OSError as exc:
        raise DataFileError(f"cannot create the output folder {ctx.out}: "
                            f"{exc.strerror or exc}") from None
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.seek(0)
        owner = fh.read().strip() or "another process"
        fh.close()
        raise DataFileError(f"{ctx.out} is in use by another forcecal run ({owner}); wait for "
                            "it to finish (two runs on one output folder would both run its "
                            "stages)") from None
    fh.seek(0)
    fh.truncate()
    fh.write(f"pid {os.getpid()}")
    fh.flush()
    for tmp in remove_stale_temporaries(ctx.out):
        log.info("removed %s, left half-written by an interrupted run", tmp)
    return fh


def _run_stage(ctx: Context, cache: Cache, stage: Stage, force: bool) -> Outcome:
    """Check, run and record one stage (decisions made on rank 0 and broadcast)."""
    try:
        return _decide_and_run(ctx, cache, stage, force)
    except Exception as exc:
        raise note_stage(exc, stage.name, _kept(ctx, stage.name)) from None


def _kept(ctx: Context, stage: str) -> str:
    """What a failed ``stage`` leaves for a rerun (the error line says it)."""
    kept = [n for n in (REFERENCE, PARAMS, GRAVITY) if (ctx.out / n).is_file()]
    parts = ctx.out / f"{REFERENCE}.parts"
    if stage == "reference" and parts.is_dir() and any(parts.glob("*.npz")):
        kept.append(f"finished FE work items in {parts}/")
    checkpoints = ctx.out / "checkpoints"
    if stage == "calibrate" and checkpoints.is_dir() and any(checkpoints.iterdir()):
        kept.append(f"the calibration checkpoint in {checkpoints}/")
    return (", ".join(kept) + "; rerun the same command to resume") if kept else "nothing"


def _decide_and_run(ctx: Context, cache: Cache, stage: Stage, force: bool) -> Outcome:
    if not stage.used(ctx.scene):
        log.info("%-9s not run: the scene's experiments %s include none of %s", stage.name,
                 list(ctx.scene.experiments), list(stage.experiments))
        # skipped (ran False); the reason is what the command line prints for it
        return Outcome(stage.name, False, ("none of its experiments in the scene's list",), 0.0)
    inputs, reasons, error, checked = None, [], None, {}
    if ctx.rank == 0:
        try:
            inputs = stage.inputs(ctx, checked)
            reasons = ["--force"] if force else cache.check(stage.name, inputs)
            if (reasons and not force and stage.name == "reference"
                    and adopt_reference(ctx, inputs.mesh)):
                cache.store(stage.name, inputs, [REFERENCE], 0.0, note="adopted")
                reasons = []
        except Exception as exc:  # noqa: BLE001 - raised on every rank below
            error = exc
    if ctx.comm is not None:
        reasons, error = ctx.comm.bcast((reasons, error), root=0)
    if error is not None:
        raise collective(error)
    if not reasons:
        log.info("%-9s up to date, skipped (inputs and outputs match %s)", stage.name,
                 cache.record_path(stage.name))
        return Outcome(stage.name, False, (), 0.0)
    log.info("%-9s running: %s", stage.name, "; ".join(reasons))
    t0 = time.perf_counter()
    outputs = stage.run(dataclasses.replace(ctx, experiments=stage.used(ctx.scene),
                                            upstream=stage.upstream_files(ctx.scene),
                                            problem=checked.get("problem")))
    seconds = time.perf_counter() - t0
    if ctx.rank == 0:
        cache.store(stage.name, inputs, outputs, seconds)
        log.info("%-9s done in %.1f s: %s", stage.name, seconds, ", ".join(outputs))
    if ctx.comm is not None:
        ctx.comm.barrier()
    return Outcome(stage.name, True, tuple(reasons), seconds)
