"""Runner of the ``reference`` stage: the FE reference (``reference.h5``), in-process or
spawned as ``mpirun -n <ranks> python -m reference_fe``, the adoption of a
``reference.h5`` that already holds what the scene asks for, and the scene the later
stages run (:func:`scene_after_reference`: without the gravity experiments when the FE
gravity test failed)."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import threading

import h5py

from forcecal.errors import DataFileError, ForcecalError
from forcecal.failures import INTERRUPTED, die_with_parent, note_stage
from forcecal.h5io import atomic_path, write_problem
from forcecal.scene import GRAVITY_EXPERIMENTS, Scene
from pipelines.runners.common import REFERENCE, Context

log = logging.getLogger(__name__)


class StageFailed(ForcecalError):
    """A stage run in a child process (``mpirun ... reference_fe``) failed."""


def run_reference(ctx: Context) -> list[str]:
    """FE reference: in-process under MPI or with one rank, else spawned with mpirun."""
    path = ctx.out / REFERENCE
    mpirun = shutil.which("mpirun")
    if ctx.under_mpi or ctx.ranks <= 1 or mpirun is None:
        if ctx.ranks > 1 and mpirun is None and not ctx.under_mpi:
            log.warning("mpirun not found: computing the FE reference on one process")
        from reference_fe.run import compute_reference
        # under MPI only rank 0 holds the checked problem: the ranks then build it
        compute_reference(ctx.scene, None if ctx.under_mpi else ctx.problem, out_path=path,
                          progress=ctx.progress)
        return [REFERENCE]
    cmd = [mpirun, "-n", str(ctx.ranks), sys.executable, "-m", "reference_fe",
           "--scene", str(ctx.scene.path), "--out", str(path)]
    if not ctx.progress:
        cmd.append("--no-progress")
    problem_file = path.with_name(path.name + ".problem")
    if ctx.problem is not None:  # the ranks read the problem the stage's checks built
        with atomic_path(problem_file) as tmp, h5py.File(tmp, "w") as fh:
            write_problem(fh, ctx.problem)
        cmd += ["--problem", str(problem_file)]
    log.info("running %s", " ".join(cmd))
    try:
        rc, error = run_mpirun(cmd)
    finally:
        problem_file.unlink(missing_ok=True)
    if rc != 0:
        parts = path.with_name(path.name + ".parts")
        # only when there are finished items: a refusal before any work kept nothing
        kept = (f"finished work items are kept in {parts}/ and reused by a rerun"
                if parts.is_dir() and any(parts.glob("*.npz")) else "")
        if error is not None:  # the ranks' own refusal, printed once by the pipeline
            raise StageFailed(f"{error} ({kept})" if kept and "kept in" not in error
                              else error)
        # 128 + 9: a rank was sent SIGKILL, on Linux most often by the out-of-memory killer
        killed = ("; 137 is a rank killed (SIGKILL), most often for want of memory: fewer "
                  "ranks (--ranks) or a smaller fe.local_refine need less" if rc == 137 else "")
        raise StageFailed(f"the FE reference failed (mpirun exit code {rc}{killed}; --verbose "
                          "shows mpirun's own text)" + (f"; {kept}" if kept else ""))
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


def adopt_reference(ctx: Context, mesh_fingerprint: str) -> bool:
    """Accept a ``reference.h5`` computed outside the pipeline (``python -m reference_fe``)
    or for another experiments list, deciding from fingerprints and content only.

    It is adopted when it holds every experiment the scene asks for with the
    current key (:func:`reference_fe.keys.experiment_keys`: scene sections, mesh
    and FE code fingerprints), or records its failure with that key (a failed FE gravity
    test, ``failed_experiment_keys``), and its content reads back valid, whatever else
    it holds: a superset is kept as it is, so removing an experiment from the
    list recomputes nothing. A file without keys does not record the FE code
    that computed it, so it is never adopted (it is recomputed).

    Raises:
        DataFileError: the keys match but the content is not valid (NaN, damaged).
    """
    from forcecal.h5io import read_reference
    from reference_fe.keys import experiment_keys
    path = ctx.out / REFERENCE
    try:
        with h5py.File(path, "r") as fh:
            stored = json.loads(fh.attrs.get("experiment_keys", "{}"))
    except (OSError, ValueError, TypeError):  # absent, foreign or damaged: recompute
        return False
    if not stored:
        log.info("reference: %s records no experiment keys (the FE code that computed it is "
                 "unknown): recomputed", path)
        return False
    keys = experiment_keys(ctx.scene, mesh_fingerprint)
    with h5py.File(path, "r") as fh:  # a failed gravity test counts as computed with its key
        failed = json.loads(fh.attrs.get("failed_experiment_keys", "{}"))
    if any(keys[e] not in (stored.get(e), failed.get(e)) for e in ctx.scene.experiments):
        return False
    try:  # the content too: a NaN-filled or damaged file would fail every later stage
        read_reference(path, expect_mesh=mesh_fingerprint)
    except DataFileError as exc:
        # nothing of it is reused: the stage's "kept" note must not offer it for a resume
        raise note_stage(DataFileError(
            f"{path} matches this scene but cannot be adopted: {exc}; delete it or recompute "
            "it with `reference --force`"), "reference", "nothing") from None
    extra = sorted(set(stored) - set(ctx.scene.experiments))
    log.info("reference: %s already holds %s with the current keys%s: not recomputed",
             path, ", ".join(ctx.scene.experiments),
             f" (and {', '.join(extra)}, which the scene does not ask for)" if extra else "")
    return True


def scene_after_reference(ctx: Context) -> Scene:
    """The scene the stages after the reference run: the scene's, less the gravity
    experiments when the FE gravity test failed (``reference.h5`` records it in
    ``fe_failures.gravity``) and less ``second_support`` when the second support's FE test
    did (``fe_failures.second_support``): the calibration, the gravity stage and the report
    then skip those parts as for a scene without them, and the report says why they were not
    run. The scene itself when ``reference.h5`` is absent or records no such failure."""
    from forcecal.fe_failures import FEFailures
    path = ctx.out / REFERENCE
    try:
        with h5py.File(path, "r") as fh:
            failures = FEFailures.from_json(fh.attrs.get("fe_failures"), str(path))
    except (OSError, DataFileError):  # absent (a later stage says so) or damaged
        return ctx.scene
    left_out = set()
    for failure, kinds, what in ((failures.gravity, GRAVITY_EXPERIMENTS, "gravity"),
                                 (failures.second_support, ("second_support",),
                                  "second support's")):
        if failure is not None and any(e in kinds for e in ctx.scene.experiments):
            left_out.update(kinds)
            log.warning("the FE %s test failed (%s: %s): %s not run; the other experiments "
                        "are", what, failure["experiment"], failure["reason"],
                        " and ".join(k for k in kinds if ctx.scene.runs(k)))
    if not left_out:
        return ctx.scene
    kept = tuple(e for e in ctx.scene.experiments if e not in left_out)
    return dataclasses.replace(ctx.scene, experiments=kept)
