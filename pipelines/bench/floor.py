"""Bench study "discretisation floor": how much of the reference tests' error is the mesh's.

``study(scene, cache_folder, quick)`` returns the bench.json key ``discretisation_floor``:
for the default liver and the liver punch scene (:data:`SCENES`), the scene's FE reference
(its ``[fe]``, as the reference computes it: both scenes run at ``fe.refine = 0``, a punch on
its rim-refined mesh) and the discretisation floor's vertex-dof elements
(:mod:`reference_fe.floor`: ANP, locking-free, and plain P1, on the particle mesh) run the
gravity test, the second-support test when the scene runs it, and the held-out points'
indentation and relaxation curves; one row per scene and element: ``{scene, element,
static_sag_error, release_period_error, first_peak_error, release_rms,
second_support_static_sag_error, second_support_release_rms,
second_support_period_error, second_support_first_peak_error, indentation_held_out,
relaxation_held_out, wall_s}`` measured as ``report.json`` measures the calibrated model
(:func:`pipelines.report.floor_block`), next to the rows of the calibrated and the baseline
particle models read from the scene's committed ``runs/<scene>/report.json`` (``wall_s``
null: their runs are the report's). Each scene's FE work is kept in the bench cache under the
FE code and scene key (:func:`pipelines.bench.items.fe_key`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from pathlib import Path
from typing import Any

from forcecal.errors import ConvergenceError
from forcecal.h5io import SecondSupportResult
from forcecal.problem import build_problem, second_support
from forcecal.scene import Scene, load_scene

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]
#: the scenes of the study (the default liver and its punch calibration)
SCENES = ("scenes/liver.toml", "scenes/liver_punch.toml")
#: a row's metrics, in report.json's floor block names -> the row's names
ROW_METRICS = {"static_sag": "static_sag_error", "period_error": "release_period_error",
               "first_peak_error": "first_peak_error", "release_rms": "release_rms",
               "second_support_static_sag": "second_support_static_sag_error",
               "second_support_release_rms": "second_support_release_rms",
               "second_support_period_error": "second_support_period_error",
               "second_support_first_peak_error": "second_support_first_peak_error",
               "indentation_held_out": "indentation_held_out",
               "relaxation_held_out": "relaxation_held_out"}


def scene_floor(scene: Scene) -> dict[str, Any]:
    """The scene's reference tests and floor, measured: report.json's floor block
    (:func:`pipelines.report.floor_block`, the particle models' values from the scene's
    committed report when it has them) plus ``reference_element``, ``reference_wall_s`` and
    ``reference_part_seconds`` (the reference's gravity test, second-support test and
    held-out curves, run as the floor runs each of its elements: with the reference's
    ``[fe]`` in place of a floor element they are the reference's own).

    Raises:
        ConvergenceError: the reference's gravity or second-support test failed (the study
            has nothing to measure the floor against).
    """
    from pipelines.report import floor_block, read_report
    from reference_fe.floor import curves_of, element_arrays, floor_arrays, result_of, runs_of

    problem = build_problem(scene)
    g = scene.gravity
    fe = dataclasses.replace(scene.fe, refine=0)
    reference = element_arrays(scene, problem, fe)
    failures = [f"{name}: {reference[key]}" for name, key in
                (("gravity test", "failed"), ("second-support test", "second_support_failed"))
                if key in reference]
    if failures:
        raise ConvergenceError(f"scene '{scene.name}', the FE reference's "
                               + "; ".join(failures))
    settings = dataclasses.replace(g, tracked_node=problem.tracked_node)
    gravity = runs_of(reference, "", settings)
    second = None
    if "second_support" in scene.experiments:
        support = second_support(scene, problem)
        second = SecondSupportResult(scene.second_support, support.fixed, runs_of(
            reference, "second_support_",
            dataclasses.replace(g, tracked_node=support.tracked_node)))
    held_out = curves_of(reference, "held_out_")
    floor = result_of(floor_arrays(scene, problem), settings)
    report_path = ROOT / "runs" / scene.name / "report.json"
    models: dict[str, dict | None] = {"calibrated": None, "baseline": None}
    dynamic, support_block = None, None
    if report_path.is_file():
        report = read_report(report_path)
        models = {"calibrated": report["errors"], "baseline": report["baseline_errors"]}
        dynamic = (report.get("gravity") or {}).get("dynamic_metrics")
        support_block = report.get("second_support")
    empty = {"gravity_static": None, "gravity_dynamic": None}
    rim = (f", each punch's mesh refined {fe.local_refine} x near its rim"
           if scene.indentation.indenter == "punch" and fe.local_refine else "")
    block = floor_block(problem, gravity, floor, models["calibrated"] or empty,
                        models["baseline"] or empty, dynamic, held_out=held_out,
                        second_support=second, support_block=support_block,
                        reference_mesh=f"{fe.element} on the particle mesh{rim}")
    return {**block, "reference_element": scene.fe.element,
            "reference_wall_s": float(reference["seconds"]),
            "reference_part_seconds": json.loads(str(reference["part_seconds"])),
            "report": str(report_path.relative_to(ROOT)) if report_path.is_file() else None}


def rows_of(name: str, block: dict[str, Any]) -> list[dict[str, Any]]:
    """The study's rows of one scene's :func:`scene_floor`: each floor element, then the
    calibrated and the baseline model."""
    rows = [{"scene": name, "element": element, "wall_s": row["fe_seconds"],
             **{out: row[key] for key, out in ROW_METRICS.items()},
             **{k: row[k] for k in ("failed", "second_support_failed", "held_out_failed")
                if row.get(k)}}
            for element, row in block["elements"].items()]
    rows += [{"scene": name, "element": f"particle ({model})", "wall_s": None,
              **{out: block[model].get(key) for key, out in ROW_METRICS.items()}}
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


def _percent(value: float | None) -> str:
    return "-" if value is None else f"{100.0 * value:+.1f} %"


def floor_table(study: dict[str, Any]) -> list[str]:
    """The study's rows as a Markdown table (errors in %, signed where the metric has a sign;
    '-' where a metric was not run: the second support on a scene that does not ask for it)."""
    from pipelines.bench.tables import table

    columns = ("static_sag_error", "release_period_error", "first_peak_error", "release_rms",
               "second_support_static_sag_error", "second_support_release_rms",
               "indentation_held_out", "relaxation_held_out")
    return table(["scene", "model", "static sag", "release period", "first peak",
                  "release RMS", "2nd support sag", "2nd support RMS", "held-out indentation",
                  "held-out relaxation", "FE wall [s]"],
                 [[row["scene"], row["element"], *(_percent(row.get(c)) for c in columns),
                   "-" if row.get("wall_s") is None else f"{row['wall_s']:.1f}"]
                  for row in study["rows"]])


def markdown(b: dict[str, Any]) -> list[str]:
    """BENCH.md's section of the study (nothing when bench.json has no such key)."""
    study = b.get("discretisation_floor")
    if not study:
        return []
    return ["", "## Discretisation floor", "",
            "The scene's gravity test, second-support test and held-out curves computed with "
            "vertex-dof FE elements and the true material on the particle mesh (ANP: "
            "locking-free average nodal pressure; P1: plain linear tets), against the scene's "
            "FE reference, next to the calibrated and closed-form baseline particle models "
            "(from the scene's committed report; docs/fe-reference.md, 'The discretisation "
            "floor'). Errors relative to the reference.", "", *floor_table(study)]
