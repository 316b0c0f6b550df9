"""Bench study "calibration methods": scene x model x calibration method -> errors and costs.

For two scenes, the bench scene (vertex indentation, ``scenes/liver.toml``) and the punch
scene (``scenes/liver_punch.toml``; ``--quick``: the bench scene only), the whole pipeline
(reference -> calibration -> gravity -> report, no figures or fields) runs once per model
(``springs``: ``particle.volume = false``; ``springs + volume``: true) and
``calibration.method`` (``paper``: global Nelder-Mead + local tuning; ``gradient``: every
connector by regularised least squares), each in a folder of its own under the bench
cache. A scene's FE reference does not depend on the model or the method: it is computed
once per scene and copied to the other folders, where
:func:`pipelines.runners.reference.adopt_reference` adopts it when its fingerprints are
current: the bench scene's is the bench's default pipeline run's (``cache/runs/default``,
brought up to date by the driver before this study), the punch scene's is adopted from
``runs/liver_punch/`` (``make demo``) when that one is current, else computed by the
first row (:func:`pipelines.bench.items.runs_source`: never in a ``--cold`` bench). The
bench scene's row with its own model and method is the default pipeline run itself: its
folder is seeded from that run (:func:`pipelines.bench.items.seed_folder`), so only the
report (another scene name) is redone, and the row reports that run's calibration. The punch
scene's four rows fit its surface curves only (its experiment ``body``, if it has one, left
out), and it has one more row, the punch + whole-body method as the scene ships it
(:data:`BODY_METHOD`, :func:`body_row`: its volume term, the gradient fit with its
``calibration.body_data``, the experiment ``body``, added when the scene has none; its
reference is the punch rows', with the body experiment computed on top if missing).

Each row: ``scene``, ``model``, ``method``, ``calibration_s`` (``timings_s.calibration``
of the run's ``report.json``), ``errors`` (the report's calibration and held-out
indentation/relaxation, gravity static/dynamic), ``haptic`` (latency of one 1 ms
:meth:`particle.haptics.HapticSession.step` of the calibrated model at the scene's first
calibration point, one thread: median and p99 [us], substeps), and ``front``: True if no
other row of the same scene is at least as good on all of held-out error (mean of the
held-out indentation and relaxation errors), static gravity error, calibration time and
haptic p99 and better on one. A run that fails is a row with ``failed`` (the message)
and no numbers. Held-out points are never used by either fit.

Key of ``bench.json``: ``calibration_methods [{scene, model, method, calibration_s,
errors {...}, haptic {...}, front}]``.
"""

from __future__ import annotations

import filecmp
import json
import logging
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from forcecal.errors import ForcecalError
from forcecal.scene import Scene, load_scene

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]
PUNCH_SCENE = ROOT / "scenes" / "liver_punch.toml"
MODELS = (("springs", False), ("springs + volume", True))
METHODS = ("paper", "gradient")
#: the punch scene's extra row: the gradient method fitting the whole-body data too
BODY_METHOD = "gradient + body"


def body_row(scene: Scene) -> tuple[str, bool | str, dict[str, Any], tuple[str, ...]]:
    """The punch + whole-body method's row as ``scene`` ships it: (model label, its
    ``particle.volume`` (the elastic term if it has none), the calibration section's changes
    (the gradient fit with the scene's ``body_data``), the experiments (the scene's, with
    ``body``))."""
    volume = scene.particle.volume or True
    model = "springs + relaxing volume" if volume == "viscoelastic" else MODELS[1][0]
    experiments = tuple(scene.experiments) + (() if scene.runs("body") else ("body",))
    return (model, volume, {"method": "gradient", "body_data": scene.calibration.body_data},
            experiments)


def surface_only(scene: Scene) -> tuple[str, ...] | None:
    """The experiments of a row that fits the surface curves only: the scene's without
    ``body`` (None: the scene's own, it has no ``body``)."""
    if not scene.runs("body"):
        return None
    return tuple(e for e in scene.experiments if e != "body")
