"""The relaxing (viscoelastic) volume term against the elastic one, each calibrated on a scene.

The question: with Maxwell arms on the per-tet volume term (``particle.volume =
"viscoelastic"``, :mod:`particle.volume`), fitted to the same surface curves, is the
calibrated model better as a body (static sag, release period, first peak, release RMS)
without losing the surface (held-out punch or vertex forces)? The committed release-lever
study (``runs/studies/release_levers.json``) put arms on the volume term of the calibrated
elastic model *without refitting*; this one refits.

For each scene and each volume term (``true``: elastic, ``"viscoelastic"``; the scene's own
calibration method unless ``--method`` names others) the pipeline's calibrate, gravity and
report stages run in ``<folder>/<scene>/<variant>/`` on the scene's FE reference
(``runs/<scene>/reference.h5``, hard-linked with its cache record, never recomputed: the
reference stage must be up to date there), and the numbers of ``report.json`` are
collected: the calibration and held-out errors of both experiments, the static sag, the
release's period, first peak, RMS and mode frequency errors, the fitted global parameters,
the calibration's wall time, and the closed-form baseline's numbers of the same report.

``python -m studies.viscoelastic_volume --scene scenes/liver_punch.toml [--scene ...]
[--method paper] [--folder runs/studies/viscoelastic_volume] [--out
runs/studies/viscoelastic_volume.json]``. A stage whose inputs did not change is skipped
(the pipeline's cache), so a rerun after a crash repeats only what is missing; the JSON is
written (atomically) after every variant.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import time
from pathlib import Path
from typing import Any

from forcecal.errors import DataFileError
from forcecal.scene import Scene, load_scene, replace
from pipelines.runners.common import REFERENCE, REPORT

log = logging.getLogger(__name__)

#: the volume terms compared: variant name -> value of ``particle.volume``
VARIANTS = {"elastic": True, "viscoelastic": "viscoelastic"}
FOLDER = Path("runs/studies/viscoelastic_volume")
OUT = Path("runs/studies/viscoelastic_volume.json")


def prepare_folder(scene: Scene, source: Path, folder: Path) -> None:
    """``folder`` holding the scene's FE reference from ``source`` (hard-linked, else copied)
    and its cache record, so the pipeline takes it as up to date; :class:`DataFileError` if
    ``source`` has no reference."""
    reference, record = source / REFERENCE, source / "cache" / "reference.json"
    if not (reference.is_file() and record.is_file()):
        raise DataFileError(f"{source}: no FE reference with its cache record; compute it "
                            f"first (python -m pipelines reference --scene {scene.path})")
    (folder / "cache").mkdir(parents=True, exist_ok=True)
    target = folder / REFERENCE
    if not target.exists():
        try:
            os.link(reference, target)
        except OSError:
            shutil.copy2(reference, target)
    shutil.copy2(record, folder / "cache" / "reference.json")


def reference_changes(scene: Scene, folder: Path) -> list[str]:
    """Why the reference stage of ``scene`` in ``folder`` would run (empty: up to date)."""
    from pipelines.cache import Cache
    from pipelines.runners.common import Context
    from pipelines.stages import STAGES

    context = Context(scene, folder, progress=False, ranks=1)
    return Cache(folder).check("reference", STAGES["reference"].inputs(context))


def report_numbers(report: dict[str, Any]) -> dict[str, Any]:
    """The study's numbers of one ``report.json``: the calibrated model's and the baseline's."""
    gravity = report.get("gravity", {})
    dynamic = gravity.get("dynamic_metrics", {})

    def model(errors: dict, metrics: dict | None) -> dict[str, Any]:
        out = {k: errors.get(k) for k in ("indentation_calibrated", "indentation_held_out",
                                          "relaxation_calibrated", "relaxation_held_out",
                                          "gravity_static", "gravity_dynamic")}
        if metrics:
            out.update({k: metrics.get(k) for k in ("period_error", "first_peak_error",
                                                     "rms_error", "mode_frequency_errors")})
        return out

    return {"calibrated": model(report["errors"], dynamic.get("calibrated")),
            "baseline": model(report["baseline_errors"], dynamic.get("baseline")),
            "global_parameters": report.get("global_parameters"),
            "calibration_s": report.get("timings_s", {}).get("calibration"),
            "fe_modes": dynamic.get("fe", {}).get("modes"),
            "warnings": report.get("warnings", [])}


