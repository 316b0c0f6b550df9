"""Runner of the ``gravity`` stage: particle gravity runs of the calibrated and baseline models
-> ``gravity.h5``."""

from __future__ import annotations

from forcecal.h5io import reference_digest
from forcecal.provenance import file_digest
from pipelines.runners.common import GRAVITY, PARAMS, REFERENCE, Context, check_fitted_to


def run_gravity_stage(ctx: Context) -> list[str]:
    """Particle gravity runs of the calibrated and baseline models -> ``gravity.h5`` (on rank 0
    under MPI; a model that fails its test is recorded there, not an error)."""
    if ctx.rank != 0:
        return []
    from calibration import read_params
    from forcecal.h5io import check_reference_settings, read_reference
    from pipelines.gravity import run_gravity, write_gravity
    reference = read_reference(ctx.out / REFERENCE)
    # the particle runs use the scene's gravity and compare with the reference's FE runs
    check_reference_settings(reference, ctx.scene, ctx.out / REFERENCE)
    params = read_params(ctx.out / PARAMS)
    check_fitted_to(params.reference_fingerprint, ctx.out, PARAMS, params.experiments)
    fitted_to = reference_digest(ctx.out / REFERENCE, ctx.experiments)
    runs = run_gravity(ctx.scene, reference, params.connectors, params.strain.bounds,
                       reference_fingerprint=fitted_to,
                       params_fingerprint=file_digest(ctx.out / PARAMS))
    write_gravity(ctx.out / GRAVITY, runs)
    return [GRAVITY]