ERROR_KEYS = ("indentation_calibrated", "relaxation_calibrated", "indentation_held_out",
              "relaxation_held_out", "gravity_static", "gravity_dynamic")
HAPTIC_CALLS = 2000


def held_out_error(errors: dict[str, float | None]) -> float | None:
    """Mean of the held-out indentation and relaxation errors (None if either is missing)."""
    values = [errors.get("indentation_held_out"), errors.get("relaxation_held_out")]
    return None if None in values else float(np.mean(values))


def objectives(row: dict[str, Any]) -> tuple[float, ...] | None:
    """The row's objectives of the front, all smaller-is-better: held-out error, static
    gravity error, calibration time [s], haptic p99 [us]; None for a failed or incomplete
    row."""
    if "failed" in row:
        return None
    values = (held_out_error(row["errors"]), row["errors"].get("gravity_static"),
              row["calibration_s"], row["haptic"]["p99_us"])
    return None if None in values else tuple(float(v) for v in values)


def mark_front(rows: list[dict[str, Any]]) -> None:
    """Set ``front`` on every row: non-dominated among the complete rows of its scene."""
    from pipelines.bench.configs import non_dominated

    for row in rows:
        row["front"] = False
    for scene in dict.fromkeys(r["scene"] for r in rows):
        members = [(r, objectives(r)) for r in rows if r["scene"] == scene]
        members = [(r, o) for r, o in members if o is not None]
        for (row, _), on in zip(members, non_dominated([o for _, o in members])):
            row["front"] = on


def haptic_row(folder: Path) -> dict[str, Any]:
    """Haptic latency of the calibrated model of the run in ``folder``."""
    from calibration.loading import load_calibrated
    from pipelines.bench.particle_engine import haptic_latency
    from pipelines.runners.common import PARAMS

    calibrated = load_calibrated(folder / PARAMS)
    model, problem = calibrated.model, calibrated.problem
    # at the first calibration point (test_points lists them first)
    latency = haptic_latency(model, int(problem.test_points[0]), problem.normals[0],
                             calls=HAPTIC_CALLS)
    return {key: latency[key] for key in ("median_us", "p99_us", "substeps", "dt_s",
                                          "connectors")}


def run_row(scene: Scene, model: str, volume: bool, method: str, folder: Path,
            reference_from: Path | None, reference_is_current: bool) -> dict[str, Any]:
    """The pipeline of ``scene`` with ``model`` and ``method`` in ``folder``; its row.

    ``reference_from``: a folder whose ``reference.h5`` this row adopts;
    ``reference_is_current``: it was computed by this run (an earlier row), so it replaces
    the row's own (stale after a code change, that one would be recomputed); otherwise (the
    scene's ``runs/<name>/``) it only fills a gap."""
    from pipelines.bench.configs import derived_scene
    from pipelines.runners.common import REFERENCE
    from pipelines.stages import run_pipeline

    row: dict[str, Any] = {"scene": scene.name, "model": model, "method": method}
    calibration, experiments = {"method": method}, surface_only(scene)
    if method == BODY_METHOD:
        _, _, calibration, experiments = body_row(scene)
    variant = derived_scene(scene, f"{scene.name}-{method.replace(' + ', '-')}-"
                            f"{'volume' if volume else 'springs'}",
                            {"particle": {"volume": volume}, "calibration": calibration},
                            folder, experiments=experiments)
    source = None if reference_from is None else reference_from / REFERENCE
    if source is not None and source.is_file() and (
            not (folder / REFERENCE).is_file()
            or reference_is_current and not filecmp.cmp(source, folder / REFERENCE,
                                                        shallow=False)):
        shutil.copy2(source, folder / REFERENCE)  # adopted by the stage if current
    try:
        run_pipeline(variant, folder, progress=False)
        report = json.loads((folder / "report.json").read_text())
        row["calibration_s"] = report["timings_s"]["calibration"]
        row["errors"] = {k: report["errors"].get(k) for k in ERROR_KEYS}
        row["haptic"] = haptic_row(folder)
    except ForcecalError as exc:
        log.warning("calibration methods: %s / %s / %s failed: %s", scene.name, model,
                    method, exc)
        return {**row, "failed": str(exc)}
    log.info("calibration methods: %s / %s / %s: held-out %.4f / %.4f, gravity %.4f / %.4f, "
             "calibration %.1f s, haptic p99 %.0f us", scene.name, model, method,
             row["errors"]["indentation_held_out"], row["errors"]["relaxation_held_out"],
             row["errors"]["gravity_static"], row["errors"]["gravity_dynamic"] or np.nan,
             row["calibration_s"], row["haptic"]["p99_us"])
    return row


