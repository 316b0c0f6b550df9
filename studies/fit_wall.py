"""Where does the gradient fit stop: at the least of its objective, or at a wall, a fitted body
load that the model one step further no longer carries?

The gradient fit (:mod:`calibration.gradient`) rejects a trial step whose model has no
static equilibrium under a whole-body load it fits (the weight along an axis perpendicular to
the scene's gravity, whose loaded state's modes are the ``loaded_modes`` data): such a model
does not carry a load it is fitted to. If the fit's steps keep running into that refusal, its
damping climbs and it ends pressed against the wall rather than at its objective's least,
and what the wall is matters more than the weights: it says what the model cannot do.

For each parameter set of a finished run (the global fit, the calibrated model, the
closed-form baseline) and each of the reference's body loads: the largest factor of the load
the model carries (:func:`carried_factor`: static equilibria of the long-term model, the
calibration's load stepping, bisection to :data:`RESOLUTION` between 0 and :data:`UPPER`).
A set that carries the fitted load (factor 1) but not ``1 + RESOLUTION`` ends *at the
wall*. At the largest load carried, what gives way (:func:`weakest_parts`): the connector
whose spring tangent ``K0 + 2 a eps + 3 b eps^2`` is lowest relative to its ``K0`` (its
strain against the experiments' strain range the run's ``params.h5`` records; with linear
springs every tangent is K0 and connector 0 is named) and the tet whose volume ratio
``V / V0`` is smallest, each with the FE's value under the whole load (the reference's load
displacement at the same vertices), and the lowest natural frequency about that state
against the one at rest.
No gravity test is read.

**Without the loads' strains** (``--without-load-strains``; reruns the calibration of the
run's reference, a few minutes on the liver): the calibration keeps every spring's tangent
above its floor on the strains where the model is used
(:func:`calibration.core.spring_validity`): the experiments', the gravity release's and,
where the fit uses the body loads, those of the FE's loaded states. Here the fit again
without the last, the rule before it, whose fits ended at the wall: a spring law left free
beyond the other strains softens where a load stretches it. Judged as the calibration judges
its own choices, on calibration data only (:func:`studies.body_stiffness_gap.fit_summary`:
the cross-validation score, the calibration and held-out curves), and by the loads each fit
carries.

``python -m studies.fit_wall --scene scenes/liver_punch.toml [--run DIR] [--out FILE]
[--without-load-strains]`` (default ``runs/studies/fit_wall_<scene name>.json``; a minute on
the liver, a few on the corpus's meshes).
"""

from __future__ import annotations

import contextlib
import logging
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

import calibration.core as calibration_core
from calibration.loading import calibrated_model
from calibration.results import read_params
from forcecal.errors import ConvergenceError, ParameterError, StabilityError
from particle.model import Model
from particle.stability import connector_strains
from particle.statics import TangentPattern, net_forces, tangent_data, weight_equilibrium
from particle.volume import signed_volumes
from studies._finished_run import finished_run, study_main
from studies.body_stiffness_gap import fit_summary

log = logging.getLogger(__name__)

#: the parameter sets of a finished run
VARIANTS = ("global", "calibrated", "baseline")
#: the bisection's resolution of the load factor [1]
RESOLUTION = 1.0 / 256.0
#: the largest load factor tried [1]
UPPER = 2.0
#: equal load increments of each static solve (each halved on failure, as the calibration's)
LOAD_STEPS = 8
#: what a static solve that finds no equilibrium raises
NO_EQUILIBRIUM = (ConvergenceError, ParameterError, StabilityError)


def equilibrium(model: Model, acceleration: np.ndarray, factor: float
                ) -> tuple[np.ndarray | None, str | None]:
    """((N, 3) positions [m] of the static equilibrium under ``factor`` times the weight
    ``m acceleration``, None), or (None, why there is none)."""
    try:
        return weight_equilibrium(model, factor * np.asarray(acceleration), LOAD_STEPS), None
    except NO_EQUILIBRIUM as exc:
        return None, f"{type(exc).__name__}: {exc}"


