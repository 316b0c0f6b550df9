"""Runner of the ``calibrate`` stage: ``reference.h5`` -> ``params.h5``."""

from __future__ import annotations

from pipelines.runners.common import PARAMS, REFERENCE, Context


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