def run_variant(scene: Scene, volume: bool | str, method: str, folder: Path) -> dict[str, Any]:
    """Calibrate, run the gravity test and report ``scene`` with ``particle.volume = volume``
    and ``calibration.method = method`` in ``folder``; the report's numbers."""
    from pipelines.stages import run_pipeline

    variant = replace(scene, particle={"volume": volume}, calibration={"method": method})
    stale = reference_changes(variant, folder)
    if stale:
        raise DataFileError(f"{folder}: the FE reference is not up to date for this scene "
                            f"({'; '.join(stale)}); the study calibrates on the scene's own "
                            "reference and never recomputes it")
    t = time.perf_counter()
    outcomes = run_pipeline(variant, folder, until="report", progress=False)
    log.info("%s, volume %s, %s: %s (%.0f s)", scene.name, volume, method,
             ", ".join(f"{o.stage} {'ran' if o.ran else 'skipped'}" for o in outcomes),
             time.perf_counter() - t)
    return report_numbers(json.loads((folder / REPORT).read_text()))


def study(scene_paths: list[str | Path], methods: list[str] | None = None,
          folder: Path = FOLDER, out: Path = OUT) -> dict[str, Any]:
    """Every scene of ``scene_paths`` with each volume term of :data:`VARIANTS` and each of
    ``methods`` (None: the scene's own); rows written to ``out`` after each variant."""
    rows: list[dict[str, Any]] = []
    result = {"variants": {k: v for k, v in VARIANTS.items()}, "rows": rows,
              "load_average_start": list(os.getloadavg())}
    for path in scene_paths:
        scene = load_scene(path)
        source = Path("runs") / scene.name
        for method in methods or [scene.calibration.method]:
            for name, volume in VARIANTS.items():
                target = folder / scene.name / (name if methods is None else f"{name}-{method}")
                prepare_folder(scene, source, target)
                rows.append({"scene": scene.name, "method": method, "volume": name,
                             "folder": str(target),
                             **run_variant(scene, volume, method, target)})
                result["load_average_end"] = list(os.getloadavg())
                write_json(out, result)
    return result


def write_json(path: Path, data: dict) -> None:
    """``data`` as JSON at ``path``, atomically (a temporary file renamed)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    tmp.replace(path)


def table(result: dict[str, Any]) -> str:
    """The rows as a plain-text table (percent)."""
    head = (f"{'scene':18s} {'method':8s} {'volume':12s} {'model':10s} {'held-out ind':>12s} "
            f"{'held-out rel':>12s} {'sag':>6s} {'period':>7s} {'peak':>6s} {'RMS':>6s}  modes")
    lines = [head]
    for row in result["rows"]:
        for model in ("calibrated", "baseline"):
            m = row[model]

            def pct(key: str) -> str:
                value = m.get(key)
                return "-" if value is None else f"{100 * value:.1f}"
            modes = ", ".join(f"{100 * f:+.1f}" for f in m.get("mode_frequency_errors") or [])
            lines.append(f"{row['scene']:18s} {row['method']:8s} {row['volume']:12s} "
                         f"{model:10s} {pct('indentation_held_out'):>12s} "
                         f"{pct('relaxation_held_out'):>12s} {pct('gravity_static'):>6s} "
                         f"{pct('period_error'):>7s} {pct('first_peak_error'):>6s} "
                         f"{pct('rms_error'):>6s}  {modes}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m studies.viscoelastic_volume",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--scene", action="append", required=True,
                        help="scene TOML whose runs/<name>/reference.h5 is computed (repeat)")
    parser.add_argument("--method", action="append", choices=("paper", "gradient"),
                        help="calibration method(s) (default: each scene's own)")
    parser.add_argument("--folder", type=Path, default=FOLDER, help="run folders' parent")
    parser.add_argument("--out", type=Path, default=OUT, help="the rows as JSON")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    print(table(study(args.scene, args.method, args.folder, args.out)))


if __name__ == "__main__":
    main()