def carried_factor(model: Model, acceleration: np.ndarray, *, upper: float = UPPER,
                   resolution: float = RESOLUTION) -> dict[str, Any]:
    """The largest factor of the weight ``m acceleration`` [m/s^2] the model carries, to
    ``resolution`` (bisection; ``upper`` if it carries that): ``factor``, the positions
    there ``x`` (N, 3) [m], ``fails_at`` (the smallest factor found without an equilibrium,
    None) and ``failure`` (why)."""
    lo, x_lo = 0.0, model.rest_positions.copy()
    hi, failure = None, None
    for trial in (1.0, upper):
        x, why = equilibrium(model, acceleration, trial)
        if x is None:
            hi, failure = trial, why
            break
        lo, x_lo = trial, x
    while hi is not None and hi - lo > resolution:
        mid = 0.5 * (lo + hi)
        x, why = equilibrium(model, acceleration, mid)
        if x is None:
            hi, failure = mid, why
        else:
            lo, x_lo = mid, x
    return {"factor": lo, "x": x_lo, "fails_at": hi, "failure": failure}


def lowest_frequency(model: Model, x: np.ndarray) -> float:
    """The lowest natural frequency [Hz] of small motions about ``x`` (N, 3): the long-term
    tangent (its geometric part included) and the lumped masses, the support's particles
    fixed; negative (minus the root of ``-omega^2``) where the state is unstable."""
    p = model.params
    limits = (np.full(model.n_volume_elements, -np.inf), np.full(model.n_volume_elements, np.inf))
    _, tension, *_ = net_forces(model, x, p, not p.is_linear, None, None, limits)
    pattern = TangentPattern.of(model)
    data = tangent_data(model, pattern, x, tension, p, not p.is_linear, None)
    n = len(pattern.indptr) - 1
    stiffness = sp.csc_matrix((data, pattern.indices, pattern.indptr), shape=(n, n))
    scale = sp.diags(1.0 / np.sqrt(np.repeat(model.masses[model.free_nodes], 3)))
    a = scale @ (0.5 * (stiffness + stiffness.T)) @ scale
    # shift-invert about a negative shift below the lowest eigenvalue of a stable state
    omega2 = float(np.min(sla.eigsh(a.tocsc(), k=1, sigma=-1.0, which="LM",
                                    return_eigenvectors=False)))
    return float(np.sign(omega2) * np.sqrt(abs(omega2)) / (2.0 * np.pi))


def weakest_parts(model: Model, x: np.ndarray, fe_displacement: np.ndarray
                  ) -> dict[str, Any]:
    """At the model's positions ``x`` (N, 3): the connector with the lowest spring tangent
    relative to its K0 and the tet with the smallest volume ratio, with the FE's strain and
    volume ratio there under its displacement ``fe_displacement`` (N, 3) [m]."""
    p = model.params
    strain = connector_strains(model, x - model.rest_positions)
    fe_strain = connector_strains(model, fe_displacement)
    tangent = p.tangent_stiffness(strain) / p.K0
    e = int(np.argmin(tangent))
    out: dict[str, Any] = {
        "connector": e, "connector_particles": [int(v) for v in model.edges[e]],
        "connector_strain": float(strain[e]), "connector_tangent_over_K0": float(tangent[e]),
        "connector_fe_strain": float(fe_strain[e]),
        "strain_range": [float(strain.min()), float(strain.max())],
        "fe_strain_range": [float(fe_strain.min()), float(fe_strain.max())]}
    if model.n_tets:
        ratio = signed_volumes(x, model.tets) / model.rest_volumes
        fe_ratio = (signed_volumes(model.rest_positions + fe_displacement, model.tets)
                    / model.rest_volumes)
        t = int(np.argmin(ratio))
        out.update(tet=t, tet_volume_ratio=float(ratio[t]), tet_fe_volume_ratio=float(fe_ratio[t]),
                   fe_smallest_volume_ratio=float(fe_ratio.min()))
    return out


