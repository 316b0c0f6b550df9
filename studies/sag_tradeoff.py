"""Could the calibrated model fit its punch curves and hang like the FE at once? A diagnostic.

The sag study (:mod:`studies.sag_split`) puts parts of the calibrated model back to
the global set and finds that every mix which hangs like the FE fits the calibration curves
worse. That does not tell whether *other* values would fit them as well and hang like the
FE. This study looks for such values in a small family: the calibrated model with each of
``R`` regions (k-means of the connector midpoints; each tet joins the region of the nearest
centre) scaled by two factors, one on its springs (``K0``, ``a``, ``b``) and one on its tets'
``kv``: 2R log-factors ``x``. From ``x = 0`` (the calibrated model) each iteration takes one
Gauss-Newton step on the calibration points' indentation residuals (the report's relative
RMS errors: ``(F - F_FE) / (max|F_FE| sqrt(S))``, so the squared norm is the sum of the
points' squared errors) subject to the linearised mean sag ratio reaching 1 (the FE's; see
:func:`studies.sag_split.mean_sag_ratio`), the Jacobian by forward differences,
within a trust radius (:func:`constrained_step`).

**The FE's sag is a constraint here.** This is a measurement of what the model could do,
never a calibration: nothing in forcecal reads its result, and the held-out points and the
sag error it reports are only read. Each iteration's row: the indentation error at the
calibration and the held-out points, the mean sag ratio and the report's sag error.
``python -m studies.sag_tradeoff --scene scenes/liver_punch.toml [--run DIR]
[--regions 12] [--iterations 20] [--out tradeoff.json]`` (measured on a slow machine:
``liver_punch`` with 24 regions 7 min for 20 iterations, ``user_organ_punch`` with 12
regions 6 min for 10).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
from scipy.cluster.vq import kmeans2

from calibration.metrics import relative_rms_error
from forcecal.errors import ParameterError
from forcecal.indenter import indenter_footprints
from particle.evaluators import IndentationEvaluator
from particle.model import build_model, params_for
from particle.params import ConnectorParams
from studies._finished_run import finished_run, parse_study, study_parser, write_result
from studies.sag_split import sag_rows

log = logging.getLogger(__name__)

#: forward-difference step of the log-factors [1]
DIFFERENCE_STEP = 0.05
#: largest change of a log-factor in one iteration [1]
TRUST_RADIUS = 0.25


def regions(connector_midpoints: np.ndarray, tet_midpoints: np.ndarray | None, n: int,
            seed: int = 1) -> tuple[np.ndarray, np.ndarray | None]:
    """(E,) and (T,) region labels 0..n-1: k-means of the connector midpoints [m] (a fixed
    seed), each tet in the region of the nearest centre (None without tets)."""
    if not 1 <= n <= len(connector_midpoints):
        raise ParameterError(f"{n} regions for {len(connector_midpoints)} connectors")
    centres, labels = kmeans2(np.asarray(connector_midpoints, dtype=float), n,
                              seed=np.random.default_rng(seed), minit="++")
    if tet_midpoints is None:
        return labels, None
    distance = ((tet_midpoints[:, None, :] - centres[None, :, :]) ** 2).sum(axis=2)
    return labels, np.argmin(distance, axis=1)


def scaled(params: ConnectorParams, connector_region: np.ndarray,
           tet_region: np.ndarray | None, x: np.ndarray) -> ConnectorParams:
    """``params`` with region r's springs (K0, a, b) times ``exp(x[r])`` and its tets' kv
    times ``exp(x[R + r])`` (``x`` (2R,); one kv per tet)."""
    n = len(x) // 2
    springs = np.exp(x[:n])[connector_region]
    out = dataclasses.replace(params, K0=params.K0 * springs, a=params.a * springs,
                              b=params.b * springs)
    if params.kv is not None and tet_region is not None:
        out = dataclasses.replace(out, kv=params.kv * np.exp(x[n:])[tet_region])
    return out


def constrained_step(jacobian: np.ndarray, gradient: np.ndarray, residual: np.ndarray,
                     target: float, radius: float = TRUST_RADIUS) -> tuple[np.ndarray, float]:
    """The step d minimising ``|r + J d|^2 + mu |d|^2`` subject to ``g . d = target``, with
    the smallest ``mu`` (1e-4, x3, ...) whose step stays within ``radius`` (max norm); a
    target out of reach within the radius is halved until it is not. Returns d and the
    target it meets."""
    n = jacobian.shape[1]
    normal = jacobian.T @ jacobian
    pull = -jacobian.T @ residual
    mu = 1e-4
    while True:
        A = normal + mu * np.eye(n)
        free, along = np.linalg.solve(A, pull), np.linalg.solve(A, gradient)
        d = free + (target - gradient @ free) / (gradient @ along) * along
        if np.abs(d).max() <= radius:
            return d, target
        mu *= 3.0
        if mu > 1e3:  # no regularisation brings it within the radius: aim half as far
            mu, target = 1e-4, 0.5 * target


def study(scene_path: str | Path, run: str | Path | None = None, n_regions: int = 12,
          iterations: int = 20) -> dict:
    """The module docstring's iterations on the finished run of ``scene_path``."""
    done = finished_run(scene_path, run)
    scene, ref, result = done.scene, done.reference, done.params
    fe_sag = done.fe_static_sag()
    problem, mesh = ref.problem, ref.problem.mesh
    n_cal = len(problem.calibration)
    gravity = np.asarray(scene.gravity.acceleration, dtype=np.float64)
    calibrated = params_for(result.connectors["calibrated"], len(mesh.edges), len(mesh.tets))
    footprints = indenter_footprints(mesh, problem.fixed, problem.test_points, problem.normals,
                                     scene.indentation.indenter, scene.indentation.radius)
    model = build_model(problem, scene.material.density, calibrated)
    evaluator = IndentationEvaluator(model, problem.test_points, problem.normals,
                                     ref.indentation.displacement,
                                     strain_range=result.strain.bounds, footprints=footprints)
    fe = ref.indentation.force_normal
    scale = np.abs(fe).max(axis=1, keepdims=True) * np.sqrt(fe.shape[1])
    labels = regions(mesh.vertices[mesh.edges].mean(axis=1),
                     None if calibrated.kv is None else mesh.vertices[mesh.tets].mean(axis=1),
                     n_regions)
    n_x = 2 * n_regions if calibrated.kv is not None else n_regions

    def measure(x: np.ndarray) -> dict:
        params = scaled(calibrated, *labels, np.r_[x, np.zeros(2 * n_regions - n_x)])
        curves = evaluator(params)
        errors = relative_rms_error(curves, fe)
        sag = sag_rows(model, {"x": params}, gravity, fe_sag,
                       result.strain.bounds, scene.gravity.static_load_steps)[0]
        return {"residual": ((curves - fe) / scale)[:n_cal].ravel(),
                "indentation_calibrated": float(errors[:n_cal].mean()),
                "indentation_held_out": float(errors[n_cal:].mean()),
                "mean_sag_ratio": sag["mean_sag_ratio"], "gravity_static": sag["error"]}

    x = np.zeros(n_x)
    here = measure(x)
    rows = []
    for k in range(iterations + 1):
        rows.append({"iteration": k, **{key: v for key, v in here.items() if key != "residual"},
                     "largest_factor": float(np.exp(np.abs(x).max()))})
        log.info("iteration %d: calibration points %.2f %%, held-out %.2f %%, hangs %.3fx, "
                 "sag error %.2f %%", k, 100 * here["indentation_calibrated"],
                 100 * here["indentation_held_out"], here["mean_sag_ratio"],
                 100 * here["gravity_static"])
        if k == iterations:
            break
        columns, slopes = [], []
        for i in range(n_x):
            moved = measure(x + DIFFERENCE_STEP * np.eye(n_x)[i])
            columns.append((moved["residual"] - here["residual"]) / DIFFERENCE_STEP)
            slopes.append((moved["mean_sag_ratio"] - here["mean_sag_ratio"]) / DIFFERENCE_STEP)
        step, _ = constrained_step(np.array(columns).T, np.array(slopes), here["residual"],
                                   1.0 - here["mean_sag_ratio"])
        x = x + step
        here = measure(x)
    return {"scene": scene.name, "regions": n_regions, "coordinates": n_x,
            "difference_step": DIFFERENCE_STEP, "trust_radius": TRUST_RADIUS, "rows": rows}


def main(argv: list[str] | None = None) -> None:
    parser = study_parser("studies.sag_tradeoff", __doc__)
    parser.add_argument("--regions", type=int, default=12, help="k-means regions (default 12)")
    parser.add_argument("--iterations", type=int, default=20, help="default 20")
    args = parse_study(parser, argv)
    # the sag study logs every set it measures: here that is every finite difference
    logging.getLogger("studies.sag_split").setLevel(logging.WARNING)
    result = study(args.scene, args.run, args.regions, args.iterations)
    print(f"{'iteration':>9s} {'calibration %':>13s} {'held-out %':>10s} {'hangs':>6s} "
          f"{'sag error %':>11s}")
    for r in result["rows"]:
        print(f"{r['iteration']:9d} {100 * r['indentation_calibrated']:13.2f} "
              f"{100 * r['indentation_held_out']:10.2f} {r['mean_sag_ratio']:6.3f} "
              f"{100 * r['gravity_static']:11.2f}")
    write_result(parser, args.out, result)


if __name__ == "__main__":
    main()
