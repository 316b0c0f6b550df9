"""The pipeline: reference -> calibrate -> gravity -> report, each stage cached by content.

A :class:`Stage` declares what it reads (scene sections, the mesh, upstream
files of the output folder, the code of the packages it runs) and how it runs;
:func:`run_pipeline` brings the requested stage and every stage before it up to
date, skipping those whose :class:`~pipelines.cache.StageInputs` and outputs
match their cache record (``<out>/cache/<stage>.json``), and says why each one
ran or was skipped.

Outputs in ``<out>/``: ``reference.h5`` (FE), ``params.h5`` (calibration),
``gravity.h5`` (particle gravity runs), ``report.json``, ``figures/*.png``,
``gravity_fe.xdmf`` / ``gravity_particle.xdmf`` (+ their ``.h5``).

MPI: run as ``mpirun -n K python -m pipelines ...``, rank 0 decides what to run
and broadcasts it; the FE reference spreads its work items over every rank,
the calibration uses ranks 1..K-1 as its workers, the other stages run on
rank 0. Outside MPI the reference is spawned as ``mpirun -n <ranks> python -m
reference_fe`` (``--ranks``, default 2) when ``mpirun`` exists, else computed
in-process.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import logging
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import h5py

from forcecal.errors import DataFileError, ForcecalError, SceneError
from forcecal.problem import load_mesh
from forcecal.scene import Scene
from forcecal.provenance import file_digest
from pipelines.cache import Cache, StageInputs, code_digests, import_closure, source_digest

log = logging.getLogger(__name__)

REFERENCE = "reference.h5"
PARAMS = "params.h5"
GRAVITY = "gravity.h5"
REPORT = "report.json"
# the scene sections reference_fe.run.REFERENCE_SECTIONS declares (a test keeps them equal;
# importing reference_fe.run here would import dolfinx and initialise MPI in this process)
REFERENCE_SECTIONS = ("mesh", "material", "fixed", "test_points", "indentation", "relaxation",
                      "gravity", "fe")


class StageFailed(ForcecalError):
    """A stage run in a child process (``mpirun ... reference_fe``) failed."""


@dataclass(frozen=True)
class Context:
    """What every stage's run function gets.

    Attributes:
        scene: the validated scene (loaded from ``scene.path``).
        out: output folder.
        progress: show progress bars (on a terminal).
        ranks: MPI ranks for a spawned FE reference (1 = in-process).
        comm: the MPI world communicator under ``mpirun`` with > 1 rank, else None.
        verbose: log every Nelder-Mead iteration of the calibration (no effect on results,
            so not part of any cache key).
    """
    scene: Scene
    out: Path
    progress: bool
    ranks: int
    comm: Any = None
    verbose: bool = False

    @property
    def rank(self) -> int:
        return 0 if self.comm is None else self.comm.Get_rank()

    @property
    def under_mpi(self) -> bool:
        return self.comm is not None


@dataclass(frozen=True)
class Stage:
    """One cached step of the pipeline.

    Attributes:
        name: CLI name.
        sections: scene sections it reads ("name": the scene's name).
        code: entry modules it runs; every project module they import is part of its
            cache key (:func:`pipelines.cache.code_digests`), and so is this module.
        upstream: files of the output folder it reads.
        run: ``run(ctx) -> output file names`` (relative to ``ctx.out``); called on every
            rank under MPI, returns the outputs on rank 0.
        reads_mesh: the stage builds the mesh itself (its fingerprint is an input).
    """
    name: str
    sections: tuple[str, ...]
    code: tuple[str, ...]
    upstream: tuple[str, ...]
    run: Callable[[Context], list[str]]
    reads_mesh: bool = False

    def inputs(self, ctx: Context) -> StageInputs:
        """Fingerprints of everything this stage reads, now."""
        for name in self.upstream:
            if not (ctx.out / name).is_file():
                raise DataFileError(f"stage {self.name} needs {ctx.out / name}, which does not "
                                    "exist")
        # "name" stands for the scene's top-level name (written into the report)
        scene = {s: (hashlib.sha256(ctx.scene.name.encode()).hexdigest() if s == "name"
                     else ctx.scene.fingerprint(s)) for s in self.sections}
        # this module holds every stage's runner, so it is part of every stage's code (its
        # lazy imports are not followed: each stage names the modules it runs in `code`)
        code = {**code_digests(self.code), "pipelines/stages.py": source_digest(Path(__file__))}
        return StageInputs(scene=scene,
                           mesh=load_mesh(ctx.scene).fingerprint() if self.reads_mesh else None,
                           upstream={n: file_digest(ctx.out / n) for n in self.upstream},
                           code=code)


# ---------------------------------------------------------------------------- reference

def run_reference(ctx: Context) -> list[str]:
    """FE reference: in-process under MPI or with one rank, else spawned with mpirun."""
    path = ctx.out / REFERENCE
    mpirun = shutil.which("mpirun")
    if ctx.under_mpi or ctx.ranks <= 1 or mpirun is None:
        if ctx.ranks > 1 and mpirun is None and not ctx.under_mpi:
            log.warning("mpirun not found: computing the FE reference on one process")
        from reference_fe.run import compute_reference
        compute_reference(ctx.scene, out_path=path, progress=ctx.progress)
        return [REFERENCE]
    cmd = [mpirun, "-n", str(ctx.ranks), sys.executable, "-m", "reference_fe",
           "--scene", str(ctx.scene.path), "--out", str(path)]
    if not ctx.progress:
        cmd.append("--no-progress")
    log.info("running %s", " ".join(cmd))
    rc = subprocess.run(cmd, env=mpirun_environment(), stdin=subprocess.DEVNULL).returncode
    if rc != 0:
        raise StageFailed(f"the FE reference failed (mpirun exit code {rc}); its message is "
                          "printed above. Finished work items are kept in "
                          f"{path}.parts/ and reused by a rerun")
    return [REFERENCE]


def mpirun_environment() -> dict[str, str]:
    """Environment of a spawned ``mpirun``: this process's, with OpenMPI allowed to run as
    root and to oversubscribe the cores (unless the caller set those variables)."""
    # an explicit copy of os.environ also leaves out what MPI, if this process initialised it
    # (e.g. dolfinx imported in-process), set in the C environment: mpirun fails with those
    env = dict(os.environ)
    for k in ("OMPI_ALLOW_RUN_AS_ROOT", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM",
              "OMPI_MCA_rmaps_base_oversubscribe"):
        env.setdefault(k, "1")
    return env


def adopt_reference(ctx: Context, stage: Stage, inputs: StageInputs) -> bool:
    """Accept a ``reference.h5`` computed outside the pipeline (``python -m reference_fe``).

    It is adopted when its stored scene and mesh fingerprints equal the current
    ones and every source file the FE stage runs is older than the start of
    that computation (``created`` minus the total time it reports): the file
    does not record the code version, so newer code means it may be stale.
    """
    path = ctx.out / REFERENCE
    try:
        with h5py.File(path, "r") as fh:
            a = dict(fh.attrs)
        started = (datetime.datetime.fromisoformat(a["created"]).timestamp()
                   - float(json.loads(a["timings_s"])["total"]))
    except (OSError, KeyError, ValueError, TypeError):  # absent, foreign or damaged: recompute
        return False
    newest_source = max(f.stat().st_mtime for f in import_closure(stage.code).values())
    if (a.get("scene_fingerprint") != ctx.scene.fingerprint(*REFERENCE_SECTIONS)
            or a.get("mesh_fingerprint") != inputs.mesh or newest_source > started):
        return False
    log.info("reference: adopting the existing %s (its scene and mesh fingerprints match and "
             "the FE code is older than it)", path)
    return True


# ---------------------------------------------------------------------------- calibration

def run_calibrate(ctx: Context) -> list[str]:
    """Calibration; under MPI rank 0 fits and ranks 1..K-1 evaluate test points."""
    if ctx.under_mpi and ctx.rank != 0:
        from calibration.pool import serve_mpi
        serve_mpi(ctx.comm)
        return []
    from calibration import calibrate
    calibrate(ctx.scene, ctx.out / REFERENCE, ctx.out / PARAMS, progress=ctx.progress,
              verbose=ctx.verbose)
    return [PARAMS]


# ---------------------------------------------------------------------------- gravity

def run_gravity_stage(ctx: Context) -> list[str]:
    """Particle gravity runs of the calibrated and baseline models -> ``gravity.h5``."""
    from calibration import read_params
    from forcecal.h5io import check_reference_settings, read_reference
    from pipelines.gravity import run_gravity, write_gravity
    reference = read_reference(ctx.out / REFERENCE)
    # the particle runs use the scene's gravity and compare with the reference's FE runs
    check_reference_settings(reference, ctx.scene, ctx.out / REFERENCE)
    params = read_params(ctx.out / PARAMS)
    check_fitted_to(params.reference_fingerprint, ctx.out, PARAMS)
    runs = run_gravity(ctx.scene, reference, params.connectors, params.strain.bounds,
                       reference_fingerprint=file_digest(ctx.out / REFERENCE),
                       params_fingerprint=file_digest(ctx.out / PARAMS))
    write_gravity(ctx.out / GRAVITY, runs)
    return [GRAVITY]


def check_fitted_to(reference_fingerprint: str, out: Path, what: str) -> None:
    """Refuse a file derived from another ``reference.h5`` than the one in ``out``."""
    if reference_fingerprint != file_digest(out / REFERENCE):
        raise DataFileError(f"{out / what} was computed from a different {REFERENCE} than the "
                            f"one in {out}; rerun the pipeline (or --force)")


# ---------------------------------------------------------------------------- report

def run_report(ctx: Context) -> list[str]:
    """``report.json``, figures and XDMF fields from the three upstream files."""
    from calibration import read_params
    from forcecal.h5io import read_reference
    from pipelines.fields import write_time_series
    from pipelines.figures import write_figures
    from pipelines.gravity import read_gravity
    from pipelines.report import build_report, write_report
    reference = read_reference(ctx.out / REFERENCE)
    params = read_params(ctx.out / PARAMS)
    gravity = read_gravity(ctx.out / GRAVITY)
    check_fitted_to(params.reference_fingerprint, ctx.out, PARAMS)
    check_fitted_to(gravity.reference_fingerprint, ctx.out, GRAVITY)
    if gravity.params_fingerprint != file_digest(ctx.out / PARAMS):
        raise DataFileError(f"{ctx.out / GRAVITY} was computed from another {PARAMS}; rerun "
                            "the gravity stage")
    outputs = [REPORT]
    write_report(ctx.out / REPORT, build_report(ctx.scene.name, reference, params, gravity))
    if ctx.scene.outputs.figures:
        written = write_figures(ctx.out / "figures", reference, params, gravity)
        outputs += [str(p.relative_to(ctx.out)) for p in written]
    if ctx.scene.outputs.fields:
        mesh = reference.problem.mesh
        fe = reference.gravity
        particle = gravity.models["calibrated"]
        for name, times, u, static in (
                ("gravity_fe.xdmf", fe.time, fe.displacement, fe.static_displacement),
                ("gravity_particle.xdmf", gravity.time, particle.displacement,
                 particle.static_displacement)):
            written = write_time_series(ctx.out / name, mesh, times, u, static)
            outputs += [str(p.relative_to(ctx.out)) for p in written]
    return outputs


STAGES: dict[str, Stage] = {s.name: s for s in (
    Stage("reference", REFERENCE_SECTIONS, ("reference_fe.__main__", "reference_fe.run"), (),
          run_reference, reads_mesh=True),
    Stage("calibrate", ("mesh", "material", "fixed", "test_points", "indentation", "relaxation",
                        "calibration", "particle"),  # particle.volume: the model fitted
          ("calibration.core", "calibration.worker"), (REFERENCE,), run_calibrate),
    Stage("gravity", ("material", "gravity", "particle"),
          ("pipelines.gravity", "calibration.results"),
          (REFERENCE, PARAMS), run_gravity_stage),
    Stage("report", ("name", "outputs"),
          ("pipelines.report", "pipelines.figures", "pipelines.fields"),
          (REFERENCE, PARAMS, GRAVITY), run_report),
)}
ORDER = tuple(STAGES)


@dataclass(frozen=True)
class Outcome:
    """What happened to one stage: ``ran`` or skipped, and why."""
    stage: str
    ran: bool
    reasons: tuple[str, ...]
    seconds: float


def run_pipeline(scene: Scene, out: str | Path, *, until: str = "report",
                 force: tuple[str, ...] = (), progress: bool = True,
                 ranks: int = 2, verbose: bool = False) -> list[Outcome]:
    """Bring ``until`` and every stage before it up to date in ``out``; see module docstring.

    ``force`` names stages to rerun even if their cache says they are up to date;
    ``verbose`` logs every Nelder-Mead iteration of the calibration.
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
    outcomes = []
    for stage in ORDER[:ORDER.index(until) + 1]:
        outcomes.append(_run_stage(ctx, cache, STAGES[stage], stage in force))
    return outcomes


def _run_stage(ctx: Context, cache: Cache, stage: Stage, force: bool) -> Outcome:
    """Check, run and record one stage (decisions made on rank 0 and broadcast)."""
    inputs, reasons = None, []
    if ctx.rank == 0:
        inputs = stage.inputs(ctx)
        reasons = ["--force"] if force else cache.check(stage.name, inputs)
        if reasons and not force and stage.name == "reference" and adopt_reference(ctx, stage,
                                                                                     inputs):
            cache.store(stage.name, inputs, [REFERENCE], 0.0, note="adopted")
            reasons = []
    if ctx.comm is not None:
        reasons = ctx.comm.bcast(reasons, root=0)
    if not reasons:
        log.info("%-9s up to date, skipped (inputs and outputs match %s)", stage.name,
                 cache.record_path(stage.name))
        return Outcome(stage.name, False, (), 0.0)
    log.info("%-9s running: %s", stage.name, "; ".join(reasons))
    t0 = time.perf_counter()
    outputs = stage.run(ctx)
    seconds = time.perf_counter() - t0
    if ctx.rank == 0:
        cache.store(stage.name, inputs, outputs, seconds)
        log.info("%-9s done in %.1f s: %s", stage.name, seconds, ", ".join(outputs))
    if ctx.comm is not None:
        ctx.comm.barrier()
    return Outcome(stage.name, True, tuple(reasons), seconds)
