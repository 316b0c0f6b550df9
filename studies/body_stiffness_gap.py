"""Is the calibrated body too soft where its static sag misses, and is it the surface curves
that soften it, or the pull of the gradient fit's prior towards the global fit?

Two parts, neither reading a gravity test to choose anything:

* **From a finished run's report** (``report.json``; nothing recomputed): the relative
  errors of the lowest rest-state natural frequencies (instantaneous and long-term moduli,
  the reference's experiment ``body``) of the three parameter sets of the report: the
  global fit (fitted to the surface curves only), the calibrated model (the gradient fit
  with the whole-body data, weighted by cross-validation) and the closed-form baseline; next
  to them each set's static sag error (maximum sag against the FE's) and the sag the
  long-term modes predict: a uniform softening by ``s`` lowers every frequency by
  ``sqrt(s)`` and raises every displacement by ``1/s``, so ``mean((1 + e_i)^-2) - 1`` over
  the lowest modes (:func:`predicted_sag_error`). And the share of the mesh's vertices on
  its surface (a wall one or two tets thick has nearly all of them there, so a network has
  no interior that could stay stiff while its surface softens).
* **The levelled prior** (``--levelled``; reruns the calibration of the run's reference, a
  few minutes): the gradient fit starts from, and its prior pulls towards, the global fit
  with every stiffness (springs, arms, volume term) times the one factor that puts its rest
  frequencies closest to the FE's (:func:`rest_mode_level`, least squares of the relative
  frequency errors at both moduli; the global fit's shape, ratios and times kept), instead
  of the global fit itself. Judged as the calibration judges its own choices, on
  calibration data only: the cross-validation score of the fit (the smallest of its last
  round's grid) and the held-out force curves; the calibrated rest frequencies are given too.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

import calibration.core as calibration_core
from calibration.parametrisation import GlobalParams
from calibration.results import read_params
from forcecal.problem import load_mesh
from forcecal.scene import load_scene
from pipelines.report import CALIBRATED_VARIANTS, point_set_means
from studies._finished_run import run_folder, study_main

log = logging.getLogger(__name__)

#: the parameter sets of a report's whole-body record
VARIANTS = ("global", "calibrated", "baseline")
#: the rest-state moduli of the whole-body data
MODULI = ("instantaneous", "long_term")
#: the lowest modes the sag prediction uses (the ones a body's own weight excites most)
LOWEST = 3


def predicted_sag_error(frequency_errors: np.ndarray) -> float:
    """The static sag error a uniform stiffness error with these relative frequency errors
    ``e_i`` (model / FE - 1) gives: ``mean((1 + e_i)^-2) - 1`` [1]."""
    e = np.asarray(frequency_errors, dtype=float)
    return float(np.mean((1.0 + e) ** -2) - 1.0)


def rest_mode_level(frequency_ratios: np.ndarray) -> float:
    """The factor ``c`` on every stiffness that puts frequencies with ratios ``r_i`` (model /
    FE) closest to the FE's: frequencies scale as ``sqrt(c)``, so ``sqrt(c) = sum r_i /
    sum r_i^2`` minimises ``sum (r_i sqrt(c) - 1)^2``."""
    r = np.asarray(frequency_ratios, dtype=float)
    return float((r.sum() / (r * r).sum()) ** 2)


def levelled(glob: GlobalParams, factor: float) -> GlobalParams:
    """``glob`` with every stiffness times ``factor`` (spring, arms, volume term and its arms;
    the spring's shape ``alpha, beta`` and the relaxation times kept)."""
    return dataclasses.replace(glob, K0=glob.K0 * factor, k1=glob.k1 * factor,
                               k2=glob.k2 * factor, kv=glob.kv * factor,
                               kv1=glob.kv1 * factor, kv2=glob.kv2 * factor)


def surface_share(scene_path: str | Path) -> dict[str, float | int]:
    """The scene mesh's vertex count and the share of them on its surface."""
    mesh = load_mesh(load_scene(scene_path))
    return {"vertices": int(mesh.n_vertices),
            "surface_share": float(len(mesh.surface_vertices) / mesh.n_vertices)}


def report_rows(report: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per parameter set of the report: its rest frequency errors at both moduli, its static
    sag error and the one its lowest long-term modes predict."""
    body, gravity = report["body"], report["gravity"]
    fe_sag = gravity["fe_max_static_sag_m"]
    rows = {}
    for variant in VARIANTS:
        modes = body["variants"][variant]
        sag = gravity.get(f"{variant}_max_static_sag_m")
        rows[variant] = {
            **{f"{m}_frequency_errors": modes[m]["frequency_errors"] for m in MODULI},
            "predicted_sag_error": predicted_sag_error(
                modes["long_term"]["frequency_errors"][:LOWEST]),
            "static_sag_error": None if sag is None else sag / fe_sag - 1.0}
    return rows


@contextlib.contextmanager
def levelled_prior(record: dict[str, Any]):
    """Within the block, :func:`calibration.core.calibrate` tunes from the global fit
    levelled to the FE's rest modes (module docstring); its factor and the rest frequency
    ratios before and after go to ``record``."""
    tune = calibration_core.tune

    def levelled_tune(pool, setup, glob, body, checkpoint, **kwargs):
        ratios = rest_frequency_ratios(body.every, setup.connector_params(glob))
        factor = rest_mode_level(ratios)
        start = levelled(glob, factor)
        record.update(factor=factor, ratios_before=ratios.tolist(), ratios_after=(
            rest_frequency_ratios(body.every, setup.connector_params(start)).tolist()))
        log.info("levelled prior: every stiffness x %.4f", factor)
        return tune(pool, setup, start, body, checkpoint, **kwargs)

    calibration_core.tune = levelled_tune
    try:
        yield
    finally:
        calibration_core.tune = tune


def rest_frequency_ratios(body, params) -> np.ndarray:
    """(2 M,) model / FE ratios of the rest-state frequencies at both moduli."""
    response = body.with_kinds(("modes",)).response(params, fitted=True, jacobian=False)
    return np.concatenate([1.0 + response.modes[m].frequency_errors for m in MODULI])


def fit_summary(result) -> dict[str, Any]:
    """What the comparison reads of a calibration: its cross-validation score, its chosen
    weights and its curve errors at the calibration and the held-out points (as the report
    has them)."""
    gradient = result.gradient
    n_cal = len(result.problem.calibration)
    calibration = np.arange(len(result.problem.test_points)) < n_cal
    out = {"cv_score": float(np.min(gradient["cv_costs"][-1])),
           "smoothness_weight": gradient["weight"], "body_weight": gradient.get("body_weight")}
    for experiment in result.variants["calibrated"].errors:
        # the report's own means over the point sets
        means = point_set_means({v: result.variants[v].errors[experiment]
                                 for v in set(CALIBRATED_VARIANTS.values())},
                                CALIBRATED_VARIANTS, calibration, experiment)
        out.update({key: means[key] for key in (f"{experiment}_calibrated",
                                                f"{experiment}_held_out")})
    return out


def levelled_comparison(scene_path: str | Path, run: Path) -> dict[str, Any]:
    """The run's own calibration (its ``params.h5``) against the levelled prior's, fitted to
    the run's ``reference.h5`` in a scratch folder."""
    record: dict[str, Any] = {}
    own = read_params(run / "params.h5")
    with tempfile.TemporaryDirectory() as scratch, levelled_prior(record):
        result = calibration_core.calibrate(scene_path, run / "reference.h5",
                                            Path(scratch) / "params.h5", progress=False)
    calibrated = (result.body or {}).get("variants", {}).get("calibrated", {})
    return {**record, "own": fit_summary(own), "levelled": fit_summary(result),
            "levelled_body": {"calibrated": {m: calibrated.get(m, {}).get("frequency_errors")
                                             for m in MODULI}}}


def study(scene_path: str | Path, run: str | Path | None, *, levelled_fit: bool = False
          ) -> dict[str, Any]:
    """The report part for the run folder ``run`` of ``scene_path`` (None: ``runs/<scene
    name>``), and with ``levelled_fit`` the levelled prior's comparison (module docstring)."""
    run = run_folder(load_scene(scene_path), run)
    report = json.loads((run / "report.json").read_text())
    result = {"scene": report["scene"], "scene_file": str(scene_path), "run": str(run),
              "body_kinds": report["body"].get("kinds"),
              "body_weight": report["body"].get("weight"),
              **surface_share(scene_path), "rows": report_rows(report)}
    if levelled_fit:
        result["levelled_prior"] = levelled_comparison(scene_path, run)
    return result


def main(argv: list[str] | None = None) -> int:
    return study_main("studies.body_stiffness_gap", __doc__, study, argv, switch=(
        "--levelled", "levelled_fit", "also recalibrate the run's reference with the levelled "
        "prior"))


if __name__ == "__main__":
    raise SystemExit(main())