def load_row(model: Model, acceleration: np.ndarray, fe_displacement: np.ndarray,
             rest_frequency: float) -> dict[str, Any]:
    """One parameter set under one body load: :func:`carried_factor` and, at the largest
    factor carried, :func:`weakest_parts` and the lowest frequency there over the rest's."""
    carried = carried_factor(model, acceleration)
    x = carried.pop("x")
    row = {**carried, "at_the_wall": bool(carried["fails_at"] is not None
                                           and 1.0 <= carried["factor"]
                                           and carried["fails_at"] <= 1.0 + RESOLUTION),
           **weakest_parts(model, x, fe_displacement)}
    row["lowest_frequency_ratio"] = lowest_frequency(model, x) / rest_frequency
    return row


@contextlib.contextmanager
def without_load_strains():
    """Within the block, the calibration keeps springs stiff on the experiments' and the
    gravity release's strains only (:func:`calibration.core.fitted_loads` None)."""
    fitted_loads = calibration_core.fitted_loads
    calibration_core.fitted_loads = lambda scene, ref: None
    try:
        yield
    finally:
        calibration_core.fitted_loads = fitted_loads


def walls(body, params_path: Path) -> list[dict[str, Any]]:
    """The calibrated model of ``params_path`` under each load of the FE's whole-body data
    ``body``: :func:`load_row` (the largest factor carried, whether it ends at the wall, what
    gives way there)."""
    model = calibrated_model(read_params(params_path), "calibrated", params_path).model
    rest = lowest_frequency(model, model.rest_positions)
    return [load_row(model, acceleration, body.load_displacement[k], rest)
            for k, acceleration in enumerate(body.load_accelerations)]


def rule_comparison(scene_path: str | Path, done) -> dict[str, Any]:
    """The finished run ``done``'s own calibration against one without the loads' strains in
    the springs' validity, fitted to its ``reference.h5`` in a scratch folder; the loads
    each carries."""
    folder, body = done.folder, done.reference.body
    with tempfile.TemporaryDirectory() as scratch:
        params = Path(scratch) / "params.h5"
        with without_load_strains():
            result = calibration_core.calibrate(scene_path, folder / "reference.h5", params,
                                                progress=False)
        return {"own": fit_summary(done.params), "without": fit_summary(result),
                "own_carries": walls(body, folder / "params.h5"),
                "without_carries": walls(body, params)}


def study(scene_path: str | Path, run: str | Path | None, *, without: bool = False
          ) -> dict[str, Any]:
    """Every parameter set of the finished run under every body load of its reference, and
    with ``without`` the recalibration without the loads' strains (module docstring)."""
    done = finished_run(scene_path, run)
    body = done.reference.body
    if body is None or not len(body.load_accelerations):
        raise ValueError(f"{done.folder}: the reference has no whole-body loads")
    calibration_range = done.params.strain
    result: dict[str, Any] = {
        "scene": done.scene.name, "scene_file": str(scene_path), "run": str(done.folder),
        "body_data": done.scene.calibration.body_data,
        "validated_strain_range": [calibration_range.low, calibration_range.high],
        "resolution": RESOLUTION, "upper": UPPER,
        "loads": [[float(c) for c in a] for a in body.load_accelerations], "variants": {}}
    for variant in VARIANTS:
        model = calibrated_model(done.params, variant, done.folder).model
        rest = lowest_frequency(model, model.rest_positions)
        rows = []
        for k, acceleration in enumerate(body.load_accelerations):
            rows.append(load_row(model, acceleration, body.load_displacement[k], rest))
            log.info("%s, load %d: carries %.4g x (fails at %s)", variant, k,
                     rows[-1]["factor"], rows[-1]["fails_at"])
        result["variants"][variant] = {"rest_lowest_frequency_hz": rest, "loads": rows}
    if without:
        result["without_load_strains"] = rule_comparison(scene_path, done)
    return result


def main(argv: list[str] | None = None) -> int:
    return study_main("studies.fit_wall", __doc__, study, argv, switch=(
        "--without-load-strains", "without", "also recalibrate the run's reference without the "
        "fitted loads' strains in the springs' validity (the rule before it)"))


if __name__ == "__main__":
    raise SystemExit(main())
