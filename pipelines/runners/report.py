"""Runner of the ``report`` stage: ``report.json``, figures and ParaView fields."""

from __future__ import annotations

import logging

from forcecal.errors import DataFileError
from forcecal.provenance import file_digest
from pipelines.runners.common import GRAVITY, PARAMS, REFERENCE, REPORT, Context, check_fitted_to

log = logging.getLogger(__name__)


def run_report(ctx: Context) -> list[str]:
    """``report.json`` (with the verdict and the real-time check), figures and XDMF fields
    from the three upstream files (on rank 0 under MPI)."""
    if ctx.rank != 0:
        return []
    from calibration import read_params
    from calibration.loading import calibrated_model
    from forcecal.h5io import read_reference
    from pipelines.fields import write_time_series
    from pipelines.figures import write_figures
    from pipelines.gravity import read_gravity
    from pipelines.realtime import realtime_block
    from pipelines.report import build_report, write_report
    reference = read_reference(ctx.out / REFERENCE)
    params = read_params(ctx.out / PARAMS)
    check_fitted_to(params.reference_fingerprint, ctx.out, PARAMS, params.experiments)
    gravity = None
    if GRAVITY in ctx.upstream:
        gravity = read_gravity(ctx.out / GRAVITY)
        check_fitted_to(gravity.reference_fingerprint, ctx.out, GRAVITY, gravity.experiments)
        if gravity.params_fingerprint != file_digest(ctx.out / PARAMS):
            raise DataFileError(f"{ctx.out / GRAVITY} was computed from another {PARAMS}; "
                                "rerun the gravity stage")
    outputs = [REPORT]
    calibrated = calibrated_model(params, "calibrated", ctx.out / PARAMS)
    realtime = realtime_block(ctx.scene, calibrated.problem, calibrated.model)
    write_report(ctx.out / REPORT, build_report(ctx.scene.name, reference, params, gravity,
                                                ctx.scene.experiments, goals=ctx.scene.verdict,
                                                realtime=realtime))
    if ctx.scene.outputs.figures:
        written = write_figures(ctx.out / "figures", reference, params, gravity)
        outputs += [str(p.relative_to(ctx.out)) for p in written]
    if ctx.scene.outputs.fields and gravity is not None and gravity.time is None:
        log.info("report: no ParaView fields (they show the dynamic release, which the "
                 "scene's experiments do not include)")
    elif ctx.scene.outputs.fields and gravity is not None:
        mesh = reference.problem.mesh
        fe = reference.gravity
        series = [("gravity_fe.xdmf", fe.time, fe.displacement, fe.static_displacement)]
        particle = gravity.models.get("calibrated")
        if particle is not None and particle.displacement is not None:
            series.append(("gravity_particle.xdmf", gravity.time, particle.displacement,
                           particle.static_displacement))
        else:  # what exists is written: the FE's
            log.info("report: no particle field: the calibrated model's release did not "
                     "complete (report.json failures)")
        for name, times, u, static in series:
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
