"""Where a calibrated model's static sag error comes from: the split between springs and kv.

The gradient fit of the punch scene moves every connector and every tet from the
global fit, and the punch curves it is fitted to pin the *sum* of a spring's and
its tets' ``kv`` stiffness better than either (README, parameter recovery). The
static sag, which no fit sees, depends on the split: the body hangs mostly in
shear, which the springs carry, while a punch also compresses the tissue under
it, which ``kv`` resists. This study measures, on a finished run folder,
nothing refitted:

* the split: the geometric mean over connectors of ``K0`` calibrated / global
  and over tets of ``kv`` calibrated / global;
* the static sag (the gravity stage's own Newton equilibrium) of the global and
  the calibrated model, each with ``kv`` as fitted and scaled by a few factors:
  the sag error of the report and the *mean sag ratio*
  ``sum_free u_particle . g / sum_free u_FE . g`` (1 = the body hangs as far as
  the FE's on average).

The first calibrated row repeats the gravity stage's static sag (checked against
``gravity.h5`` to 1e-9 of its largest displacement). Not a bench item (seconds on
a finished run folder): ``python -m pipelines.bench.sag_split --scene
scenes/liver_punch.toml [--run DIR] [--out sag.json]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
from pathlib import Path

import numpy as np

from forcecal.errors import DataFileError, ParameterError
from forcecal.h5io import read_reference
from forcecal.scene import load_scene
from particle.model import Model, build_model
from particle.params import ConnectorParams
from particle.statics import gravity_static
from pipelines.report import gravity_static_error

log = logging.getLogger(__name__)

KV_FACTORS = (1.0, 1.5, 2.0, 3.0)


def _per_item(values: np.ndarray, n: int) -> np.ndarray:
    """(n,) values from a (1,) global value or an (n,) array."""
    values = np.asarray(values, dtype=float)
    return np.broadcast_to(values, (n,)) if values.shape == (1,) else values


def split_ratios(global_params: ConnectorParams, calibrated: ConnectorParams) -> dict:
    """Geometric means of calibrated / global: ``K0`` over the connectors, ``kv`` over the
    tets (None without the volume term) [1]."""
    out = {"K0": float(np.exp(np.mean(np.log(calibrated.K0 / global_params.K0))))}
    if calibrated.kv is None or global_params.kv is None:
        out["kv"] = None
    else:
        n = max(len(calibrated.kv), len(global_params.kv))
        ratio = _per_item(calibrated.kv, n) / _per_item(global_params.kv, n)
        out["kv"] = float(np.exp(np.mean(np.log(ratio))))
    return out


def mean_sag_ratio(fe: np.ndarray, particle: np.ndarray, free: np.ndarray,
                   gravity: np.ndarray) -> float:
    """``sum_free u_particle . g / sum_free u_FE . g`` for (N, 3) sags [m] [1]."""
    down = np.asarray(gravity, dtype=float) / np.linalg.norm(gravity)
    fe_total = float(fe[free] @ down @ np.ones(len(free)))
    if not fe_total > 0:
        raise DataFileError("the FE static sag does not move the free vertices along gravity")
    return float(particle[free] @ down @ np.ones(len(free))) / fe_total


def sag_rows(models: dict[str, Model], gravity: np.ndarray, fe: np.ndarray,
             kv_factors: tuple[float, ...] = KV_FACTORS, load_steps: int = 4) -> list[dict]:
    """Static sag of each model with its ``kv`` scaled by each factor (a model without the
    volume term: its one row). Rows: ``model``, ``kv_factor``, ``max_sag_m``, ``error``
    (the report's sag error against ``fe`` (N, 3) [m]), ``mean_sag_ratio``; ``sag`` (N, 3)
    [m] of the unscaled rows is kept under ``displacement`` for checks."""
    if not all(f > 0 for f in kv_factors):
        raise ParameterError(f"kv factors {kv_factors} must be > 0")
    rows = []
    for name, model in models.items():
        free = model.free_nodes
        factors = kv_factors if model.params.kv is not None else (1.0,)
        for factor in factors:
            params = model.params
            if params.kv is not None and factor != 1.0:
                params = dataclasses.replace(params, kv=params.kv * factor)
            u = gravity_static(model.with_params(params), gravity, load_steps=load_steps)
            row = {"model": name, "kv_factor": float(factor),
                   "max_sag_m": float(np.linalg.norm(u, axis=1).max()),
                   "error": gravity_static_error(fe, u, free),
                   "mean_sag_ratio": mean_sag_ratio(fe, u, free, gravity)}
            if factor == 1.0:
                row["displacement"] = u
            rows.append(row)
            log.info("%s, kv x%g: max sag %.2f mm, error %.2f %%, mean sag ratio %.3f", name,
                     factor, 1e3 * row["max_sag_m"], 100 * row["error"], row["mean_sag_ratio"])
    return rows


def study(scene_path: str | Path, run: str | Path | None = None,
          kv_factors: tuple[float, ...] = KV_FACTORS) -> dict:
    """:func:`split_ratios` and :func:`sag_rows` of the global and calibrated models of the
    finished run of ``scene_path`` (folder ``run``, default ``runs/<scene name>``)."""
    from calibration import read_params
    from pipelines.gravity import read_gravity

    scene = load_scene(scene_path)
    folder = Path(run or Path("runs") / scene.name)
    ref = read_reference(folder / "reference.h5")
    params = read_params(folder / "params.h5")
    stage = read_gravity(folder / "gravity.h5")
    if ref.gravity is None:
        raise DataFileError(f"{folder}: the reference has no gravity sag to compare with")
    gravity = np.asarray(scene.gravity.acceleration, dtype=np.float64)
    models = {name: build_model(ref.problem, scene.material.density, params.connectors[name])
              for name in ("global", "calibrated")}
    fe = ref.gravity.static_displacement
    rows = sag_rows(models, gravity, fe, kv_factors, scene.gravity.static_load_steps)
    own = stage.models["calibrated"].static_displacement
    ours = next(r["displacement"] for r in rows if r["model"] == "calibrated")
    gap = float(np.abs(ours - own).max() / np.abs(own).max())
    if gap > 1e-9:
        raise DataFileError(f"the study's static sag differs from gravity.h5's by {gap:.3g} of "
                            "its largest displacement: not the same model")
    for r in rows:
        r.pop("displacement", None)
    return {"scene": scene.name, "fe_max_sag_m": float(np.linalg.norm(fe, axis=1).max()),
            "split": split_ratios(params.connectors["global"], params.connectors["calibrated"]),
            "rows": rows}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m pipelines.bench.sag_split",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--scene", required=True, help="scene TOML of a finished run")
    parser.add_argument("--run", help="its run folder (default runs/<scene name>)")
    parser.add_argument("--out", help="write the result to this JSON file")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    result = study(args.scene, args.run)
    split = result["split"]
    kv = "-" if split["kv"] is None else f"{split['kv']:.3f}"
    print(f"{result['scene']}: calibrated / global, geometric means: K0 {split['K0']:.3f}, "
          f"kv {kv}; FE max sag {1e3 * result['fe_max_sag_m']:.2f} mm")
    print(f"{'model':12s} {'kv x':>5s} {'max sag mm':>10s} {'error %':>8s} {'mean sag ratio':>15s}")
    for r in result["rows"]:
        print(f"{r['model']:12s} {r['kv_factor']:5.2f} {1e3 * r['max_sag_m']:10.2f} "
              f"{100 * r['error']:8.2f} {r['mean_sag_ratio']:15.3f}")
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
