"""Bench study "discretisation floor": how much of the gravity test's error is the mesh's.

``study(scene, cache_folder, quick)`` returns the bench.json key ``discretisation_floor``:
for the default liver and the liver punch scene (:data:`SCENES`), the gravity test of the
scene's FE reference (its ``[fe]`` element on the particle mesh, as the reference computes
it: both scenes run their gravity test at ``fe.refine = 0``) and of the discretisation floor's
vertex-dof elements (:mod:`reference_fe.floor`: ANP, locking-free, and plain P1), one row
per scene and element: ``{scene, element, static_sag_error, release_period_error,
first_peak_error, release_rms, wall_s}`` measured as ``report.json`` measures the calibrated
model (:func:`pipelines.report.floor_block`), next to the rows of the calibrated and the
baseline particle models read from the scene's committed ``runs/<scene>/report.json``
(``wall_s`` null: their runs are the report's). Each scene's FE work is kept in the bench
cache under the FE code and scene key (:func:`pipelines.bench.items.fe_key`).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from forcecal.h5io import GravityResult
from forcecal.problem import build_problem
from forcecal.scene import Scene, load_scene

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]
#: the scenes of the study (the default liver and its punch calibration)
SCENES = ("scenes/liver.toml", "scenes/liver_punch.toml")
#: a row's metrics, in report.json's floor block names -> the row's names
ROW_METRICS = {"static_sag": "static_sag_error", "period_error": "release_period_error",
               "first_peak_error": "first_peak_error", "release_rms": "release_rms"}


def scene_floor(scene: Scene) -> dict[str, Any]:
    """The scene's reference gravity test and floor, measured: report.json's floor block
    (:func:`pipelines.report.floor_block`, the particle models' values from the scene's
    committed report when it has them) plus ``reference_element`` and ``reference_wall_s``."""
    from pipelines.report import floor_block, read_report
    from reference_fe.experiments import gravity_dynamic, gravity_static
    from reference_fe.floor import floor_arrays, result_of
    from reference_fe.model import FEModel

    problem = build_problem(scene)
    g = scene.gravity
    start = time.perf_counter()
    fe = dataclasses.replace(scene.fe, refine=0, local_refine=0)
    model = FEModel(problem.mesh, scene.material, fe)
    static = gravity_static(model, problem.fixed, g.acceleration, g.static_load_steps)
    times, displacement = gravity_dynamic(model, problem.fixed, g.acceleration, g.duration,
                                          g.fe_dt, g.record_interval)
    reference_s = time.perf_counter() - start
    settings = dataclasses.replace(g, tracked_node=problem.tracked_node)
    gravity = GravityResult(static, times, displacement, settings)
    floor = result_of(floor_arrays(scene, problem), settings)
    report_path = ROOT / "runs" / scene.name / "report.json"
    models: dict[str, dict | None] = {"calibrated": None, "baseline": None}
    dynamic = None
    if report_path.is_file():
        report = read_report(report_path)
        models = {"calibrated": report["errors"], "baseline": report["baseline_errors"]}
        dynamic = (report.get("gravity") or {}).get("dynamic_metrics")
    empty = {"gravity_static": None, "gravity_dynamic": None}
    block = floor_block(problem, gravity, floor, models["calibrated"] or empty,
                        models["baseline"] or empty, dynamic)
    return {**block, "reference_element": scene.fe.element, "reference_wall_s": reference_s,
            "report": str(report_path.relative_to(ROOT)) if report_path.is_file() else None}


def rows_of(name: str, block: dict[str, Any]) -> list[dict[str, Any]]:
    """The study's rows of one scene's :func:`scene_floor`: each floor element, then the
    calibrated and the baseline model."""
    rows = [{"scene": name, "element": element, "wall_s": row["fe_seconds"],
             **{out: row[key] for key, out in ROW_METRICS.items()},
             **({"failed": row["failed"]} if row["failed"] else {})}
            for element, row in block["elements"].items()]
    rows += [{"scene": name, "element": f"particle ({model})", "wall_s": None,
              **{out: block[model][key] for key, out in ROW_METRICS.items()}}
             for model in ("calibrated", "baseline")]
    return rows


def study(scene: Scene, cache_folder: Path, quick: bool) -> dict[str, Any]:
    """The bench.json key ``discretisation_floor`` (module docstring); ``scene`` and ``quick``
    are not used: the study's scenes are :data:`SCENES`."""
    from pipelines.bench.items import cached, fe_key

    out: dict[str, Any] = {"load_average_start": os.getloadavg()[0], "rows": [],
                           "scenes": {}}
    for path in SCENES:
        floor_scene = load_scene(ROOT / path)
        block = cached(cache_folder / f"floor_{floor_scene.name}.json", fe_key(floor_scene),
                       lambda s=floor_scene: scene_floor(s))
        out["scenes"][floor_scene.name] = block
        out["rows"] += rows_of(floor_scene.name, block)
    out["load_average_end"] = os.getloadavg()[0]
    return {"discretisation_floor": out}
