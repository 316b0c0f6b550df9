"""Where a calibrated model's static sag error comes from: which of its fitted changes, where.

The gradient fit of the punch scene moves every connector and every tet away from the
global fit, and the punch curves it is fitted to pin the *sum* of a spring's and its tets'
``kv`` stiffness better than either (docs/calibration.md, parameter recovery). The static sag, which no
fit sees, hangs on whatever the curves leave open. This study puts parts of the calibrated
model back to the global fit's values, nothing refitted, and measures the static sag (the
gravity stage's own Newton equilibrium on the calibrated strain range) of each mix:

* ``global``, ``calibrated``: the two models of ``params.h5``;
* ``calibrated springs, global kv`` and ``global springs, calibrated kv``: which of the two
  terms' changes moves the sag; ``global springs x K0 mean, calibrated kv``: the global
  springs scaled evenly by the calibrated ones' geometric mean (their level without their
  spread);
* ``calibrated, global below half height`` / ``above half height``: where (connector and
  tet midpoints below or above the middle of the body's extent against gravity);
* ``calibrated, global beyond d mm of the footprints``: the connectors and tets whose
  midpoints lie farther than d (:data:`DISTANCES`) from every particle a calibration point's
  indenter holds, i.e. the parts the punch curves see least;
* ``calibrated, kv x f``: every tet's kv scaled (how stiff a volume term would have to be).

Each row has the report's sag error, the *mean sag ratio*
``sum_free u_particle . g / sum_free u_FE . g`` (1 = the body hangs as far as the FE's on
average) and ``calibration_indentation_error``: the mean relative RMS error of the
indentation curves at the calibration points (the report's ``indentation_calibrated``), i.e.
what putting those values back costs against the data the fit saw; the result also has the
geometric means over connectors and tets of ``K0`` and ``kv`` calibrated / global. The
``calibrated`` row repeats the gravity stage's static sag (checked against ``gravity.h5`` to
1e-9 of its largest displacement). ``python -m studies.sag_split --scene
scenes/liver_punch.toml [--run DIR] [--out sag.json]`` (seconds on a finished run folder).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from calibration.metrics import relative_rms_error
from forcecal.errors import DataFileError, ParameterError
from forcecal.indenter import indenter_footprints
from particle.evaluators import IndentationEvaluator
from particle.model import Model, build_model, params_for
from particle.params import PARAM_NAMES, ConnectorParams
from particle.statics import gravity_static
from studies._finished_run import finished_run, parse_study, study_parser, write_result
from pipelines.report import gravity_static_error

log = logging.getLogger(__name__)

KV_FACTORS = (1.5, 2.0)
#: distances [m] from the calibration footprints beyond which ``variants`` puts back the
#: global set
DISTANCES = (0.01, 0.02, 0.03)


def split_ratios(global_params: ConnectorParams, calibrated: ConnectorParams) -> dict:
    """Geometric means of calibrated / global: ``K0`` over the connectors, ``kv`` over the
    tets (None without the volume term) [1]. Both sets with one kv per tet
    (:func:`particle.model.params_for`)."""
    out = {"K0": float(np.exp(np.mean(np.log(calibrated.K0 / global_params.K0))))}
    if calibrated.kv is None or global_params.kv is None:
        out["kv"] = None
    else:
        out["kv"] = float(np.exp(np.mean(np.log(calibrated.kv / global_params.kv))))
    return out


def mean_sag_ratio(fe: np.ndarray, particle: np.ndarray, free: np.ndarray,
                   gravity: np.ndarray) -> float:
    """``sum_free u_particle . g / sum_free u_FE . g`` for (N, 3) sags [m] [1]."""
    down = np.asarray(gravity, dtype=float) / np.linalg.norm(gravity)
    fe_total = float(fe[free] @ down @ np.ones(len(free)))
    if not fe_total > 0:
        raise DataFileError("the FE static sag does not move the free vertices along gravity")
    return float(particle[free] @ down @ np.ones(len(free))) / fe_total


def mixed(base: ConnectorParams, other: ConnectorParams, connectors: np.ndarray,
          tets: np.ndarray | None) -> ConnectorParams:
    """``base`` with the (E,) bool ``connectors`` and (T,) bool ``tets`` taken from ``other``
    (both with one kv per tet)."""
    fields = {n: np.where(connectors, getattr(other, n), getattr(base, n)) for n in PARAM_NAMES}
    if base.kv is not None and tets is not None:
        fields["kv"] = np.where(tets, other.kv, base.kv)
    return dataclasses.replace(base, **fields)


def variants(global_params: ConnectorParams, calibrated: ConnectorParams,
             connector_height: np.ndarray, tet_height: np.ndarray | None,
             kv_factors: tuple[float, ...] = KV_FACTORS,
             distances: tuple[np.ndarray, np.ndarray | None] | None = None
             ) -> dict[str, ConnectorParams]:
    """The module docstring's parameter sets; heights [m] of the connector and tet midpoints
    against gravity (the tets' None without the volume term); ``distances``: the connector
    and tet midpoints' distances [m] from the calibration footprints (None: no distance
    rows). Both sets with one kv per tet (:func:`particle.model.params_for`)."""
    if not all(f > 0 for f in kv_factors):
        raise ParameterError(f"kv factors {kv_factors} must be > 0")
    every, none = np.ones(len(connector_height), bool), np.zeros(len(connector_height), bool)
    volume = calibrated.kv is not None and tet_height is not None
    out = {"global": global_params, "calibrated": calibrated}
    if volume:
        all_tets = np.ones(len(tet_height), bool)
        out["calibrated springs, global kv"] = mixed(calibrated, global_params, none, all_tets)
        out["global springs, calibrated kv"] = mixed(calibrated, global_params, every,
                                                     ~all_tets)
        # the springs' level without their spread: the global springs scaled evenly
        level = split_ratios(global_params, calibrated)["K0"]
        out["global springs x K0 mean, calibrated kv"] = mixed(
            calibrated, dataclasses.replace(global_params, K0=level * global_params.K0,
                                            a=level * global_params.a,
                                            b=level * global_params.b), every, ~all_tets)
    lo, hi = connector_height.min(), connector_height.max()
    if volume:
        lo, hi = min(lo, tet_height.min()), max(hi, tet_height.max())
    middle = 0.5 * (lo + hi)
    for label, below in (("below", True), ("above", False)):
        side_c = (connector_height < middle) if below else (connector_height >= middle)
        side_t = None if not volume else ((tet_height < middle) if below
                                          else (tet_height >= middle))
        out[f"calibrated, global {label} half height"] = mixed(calibrated, global_params,
                                                               side_c, side_t)
    if distances is not None:
        connector_distance, tet_distance = distances
        for d in DISTANCES:
            out[f"calibrated, global beyond {1e3 * d:g} mm of the footprints"] = mixed(
                calibrated, global_params, connector_distance > d,
                None if not volume else tet_distance > d)
    if volume:
        for f in kv_factors:
            out[f"calibrated, kv x{f:g}"] = dataclasses.replace(calibrated,
                                                                 kv=calibrated.kv * f)
    return out


def sag_rows(model: Model, sets: dict[str, ConnectorParams], gravity: np.ndarray,
             fe: np.ndarray, strain_range: tuple[float, float], load_steps: int = 4
             ) -> list[dict]:
    """Static sag of ``model`` with each parameter set: rows ``label``, ``max_sag_m``,
    ``error`` (the report's sag error against ``fe`` (N, 3) [m]), ``mean_sag_ratio``, and
    ``displacement`` (N, 3) [m] for checks. ``strain_range``: where the springs are valid
    (the calibration's), as in the gravity stage."""
    rows = []
    for label, params in sets.items():
        u = gravity_static(model.with_params(params), gravity, load_steps=load_steps,
                           strain_range=strain_range)
        free = model.free_nodes
        rows.append({"label": label, "max_sag_m": float(np.linalg.norm(u, axis=1).max()),
                     "error": gravity_static_error(fe, u, free),
                     "mean_sag_ratio": mean_sag_ratio(fe, u, free, gravity),
                     "displacement": u})
        log.info("%s: max sag %.2f mm, error %.2f %%, mean sag ratio %.3f", label,
                 1e3 * rows[-1]["max_sag_m"], 100 * rows[-1]["error"],
                 rows[-1]["mean_sag_ratio"])
    return rows


def heights(points: np.ndarray, gravity: np.ndarray) -> np.ndarray:
    """Height [m] of (..., 3) points against ``gravity`` (up = -g)."""
    return -points @ (np.asarray(gravity, dtype=float) / np.linalg.norm(gravity))


def footprint_distance(points: np.ndarray, held: np.ndarray) -> np.ndarray:
    """(M,) distance [m] of each of the (M, 3) ``points`` from the nearest of the (H, 3)
    ``held`` particle positions."""
    points, held = np.asarray(points, dtype=float), np.asarray(held, dtype=float)
    return np.sqrt(((points[:, None, :] - held[None, :, :]) ** 2).sum(axis=2).min(axis=1))


def calibration_errors(problem, density: float, depths: np.ndarray, reference: np.ndarray,
                       footprints: tuple[np.ndarray, ...] | None,
                       strain_range: tuple[float, float],
                       sets: dict[str, ConnectorParams]) -> dict[str, float]:
    """Label -> mean relative RMS error of each set's indentation curves against
    ``reference`` (Pc, S) at the first Pc test points of ``problem`` (the calibration points)
    [1], with the calibration's evaluator (``footprints``: the particles the indenter holds,
    per calibration point, :func:`forcecal.indenter.indenter_footprints`; None: the point
    alone)."""
    n_cal = len(reference)
    model = build_model(problem, density, next(iter(sets.values())))
    evaluator = IndentationEvaluator(model, problem.test_points[:n_cal],
                                     problem.normals[:n_cal], depths,
                                     strain_range=strain_range, footprints=footprints)
    return {label: float(relative_rms_error(evaluator(params), reference).mean())
            for label, params in sets.items()}


def study(scene_path: str | Path, run: str | Path | None = None,
          kv_factors: tuple[float, ...] = KV_FACTORS) -> dict:
    """:func:`split_ratios` and :func:`sag_rows` of :func:`variants` on the finished run of
    ``scene_path`` (folder ``run``, default ``runs/<scene name>``)."""
    done = finished_run(scene_path, run)
    scene, ref, params, stage = done.scene, done.reference, done.params, done.gravity
    fe = done.fe_static_sag()
    gravity = np.asarray(scene.gravity.acceleration, dtype=np.float64)
    mesh = ref.problem.mesh
    # one kv per tet in both sets (the global fit's is one for all)
    glob, cal = (params_for(params.connectors[name], len(mesh.edges), len(mesh.tets))
                 for name in ("global", "calibrated"))
    problem = ref.problem
    n_cal = len(problem.calibration)
    footprints = indenter_footprints(mesh, problem.fixed, problem.test_points[:n_cal],
                                     problem.normals[:n_cal], scene.indentation.indenter,
                                     scene.indentation.radius)
    held = mesh.vertices[np.unique(np.concatenate(footprints))]
    centres = (mesh.vertices[mesh.edges].mean(axis=1), mesh.vertices[mesh.tets].mean(axis=1))
    sets = variants(glob, cal, heights(centres[0], gravity), heights(centres[1], gravity),
                    kv_factors, tuple(footprint_distance(c, held) for c in centres))
    model = build_model(ref.problem, scene.material.density, cal)
    rows = sag_rows(model, sets, gravity, fe, params.strain.bounds,
                    scene.gravity.static_load_steps)
    own = stage.models["calibrated"].static_displacement
    ours = next(r["displacement"] for r in rows if r["label"] == "calibrated")
    gap = float(np.abs(ours - own).max() / np.abs(own).max())
    if gap > 1e-9:
        raise DataFileError(f"the study's static sag differs from gravity.h5's by {gap:.3g} of "
                            "its largest displacement: not the same model")
    errors = calibration_errors(problem, scene.material.density, ref.indentation.displacement,
                                ref.indentation.force_normal[:n_cal], footprints,
                                params.strain.bounds, sets)
    for r in rows:
        r.pop("displacement")
        r["calibration_indentation_error"] = errors[r["label"]]
    return {"scene": scene.name, "fe_max_sag_m": float(np.linalg.norm(fe, axis=1).max()),
            "split": split_ratios(glob, cal), "rows": rows}


def main(argv: list[str] | None = None) -> None:
    parser = study_parser("studies.sag_split", __doc__)
    args = parse_study(parser, argv)
    result = study(args.scene, args.run)
    split = result["split"]
    kv = "-" if split["kv"] is None else f"{split['kv']:.3f}"
    print(f"{result['scene']}: calibrated / global, geometric means: K0 {split['K0']:.3f}, "
          f"kv {kv}; FE max sag {1e3 * result['fe_max_sag_m']:.2f} mm")
    print(f"{'parameters':52s} {'max sag mm':>10s} {'error %':>8s} {'mean sag ratio':>15s} "
          f"{'calibration indentation %':>26s}")
    for r in result["rows"]:
        print(f"{r['label']:52s} {1e3 * r['max_sag_m']:10.2f} {100 * r['error']:8.2f} "
              f"{r['mean_sag_ratio']:15.3f} {100 * r['calibration_indentation_error']:26.2f}")
    write_result(parser, args.out, result)


if __name__ == "__main__":
    main()
