"""Bench study "calibration methods": model x calibration method -> errors and calibration time.

For the bench scene, the whole pipeline (reference -> calibration -> gravity ->
report) runs once per ``calibration.method`` (``paper``, ``gradient``) in its
own folder under the bench cache; the FE reference is computed once (the first
method's) and adopted by the others (:func:`pipelines.runners.reference.adopt_reference`:
same scene sections and mesh, the FE code older than it). Each row: the model
(``springs``; ``springs + volume`` once the scene switches the volume term on),
the method, the calibration wall time (``timings_s.calibration`` of
``report.json``) and the errors the report quotes (calibration and held-out
indentation/relaxation, gravity static/dynamic). Held-out points are never
used by either fit.

Key of ``bench.json``: ``calibration_methods [{model, method, calibration_s,
errors {...}}]``.
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path
from typing import Any

from forcecal.scene import Scene, replace

log = logging.getLogger(__name__)

METHODS = ("paper", "gradient")
ERROR_KEYS = ("indentation_calibrated", "relaxation_calibrated", "indentation_held_out",
              "relaxation_held_out", "gravity_static", "gravity_dynamic")


def study(scene: Scene, cache_folder: str | Path, quick: bool) -> dict[str, Any]:
    """Run the pipeline once per method (module docstring); returns ``calibration_methods``."""
    from pipelines.runners.common import REFERENCE
    from pipelines.stages import run_pipeline

    base = Path(cache_folder) / "calibration_methods"
    model = "springs + volume" if getattr(scene.particle, "volume", False) else "springs"
    rows, first = [], None
    for method in METHODS:
        out = base / method
        out.mkdir(parents=True, exist_ok=True)
        if first is not None and not (out / REFERENCE).is_file():
            shutil.copy2(first / REFERENCE, out / REFERENCE)  # adopted, not recomputed
        run_pipeline(replace(scene, calibration={"method": method}), out, progress=False)
        report = json.loads((out / "report.json").read_text())
        errors = {k: report["errors"].get(k) for k in ERROR_KEYS}
        rows.append({"model": model, "method": method,
                     "calibration_s": report["timings_s"]["calibration"], "errors": errors})
        log.info("calibration methods: %s / %s: %s, calibration %.1f s", model, method, errors,
                 report["timings_s"]["calibration"])
        first = first or out
    return {"calibration_methods": rows}
