"""What every stage runner shares: the output files' names, the :class:`Context` and the check
that a file was derived from the ``reference.h5`` beside it.

Part of every stage's code fingerprint (each runner imports it), so keep it small.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from forcecal.errors import DataFileError
from forcecal.h5io import reference_digest
from forcecal.scene import Scene

REFERENCE = "reference.h5"
PARAMS = "params.h5"
GRAVITY = "gravity.h5"
REPORT = "report.json"


@dataclass(frozen=True)
class Context:
    """What every stage's run function gets.

    Attributes:
        scene: the validated scene (loaded from ``scene.path``).
        out: output folder.
        progress: show progress bars (on a terminal).
        ranks: MPI ranks for a spawned FE reference (1 = in-process).
        comm: the MPI world communicator under ``mpirun`` with > 1 rank, else None.
        verbose: log every optimiser iteration of the calibration (no effect on results,
            so not part of any cache key).
        experiments: the scene's experiments the running stage uses.
        upstream: the files of ``out`` the running stage reads.
        problem: the scene's :class:`~forcecal.problem.Problem` when the running stage's
            input checks built it (the reference stage's, on rank 0): the FE ranks take it
            instead of building it again (the "cover" test points are an integer programme
            of seconds). None otherwise.
    """
    scene: Scene
    out: Path
    progress: bool
    ranks: int
    comm: Any = None
    verbose: bool = False
    experiments: tuple[str, ...] = ()
    upstream: tuple[str, ...] = ()
    problem: Any = None

    @property
    def rank(self) -> int:
        return 0 if self.comm is None else self.comm.Get_rank()

    @property
    def under_mpi(self) -> bool:
        return self.comm is not None



def check_fitted_to(reference_fingerprint: str, out: Path, what: str,
                    experiments: tuple[str, ...]) -> None:
    """Refuse a file derived from another ``reference.h5`` than the one in ``out`` (compared
    on the ``experiments`` it read: :func:`forcecal.h5io.reference_digest`)."""
    if reference_fingerprint != reference_digest(out / REFERENCE, experiments):
        raise DataFileError(f"{out / what} was computed from a different {REFERENCE} than the "
                            f"one in {out}; rerun the pipeline (or --force)")
