"""Bench study "experiments": what a scene saves by listing only the experiments it needs.

The bench scene up to the calibration with three experiment lists: the full
list is the bench's default pipeline run (``cache/runs/default``, which the driver
brings up to date before this study: the same FE reference and calibration, so
it is not computed twice), ``indentation`` + ``relaxation`` and ``indentation``
alone each run in a fresh folder of its own. Its rows go to ``bench.json``
``skip`` (next to the particle engine's term-skipping rows), two per reduced
list: the FE reference's wall time (``stage`` "reference") and the
calibration's (``stage`` "calibration"), full list against reduced list, with
``skipped`` naming the experiments left out and ``saved_s`` the difference.
``experiments`` (a key of its own) has the three runs' details, with the FE's
compute seconds per experiment. The times are the stages' recorded wall times
(``cache/<stage>.json``), so a rerun with nothing changed reports the runs it
reuses.

Run: ``python -m pipelines bench --full --only experiments`` (``--quick``: the tiny scene;
an item of ``make bench-full`` only).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from forcecal.errors import ForcecalError
from forcecal.h5io import read_reference
from forcecal.scene import DEFAULT_EXPERIMENTS as EXPERIMENTS, Scene
from pipelines.bench.configs import derived_scene
from pipelines.bench.items import default_folder
from pipelines.cache import Cache
from pipelines.runners.common import REFERENCE
from pipelines.stages import run_pipeline

log = logging.getLogger(__name__)

#: the lists compared with the full one
REDUCED = (("indentation", "relaxation"), ("indentation",))


def list_scene(base: Scene, experiments: tuple[str, ...], folder: Path) -> Scene:
    """``base`` with ``experiments``, no figures or fields, written to ``folder/scene.toml``."""
    return derived_scene(base, f"{base.name}-{'-'.join(experiments)}", {}, folder,
                         experiments=experiments)


def run_list(base: Scene, experiments: tuple[str, ...], folder: Path, ranks: int = 2
             ) -> dict[str, Any]:
    """Reference and calibration of ``base`` restricted to ``experiments`` in ``folder``:
    their recorded wall times [s] and the FE's compute seconds per experiment."""
    scene = list_scene(base, experiments, folder)
    run_pipeline(scene, folder, until="calibrate", progress=False, ranks=ranks)
    cache = Cache(folder)
    timings = json.loads(read_reference(folder / REFERENCE).meta["timings_s"])
    return {"experiments": list(experiments), "reference_s": cache.elapsed("reference"),
            "calibration_s": cache.elapsed("calibrate"),
            "fe_compute_s": {e: timings[e] for e in EXPERIMENTS}}


def full_list(scene: Scene, folder: Path) -> dict[str, Any]:
    """:func:`run_list`'s record of the default pipeline run in ``folder`` (the full list),
    from its stage records; its stages must have run (the driver's default item)."""
    cache = Cache(folder)
    record = {"experiments": list(EXPERIMENTS), "reference_s": cache.elapsed("reference"),
              "calibration_s": cache.elapsed("calibrate")}
    if None in record.values() or not (folder / REFERENCE).is_file():
        raise ForcecalError(f"bench experiments: {folder} holds no finished default run of "
                            f"{scene.name} (run the 'default pipeline run' item first)")
    timings = json.loads(read_reference(folder / REFERENCE).meta["timings_s"])
    return {**record, "fe_compute_s": {e: timings[e] for e in EXPERIMENTS}}


def study(scene: Scene, cache: Path, quick: bool) -> dict[str, Any]:
    """The ``skip`` rows and the ``experiments`` details (module docstring)."""
    root = cache / "experiments"
    runs = {EXPERIMENTS: full_list(scene, default_folder(cache))}
    runs.update({experiments: run_list(scene, experiments, root / "-".join(experiments))
                 for experiments in REDUCED})
    full = runs[EXPERIMENTS]
    rows = []
    for experiments in REDUCED:
        skipped = ", ".join(e for e in EXPERIMENTS if e not in experiments)
        for stage, key in (("reference", "reference_s"), ("calibration", "calibration_s")):
            row = {"scene": f"{scene.name}: {stage}, {' + '.join(experiments)}",
                   "full_s": full[key], "skipped_s": runs[experiments][key],
                   "stage": stage, "skipped": skipped,
                   "saved_s": full[key] - runs[experiments][key]}
            rows.append(row)
            log.info("experiments: %s without %s: %.1f s instead of %.1f s", stage, skipped,
                     row["skipped_s"], row["full_s"])
    return {"skip": rows, "experiments": [runs[e] for e in (EXPERIMENTS, *REDUCED)]}