def study(scene: Scene, cache_folder: str | Path, quick: bool) -> dict[str, Any]:
    """Every scene x model x method (module docstring); returns ``calibration_methods``."""
    from pipelines.bench.items import default_folder, runs_source, seed_folder

    cache_folder = Path(cache_folder)
    scenes = [scene] if quick else [scene, load_scene(PUNCH_SCENE)]
    rows = []
    for sc in scenes:
        base = cache_folder / "calibration_methods" / sc.name
        if sc is scene:  # the default pipeline run's reference, current
            reference_from, reference_is_current = default_folder(cache_folder), True
        else:
            reference_from, reference_is_current = runs_source(cache_folder, sc.name), False
        kinds = [(model, volume, method) for model, volume in MODELS for method in METHODS]
        if sc is not scene:  # the punch scene: the punch + whole-body method too
            kinds.append((*body_row(sc)[:2], BODY_METHOD))
        for model, volume, method in kinds:
            folder = base / f"{'volume' if volume else 'springs'}-{method.replace(' + ', '-')}"
            if sc is scene and (volume, method) == (scene.particle.volume,
                                                    scene.calibration.method):
                seed_folder(default_folder(cache_folder), folder)  # the same run
            rows.append(run_row(sc, model, volume, method, folder, reference_from,
                                reference_is_current))
            if "failed" not in rows[-1] and method != BODY_METHOD:
                reference_from, reference_is_current = folder, True
    mark_front(rows)
    return {"calibration_methods": rows}


def markdown(b: dict[str, Any]) -> list[str]:
    """The "Model and calibration method" section of BENCH.md (empty without rows)."""
    from pipelines.bench.tables import table

    rows = b.get("calibration_methods")
    if not rows:
        return []

    def percent(value: float | None) -> str:
        return "-" if value is None else f"{100 * value:.2f}"

    body = []
    for r in rows:
        if "failed" in r:
            body.append([r["scene"], r["model"], r["method"], f"failed: {r['failed']}", "", "",
                         "", "", "", "no"])
            continue
        e = r["errors"]
        body.append([r["scene"], r["model"], r["method"],
                     f"{percent(e['indentation_calibrated'])} / "
                     f"{percent(e['indentation_held_out'])}",
                     f"{percent(e['relaxation_calibrated'])} / "
                     f"{percent(e['relaxation_held_out'])}",
                     percent(e["gravity_static"]), percent(e["gravity_dynamic"]),
                     f"{r['calibration_s']:.0f}",
                     f"{r['haptic']['p99_us']:.0f} ({r['haptic']['substeps']})",
                     "**yes**" if r["front"] else "no"])
    return ["", "## Model and calibration method", "",
            "Each scene with each particle model and calibration method, the whole pipeline "
            "per row on the scene's one FE reference (`calibration methods`, "
            "`pipelines/bench/calibration_methods.py`). Errors in % (relative RMS, docs/results.md "
            "'Error definitions'): calibration / held-out curves, gravity sag and release, "
            "none of which the held-out points or the gravity test were fitted to. Haptic: "
            "p99 latency of one 1 ms haptic step of the calibrated model, one thread "
            "(substeps in brackets). Front: no other row of the scene is at least as good on "
            "held-out error (mean of indentation and relaxation), static sag error, "
            "calibration time and haptic p99 and better on one.", ""] + table(
        ["scene", "model", "method", "indentation cal. / held-out", "relaxation cal. / "
         "held-out", "static sag", "release", "calibration [s]", "haptic p99 [us]", "front"],
        body)
