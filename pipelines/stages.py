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

Experiments: every stage reads only the experiments of the scene's
``experiments`` list it uses (:attr:`Stage.experiments`); they, the scene
sections they need and the part of ``reference.h5`` that holds them
(:func:`forcecal.h5io.reference_digest`) are its cache key, so adding an
experiment reruns only the stages that use it (the FE stage computes only its
work items), and a stage with none of its experiments in the list does not
run. A ``reference.h5`` holding more experiments than the scene asks for is
kept as it is (:func:`adopt_reference`): removing an experiment recomputes
nothing upstream.

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
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import h5py

from forcecal.errors import DataFileError, ForcecalError, SceneError
from forcecal.cost import check_cost
from forcecal.failures import INTERRUPTED, collective, die_with_parent, note_stage
from forcecal.h5io import reference_digest
from forcecal.problem import load_mesh
from forcecal.scene import EXPERIMENTS, Scene
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
        experiments: the experiments it uses when the scene lists them; it does not run
            when the scene lists none of them.
    """
    name: str
    sections: tuple[str, ...]
    code: tuple[str, ...]
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
                     if n != GRAVITY or any(e.startswith("gravity") for e in scene.experiments))

    def inputs(self, ctx: Context) -> StageInputs:
        """Fingerprints of everything this stage reads, now."""
        used = self.used(ctx.scene)
        for name in self.upstream_files(ctx.scene):
            if not (ctx.out / name).is_file():
                raise DataFileError(f"stage {self.name} needs {ctx.out / name}, which does not "
                                    "exist")
        # an experiment's own section is read only when the experiment runs
        skipped = {"relaxation": "relaxation" not in used,
                   "gravity": not any(e.startswith("gravity") for e in used)}
        # "name" stands for the scene's top-level name (written into the report)
        scene = {s: (hashlib.sha256(ctx.scene.name.encode()).hexdigest() if s == "name"
                     else ctx.scene.fingerprint(s)) for s in self.sections
                 if not skipped.get(s, False)}
        scene["experiments"] = hashlib.sha256(json.dumps(used).encode()).hexdigest()
        # this module holds every stage's runner, so it is part of every stage's code (its
        # lazy imports are not followed: each stage names the modules it runs in `code`)
        code = {**code_digests(self.code), "pipelines/stages.py": source_digest(Path(__file__))}
        mesh = None
        if self.reads_mesh:  # the first stage: absurd work is refused before any is done
            mesh = load_mesh(ctx.scene)
            check_cost(ctx.scene, mesh.n_vertices, len(mesh.edges))
        return StageInputs(scene=scene,
                           mesh=mesh.fingerprint() if mesh is not None else None,
                           # of reference.h5, only the experiments it uses
                           upstream={n: (reference_digest(ctx.out / n, used) if n == REFERENCE
                                         else file_digest(ctx.out / n))
                                     for n in self.upstream_files(ctx.scene)},
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
    rc, error = run_mpirun(cmd)
    if rc != 0:
        kept = f"finished work items are kept in {path}.parts/ and reused by a rerun"
        if error is not None:  # the ranks' own refusal, printed once by the pipeline
            raise StageFailed(f"{error} ({kept})")
        raise StageFailed(f"the FE reference failed (mpirun exit code {rc}; --verbose shows "
                          f"mpirun's own text); {kept}")
    return [REFERENCE]


#: a line of mpirun's (OpenMPI's) own text: its boxed help messages are delimited by dashes
_MPIRUN_RULE = re.compile(r"^-{20,}$")
_RANK_ERROR = re.compile(r"^(\[rank \d+\] )?error: ")
_MPIRUN_LINE = re.compile(r"^(\[[^\]\s]+:\d+\]|mpirun|Primary job|prterun)")


def run_mpirun(cmd: list[str]) -> tuple[int, str | None]:
    """Run a spawned ``mpirun`` and return (exit code, the ranks' ``error:`` message or None).

    The ranks' stderr is read line by line: their ``error: ...`` line is returned
    (the pipeline prints it once, as its own), mpirun's boilerplate goes to the log
    at DEBUG (``--verbose``), everything else (the ranks' log lines) passes through.
    mpirun runs in its own process group, is asked to die with this process
    (PR_SET_PDEATHSIG on Linux, so even a SIGKILLed pipeline ends its ranks) and is
    terminated (then killed) when this process is interrupted or fails.
    """
    error: list[str] = []
    proc = subprocess.Popen(cmd, env=mpirun_environment(), stdin=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, start_new_session=True,
                            preexec_fn=die_with_parent)

    def forward() -> None:
        boxed = False
        for raw in proc.stderr:
            line = raw.decode(errors="replace").rstrip("\n")
            if _MPIRUN_RULE.match(line.strip()):
                boxed = not boxed
                log.debug("mpirun: %s", line)
            elif _RANK_ERROR.match(line):
                error.append(_RANK_ERROR.sub("", line))
            elif (boxed or _MPIRUN_LINE.match(line) or not line.strip()
                  or line.endswith(INTERRUPTED)):  # the pipeline says it once
                log.debug("mpirun: %s", line)
            else:
                print(line, file=sys.stderr, flush=True)

    reader = threading.Thread(target=forward, name="mpirun-stderr", daemon=True)
    reader.start()
    try:
        rc = proc.wait()
    except BaseException:  # Ctrl-C, SIGTERM, a failure here: end the ranks with us
        _end_process_group(proc)
        raise
    finally:
        reader.join(timeout=5)
    return rc, (error[0] if error else None)


def _end_process_group(proc: subprocess.Popen, grace: float = 10.0) -> None:
    """SIGTERM the child's process group (mpirun and its ranks), SIGKILL after ``grace`` s."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(proc.pid, sig)
        except (ProcessLookupError, PermissionError):
            return
        try:
            proc.wait(timeout=grace)
            return
        except subprocess.TimeoutExpired:
            continue


#: variables an initialised OpenMPI job (or singleton) sets; a spawned mpirun must not see them
_INHERITED_MPI_JOB = ("PMIX_", "ORTE_", "OMPI_MCA_orte_", "OMPI_MCA_ess", "OMPI_MCA_pmix",
                      "OMPI_APP_CTX_", "OMPI_COMM_WORLD_", "OMPI_UNIVERSE_SIZE", "OMPI_FILE_LOCATION")


def mpirun_environment() -> dict[str, str]:
    """Environment of a spawned ``mpirun``: this process's, with OpenMPI allowed to run as
    root and to oversubscribe the cores (unless the caller set those variables)."""
    # an explicit copy of os.environ also leaves out what MPI, if this process initialised it
    # (e.g. dolfinx imported in-process), set in the C environment: mpirun fails with those;
    # the same variables inherited from a parent that initialised MPI (a test runner, a
    # notebook) are dropped too (mpirun is spawned only outside an MPI job)
    env = {k: v for k, v in os.environ.items() if not k.startswith(_INHERITED_MPI_JOB)}
    for k in ("OMPI_ALLOW_RUN_AS_ROOT", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM",
              "OMPI_MCA_rmaps_base_oversubscribe"):
        env.setdefault(k, "1")
    return env


def adopt_reference(ctx: Context, stage: Stage, inputs: StageInputs) -> bool:
    """Accept a ``reference.h5`` computed outside the pipeline (``python -m reference_fe``)
    or for another experiments list.

    It is adopted when it holds every experiment the scene asks for with the
    current key (:func:`reference_fe.keys.experiment_keys`: scene sections, mesh
    and FE code), whatever else it holds: a superset is kept as it is, so
    removing an experiment from the list recomputes nothing. A file without
    keys is adopted when its stored scene and mesh fingerprints equal the current
    ones and every source file the FE stage runs is older than the start of
    that computation (``created`` minus the total time it reports): such a file
    does not record the code version, so newer code means it may be stale.
    """
    from reference_fe.keys import experiment_keys
    path = ctx.out / REFERENCE
    try:
        with h5py.File(path, "r") as fh:
            a = dict(fh.attrs)
        started = (datetime.datetime.fromisoformat(a["created"]).timestamp()
                   - float(json.loads(a["timings_s"])["total"]))
        stored = json.loads(a.get("experiment_keys", "{}"))
    except (OSError, KeyError, ValueError, TypeError):  # absent, foreign or damaged: recompute
        return False
    if stored:
        keys = experiment_keys(ctx.scene, inputs.mesh)
        if any(stored.get(e) != keys[e] for e in ctx.scene.experiments):
            return False
        extra = sorted(set(stored) - set(ctx.scene.experiments))
        log.info("reference: %s already holds %s with the current keys%s: not recomputed",
                 path, ", ".join(ctx.scene.experiments),
                 f" (and {', '.join(extra)}, which the scene does not ask for)" if extra else "")
        return True
    newest_source = max(f.stat().st_mtime for f in import_closure(stage.code).values())
    if (a.get("scene_fingerprint") != ctx.scene.fingerprint(*REFERENCE_SECTIONS)
            or a.get("mesh_fingerprint") != inputs.mesh or newest_source > started):
        return False
    from forcecal.h5io import read_reference
    try:  # the content too: a NaN-filled or damaged file would fail every later stage
        read_reference(path, expect_mesh=inputs.mesh)
    except DataFileError as exc:
        raise DataFileError(f"{path} matches this scene but cannot be adopted: {exc}; delete "
                            "it or recompute it with `reference --force`") from None
    log.info("reference: adopting the existing %s (its scene and mesh fingerprints match, the "
             "FE code is older than it and its content is valid)", path)
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
    check_fitted_to(params.reference_fingerprint, ctx.out, PARAMS, params.experiments)
    used = STAGES["gravity"].used(ctx.scene)
    runs = run_gravity(ctx.scene, reference, params.connectors, params.strain.bounds,
                       reference_fingerprint=reference_digest(ctx.out / REFERENCE, used),
                       params_fingerprint=file_digest(ctx.out / PARAMS))
    write_gravity(ctx.out / GRAVITY, runs)
    return [GRAVITY]


def check_fitted_to(reference_fingerprint: str, out: Path, what: str,
                    experiments: tuple[str, ...]) -> None:
    """Refuse a file derived from another ``reference.h5`` than the one in ``out`` (compared
    on the ``experiments`` it read: :func:`forcecal.h5io.reference_digest`)."""
    if reference_fingerprint != reference_digest(out / REFERENCE, experiments):
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
    check_fitted_to(params.reference_fingerprint, ctx.out, PARAMS, params.experiments)
    gravity = None
    if GRAVITY in STAGES["report"].upstream_files(ctx.scene):
        gravity = read_gravity(ctx.out / GRAVITY)
        check_fitted_to(gravity.reference_fingerprint, ctx.out, GRAVITY, gravity.experiments)
        if gravity.params_fingerprint != file_digest(ctx.out / PARAMS):
            raise DataFileError(f"{ctx.out / GRAVITY} was computed from another {PARAMS}; "
                                "rerun the gravity stage")
    outputs = [REPORT]
    write_report(ctx.out / REPORT, build_report(ctx.scene.name, reference, params, gravity,
                                                ctx.scene.experiments))
    if ctx.scene.outputs.figures:
        written = write_figures(ctx.out / "figures", reference, params, gravity)
        outputs += [str(p.relative_to(ctx.out)) for p in written]
    if ctx.scene.outputs.fields and gravity is not None and gravity.time is None:
        log.info("report: no ParaView fields (they show the dynamic release, which the "
                 "scene's experiments do not include)")
    elif ctx.scene.outputs.fields and gravity is not None:
        mesh = reference.problem.mesh
        fe = reference.gravity
        particle = gravity.models["calibrated"]
        for name, times, u, static in (
                ("gravity_fe.xdmf", fe.time, fe.displacement, fe.static_displacement),
                ("gravity_particle.xdmf", gravity.time, particle.displacement,
                 particle.static_displacement)):
            written = write_time_series(ctx.out / name, mesh, times, u, static)
            outputs += [str(p.relative_to(ctx.out)) for p in written]
    for name in REPORT_FILES:  # left by a run with other experiments: not this scene's
        if name not in outputs:
            (ctx.out / name).unlink(missing_ok=True)
    return outputs


#: every file the report stage may write (one it did not write this time is removed)
REPORT_FILES = tuple(f"figures/{n}.png" for n in ("calibration", "held_out", "gravity_static",
                                                   "gravity_dynamic", "errors")) + tuple(
    f"gravity_{m}.{x}" for m in ("fe", "particle") for x in ("xdmf", "h5"))


STAGES: dict[str, Stage] = {s.name: s for s in (
    Stage("reference", REFERENCE_SECTIONS, ("reference_fe.__main__", "reference_fe.run"), (),
          run_reference, reads_mesh=True),
    Stage("calibrate", ("mesh", "material", "fixed", "test_points", "indentation", "relaxation",
                        "calibration", "particle"),  # particle.volume: the model fitted
          ("calibration.core", "calibration.worker"), (REFERENCE,), run_calibrate,
          experiments=("indentation", "relaxation")),
    Stage("gravity", ("material", "gravity", "particle"),
          ("pipelines.gravity", "calibration.results"),
          (REFERENCE, PARAMS), run_gravity_stage,
          experiments=("gravity_static", "gravity_dynamic")),
    Stage("report", ("name", "outputs"),
          ("pipelines.report", "pipelines.figures", "pipelines.fields"),
          (REFERENCE, PARAMS, GRAVITY), run_report),
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
    lock = _lock_folder(ctx) if ctx.rank == 0 else None
    try:
        outcomes = []
        for stage in ORDER[:ORDER.index(until) + 1]:
            outcomes.append(_run_stage(ctx, cache, STAGES[stage], stage in force))
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
    inputs, reasons, error = None, [], None
    if ctx.rank == 0:
        try:
            inputs = stage.inputs(ctx)
            reasons = ["--force"] if force else cache.check(stage.name, inputs)
            if (reasons and not force and stage.name == "reference"
                    and adopt_reference(ctx, stage, inputs)):
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
    outputs = stage.run(ctx)
    seconds = time.perf_counter() - t0
    if ctx.rank == 0:
        cache.store(stage.name, inputs, outputs, seconds)
        log.info("%-9s done in %.1f s: %s", stage.name, seconds, ", ".join(outputs))
    if ctx.comm is not None:
        ctx.comm.barrier()
    return Outcome(stage.name, True, tuple(reasons), seconds)
