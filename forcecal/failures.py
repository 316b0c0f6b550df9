"""How every command of the project ends when something goes wrong: one path for every process.

:func:`run_command` wraps the body of each command line (``python -m pipelines``,
``python -m reference_fe``, ``python -m calibration``), on every MPI rank:

* any exception ends the command with **one** ``error: <cause>`` line on stderr and
  exit code :data:`EXIT_ERROR` (2), never a traceback (the traceback goes to the log
  at DEBUG, i.e. with ``--verbose``). A :class:`~forcecal.errors.ForcecalError`
  prints its message; anything else (a bug, a library's error, a full disk) is named
  by its type and message. The pipeline adds the stage and what is kept
  (:func:`note_stage`).
* Ctrl-C (SIGINT) and SIGTERM end it with ``interrupted; rerun the same command to
  resume`` and exit code 130 (SIGINT) or 143 (SIGTERM); finished work stays in the
  checkpoints.
* under MPI, an error every rank raises together (marked with :func:`collective`) is
  printed by rank 0 alone and every rank returns 2; an error one rank met alone is
  printed by that rank, which then aborts the job so no other rank waits forever.
"""
from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from typing import Callable

from forcecal.errors import ForcecalError

log = logging.getLogger(__name__)

EXIT_ERROR = 2
EXIT_INTERRUPTED = 130
INTERRUPTED = "interrupted; rerun the same command to resume"


class Interrupted(BaseException):
    """SIGTERM received (SIGINT raises KeyboardInterrupt); a BaseException like it, so
    ``except Exception`` blocks in the project do not swallow it."""

    def __init__(self, signum: int):
        super().__init__(f"signal {signum}")
        self.signum = signum


def collective(exc: BaseException) -> BaseException:
    """Mark ``exc`` as raised on every MPI rank at once (printed by rank 0 only, no abort)."""
    exc.forcecal_collective = True  # type: ignore[attr-defined]
    return exc


def note_stage(exc: BaseException, stage: str, kept: str) -> BaseException:
    """Record the pipeline stage ``exc`` ended and what it keeps for a rerun (first wins)."""
    if getattr(exc, "forcecal_stage", None) is None:
        exc.forcecal_stage = (stage, kept)  # type: ignore[attr-defined]
    return exc


def describe(exc: BaseException) -> str:
    """The one-line cause of ``exc`` as the user sees it after ``error: ``."""
    if isinstance(exc, ForcecalError):
        text = str(exc)
    elif isinstance(exc, OSError) and exc.filename is not None:
        text = f"cannot access {exc.filename}: {exc.strerror or exc}"
    elif isinstance(exc, OSError):
        text = f"input/output error: {exc.strerror or exc}"
    elif isinstance(exc, MemoryError):
        text = "out of memory (use a coarser mesh or fewer ranks)"
    else:
        text = (f"unexpected {type(exc).__name__}: {exc} (a bug in forcecal or a library it "
                "uses; --verbose logs the traceback)")
    stage = getattr(exc, "forcecal_stage", None)
    if stage is not None:
        name, kept = stage
        text += f" [stage {name}; kept: {kept}]"
    return text.replace("\n", " ")


def _rank() -> tuple[int, int]:
    """(rank, size) of this process under mpirun, from the environment (no MPI import)."""
    env = os.environ
    rank = int(env.get("OMPI_COMM_WORLD_RANK", env.get("PMI_RANK", "0")))
    size = int(env.get("OMPI_COMM_WORLD_SIZE", env.get("PMI_SIZE", "1")))
    return rank, size


def _abort(code: int) -> None:
    """Abort the MPI job if this process initialised MPI and has peers (they may wait)."""
    mpi = sys.modules.get("mpi4py.MPI")
    if mpi is not None and _rank()[1] > 1 and mpi.Is_initialized() and not mpi.Is_finalized():
        sys.stderr.flush()
        mpi.COMM_WORLD.Abort(code)


def die_with_parent() -> None:
    """Run in a child process before exec (``Popen(preexec_fn=...)``): it receives SIGTERM
    when its parent dies, even of SIGKILL (Linux PR_SET_PDEATHSIG; elsewhere nothing), so a
    killed pipeline leaves no mpirun rank or calibration worker running."""
    try:
        import ctypes
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _on_sigterm(signum, frame) -> None:
    raise Interrupted(signum)


def run_command(body: Callable[[], int]) -> int:
    """Run a command's ``body`` with the project's one failure path (module docstring)."""
    rank, size = _rank()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        return body()
    except (KeyboardInterrupt, Interrupted) as exc:
        if rank == 0:
            print(INTERRUPTED, file=sys.stderr, flush=True)
        return 128 + getattr(exc, "signum", signal.SIGINT)
    except Exception as exc:  # noqa: BLE001 - the one place every failure ends
        log.debug("the error's traceback:", exc_info=exc)
        together = getattr(exc, "forcecal_collective", False)
        if rank == 0 or not together:
            prefix = "" if rank == 0 or size <= 1 else f"[rank {rank}] "
            print(f"{prefix}error: {describe(exc)}", file=sys.stderr, flush=True)
        if not together:
            _abort(EXIT_ERROR)
        return EXIT_ERROR
