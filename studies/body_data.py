"""Which whole-body data to fit with the surface curves: measured, on calibration data only.

The calibrated punch models carry over at the surface but are no better than the closed-form
baseline as bodies (README, "Why the release misses its goal"): nothing in the surface
curves constrains the interior or the global modes. The FE stage's experiment ``body``
(:mod:`reference_fe.body`) gives four kinds of whole-body data the gravity test does not
use: the natural modes about the rest state (instantaneous and long-term moduli), the static
weight along the two directions perpendicular to the test's gravity, the modes about each
of those loaded states, and the natural modes of the unsupported body. This study calibrates each scene with some choices of
``calibration.body_data`` (gradient method, the body weight chosen by the calibration's own
cross-validation) and records, for every fit:

* **what chooses** (calibration data only): the fit of every kind
  (:data:`EVERY_KIND`) also scores every set of kinds by the cross-validation
  (``calibration.body_candidates``; at the global fit and at the first round's fit): the
  point folds and each whole-body item of every kind left out in turn, each predicted by the
  fit to the rest of that set, so a kind the set does not use is predicted by fits that
  never saw it. **Rule** (set before the other sets' nonlinear fits ran): the set with the
  lowest score, summed over the scenes, the first round's (the fitted point's); a set with
  fewer kinds wins a tie (within 1 %). With ``--volume elastic --volume viscoelastic`` the
  fit of every kind runs with each volume term and the candidates are the sets with a volume
  term, each score with the residual its fit's rows' compression leaves out (the same for
  every set of one fit, not for two models'): the elastic term wins a tie. Checked against
  each fit's whole-body errors on every item (``whole_body_score``: fitted or predicted) and
  the calibration points' errors;
* **what is reported, never used to choose**: the held-out surface points, the gravity
  test's static sag and release (period, first peak, RMS, modes), the baseline's same
  numbers.

The FE references of the scenes are computed already (``runs/<scene>/reference.h5``). One
whose scene asks for ``body`` holds it (the reference stage's, with its time) and is used as
it is; otherwise the ``body`` experiment is computed into a copy
(``<folder>/<scene>/reference.h5``) by the FE stage's own code
(:func:`reference_fe.run.compute_item`), because the FE code changed with the new
experiment, so the pipeline's reference stage would recompute everything else too;
its time is recorded against the reference's (``fe_cost``). The calibrate, gravity and
report stages then run on that copy (their runners, without the pipeline's cache).

``python -m studies.body_data --scene scenes/liver_punch.toml [--scene ...] [--variants
loads+modes+loaded_modes,none,...] [--volume elastic --volume viscoelastic] [--folder
runs/studies/body_data] [--out runs/studies/body_data.json]``; the JSON is written
(atomically) after every variant, and a variant whose ``report.json`` exists is not rerun.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from forcecal.errors import DataFileError
from forcecal.h5io import Reference, read_reference, write_reference
from forcecal.scene import (BODY_DATA_CHOICES, HELD_OUT_EXPERIMENTS, Scene, load_scene,
                            replace)
from studies.viscoelastic_volume import report_numbers, write_json

log = logging.getLogger(__name__)

#: the fit of every kind of whole-body data, which also scores every set of them
EVERY_KIND = BODY_DATA_CHOICES[-1]
VARIANTS = (EVERY_KIND, "none", "modes+loaded_modes", "loads+modes")
FOLDER = Path("runs/studies/body_data")
OUT = Path("runs/studies/body_data.json")


def add_body_experiment(scene: Scene, source: Path, out: Path) -> dict[str, float]:
    """Copy ``source`` (a ``reference.h5`` of ``scene``) to ``out`` with the experiment
    ``body`` computed by the FE stage's code; returns its seconds and the reference's
    compute seconds (summed over work items, as ``timings_s`` records them)."""
    from reference_fe.body import result_of
    from reference_fe.model import FEModel
    from reference_fe.refine import fe_problem
    from reference_fe.run import WorkItem, compute_item, run_keys

    ref = read_reference(source)
    problem = ref.problem
    t = time.perf_counter()
    fe = fe_problem(problem, scene.fe)
    model = FEModel(fe.problem.mesh, scene.material, scene.fe)
    build = time.perf_counter() - t
    t = time.perf_counter()
    arrays = compute_item(model, scene, problem, WorkItem("body", -1, 0.0), fe)
    seconds = time.perf_counter() - t
    timings = json.loads(ref.meta["timings_s"])
    keys = json.loads(ref.meta["experiment_keys"])
    keys["body"] = run_keys(scene, problem)["body"]
    experiments = [e for e in ("indentation", "relaxation", "gravity_static", "gravity_dynamic")
                   if e in timings]
    compute = float(sum(timings[e] for e in experiments))
    meta = {**ref.meta, "timings_s": json.dumps({**timings, "body": seconds}),
            "experiment_keys": json.dumps(keys),
            "body_computed_by": "studies.body_data: reference_fe.run.compute_item into a copy "
                                "of the reference; the other experiments as computed before"}
    body = result_of(arrays, float(np.linalg.norm(scene.gravity.acceleration)))
    write_reference(out, dataclasses.replace(ref, body=body, meta=meta))
    return {"body_s": seconds, "model_build_s": build, "reference_compute_s": compute,
            "share": seconds / compute, "load_average": list(os.getloadavg())}


def holds_body(scene: Scene, ref: Reference) -> bool:
    """Whether the reference ``ref`` holds the experiment ``body`` with the key the FE code
    would give it now (the scene's ``experiments`` asked for it)."""
    from reference_fe.run import run_keys

    keys = json.loads(ref.meta.get("experiment_keys", "{}"))
    return ref.body is not None and keys.get("body") == run_keys(scene, ref.problem)["body"]


def body_cost(ref: Reference) -> dict[str, Any]:
    """:func:`add_body_experiment`'s record of a reference ``ref`` that computed ``body``
    itself: its seconds and their share of every experiment's compute seconds (``timings_s``,
    summed over the ranks; not the mesh's, not the wall ``total``)."""
    timings = json.loads(ref.meta["timings_s"])
    compute = float(sum(v for k, v in timings.items() if k not in ("mesh", "total")))
    return {"body_s": timings["body"], "reference_compute_s": compute,
            "share": timings["body"] / compute, "computed_by": "the reference stage"}


def run_variant(scene: Scene, body_data: str, folder: Path, reference: Path,
                volume: bool | str | None = None) -> dict[str, Any]:
    """Calibrate ``scene`` fitting ``body_data`` on ``reference`` (hard-linked into
    ``folder``; ``volume``: another ``particle.volume``, None: the scene's), run the gravity
    test and the report there (the stages' runners); the numbers of :func:`variant_numbers`.
    A folder whose report exists is read, not rerun."""
    from pipelines.runners.calibrate import run_calibrate
    from pipelines.runners.common import GRAVITY, PARAMS, REFERENCE, REPORT, Context
    from pipelines.runners.gravity import run_gravity_stage
    from pipelines.runners.reference import scene_after_reference
    from pipelines.runners.report import run_report

    variant = replace(scene, experiments=[*scene.experiments, "body"]
                      if "body" not in scene.experiments else list(scene.experiments),
                      # every set's cross-validation score from the fit of every kind only:
                      # the other fits' times are the product's
                      calibration={"body_data": body_data,
                                   "body_candidates": body_data == EVERY_KIND},
                      **({} if volume is None else {"particle": {"volume": volume}}))
    folder.mkdir(parents=True, exist_ok=True)
    target = folder / REFERENCE
    if not target.exists():
        os.link(reference, target)
    if not (folder / REPORT).is_file():
        t = time.perf_counter()
        # less the held-out tests whose FE run failed, as the pipeline's stages run it
        variant = scene_after_reference(Context(variant, folder, progress=False, ranks=1))
        context = Context(variant, folder, progress=False, ranks=1)
        run_calibrate(context)
        # the gravity stage's experiments (the second support's too): its file's key
        gravity = tuple(e for e in variant.experiments if e in HELD_OUT_EXPERIMENTS)
        run_gravity_stage(dataclasses.replace(context, experiments=gravity))
        run_report(dataclasses.replace(context, experiments=variant.experiments,
                                       upstream=(REFERENCE, PARAMS, GRAVITY)))
        log.info("%s, body_data %s: %.0f s", scene.name, body_data, time.perf_counter() - t)
    return variant_numbers(json.loads((folder / REPORT).read_text()))


def variant_numbers(report: dict[str, Any]) -> dict[str, Any]:
    """The study's numbers of one ``report.json``: the calibrated model's and the baseline's
    surface and gravity errors (:func:`studies.viscoelastic_volume.report_numbers`), and the
    whole-body record (fitted or predicted errors of every item, the weight, the
    cross-validation's candidate scores)."""
    return {**report_numbers(report), "body": report.get("body") or {}}


#: scores within this fraction of the lowest are a tie (the set with fewer kinds wins)
TIE = 0.01


#: the volume terms in the order a tie prefers them (the fewer parameters and the cheaper
#: haptic step first); rows without one are the scenes' own
VOLUMES = ("elastic", "viscoelastic")


def every_kind_rows(rows: dict[str, Any]) -> dict[str, Any]:
    """The rows of the fits of every kind (which score every set): ``{volume or "": row}``
    (a row ``<EVERY_KIND> (<volume>)`` of another volume term, ``<EVERY_KIND>`` the scene's)."""
    out = {}
    for name, row in rows.items():
        kinds, _, volume = name.partition(" (")
        if kinds == EVERY_KIND:
            out[volume.rstrip(")")] = row
    return out


def choose(result: dict[str, Any], round_: str = "round_2") -> dict[str, Any]:
    """The rule of the module docstring on the scenes' candidate scores (those of the fits of
    every kind, ``round_`` of their cross-validation): {"scores": summed per candidate,
    "chosen"}. With fits of more than one volume term, a candidate is a set of kinds with a
    volume term (``"<set> (<volume>)"``), each score with its fit's ``left_out`` (the
    residual its rows' compression leaves out, :attr:`calibration.gradient.GroupedRows.
    scored_left_out`), so the models' scores compare; a tie (within :data:`TIE`) goes to the
    fewer kinds, then to the volume term first in :data:`VOLUMES`."""
    totals: dict[str, float] = {}
    order: dict[str, tuple[int, int]] = {}
    for entry in result["scenes"].values():
        fits = every_kind_rows(entry["rows"])
        for volume, row in fits.items():
            cv = row.get("body", {}).get("cv", {})
            for name, score in (cv.get(round_) or cv.get("round_1") or {}).items():
                label = name if len(fits) == 1 else f"{name} ({volume})"
                totals[label] = (totals.get(label, 0.0) + score["score"]
                                 + (score.get("left_out", 0.0) if len(fits) > 1 else 0.0))
                order[label] = (0 if name == "none" else name.count("+") + 1,
                                VOLUMES.index(volume) if volume in VOLUMES else 0)
    if not totals:
        return {"scores": {}, "chosen": None}
    lowest = min(totals.values())
    ties = [n for n, v in totals.items() if v <= (1.0 + TIE) * lowest]
    chosen = min(ties, key=lambda n: (*order[n], totals[n]))
    return {"scores": totals, "chosen": chosen, "round": round_}


def whole_body_score(record: dict[str, Any], variant: str = "calibrated") -> float | None:
    """Mean squared error over every whole-body item of ``variant`` (None if it has no
    response): the whole-body part of the calibration data's error, fitted or predicted."""
    errors = record.get("variants", {}).get(variant, {}).get("item_errors")
    if errors is None or any(e is None for e in errors):
        return None
    return float(np.mean(np.square(errors)))


def study(scene_paths: list[str | Path], variants: tuple[str, ...] = VARIANTS,
          folder: Path = FOLDER, out: Path = OUT,
          volumes: tuple[str | None, ...] = (None,)) -> dict[str, Any]:
    """Every scene of ``scene_paths`` with each ``calibration.body_data`` of ``variants``,
    for each ``particle.volume`` of ``volumes`` (None: the scene's; another: rows
    ``<variant> (<volume>)``); written to ``out`` after each (module docstring)."""
    result: dict[str, Any] = {"variants": list(variants), "scenes": {},
                              "load_average_start": list(os.getloadavg())}
    if out.is_file():  # a rerun keeps the rows it has (the folders' reports are reused)
        result["scenes"] = json.loads(out.read_text()).get("scenes", {})
    for path in scene_paths:
        scene = load_scene(path)
        source = Path("runs") / scene.name / "reference.h5"
        if not source.is_file():
            raise DataFileError(f"{source}: the scene's FE reference is not computed; the "
                                "study adds the body experiment to it and never recomputes it")
        base = folder / scene.name
        reference = base / "reference.h5"
        entry = result["scenes"].setdefault(scene.name, {"rows": {}})
        computed = read_reference(source)
        if holds_body(scene, computed):  # the reference stage computed it: its own time
            entry["fe_cost"] = body_cost(computed)
            reference = source
        elif not reference.is_file():
            entry["fe_cost"] = add_body_experiment(scene, source, reference)
        elif "fe_cost" not in entry:  # the copy was made before: time the experiment again
            timing = base / "reference-timing.h5"
            entry["fe_cost"] = add_body_experiment(scene, source, timing)
            timing.unlink()
        for volume in volumes:
            for name in variants:
                row = name if volume is None else f"{name} ({volume})"
                where = base / (name.replace("+", "_")
                                + ("" if volume is None else f"-{volume}"))
                entry["rows"][row] = run_variant(scene, name, where, reference,
                                                 {"elastic": True}.get(volume, volume))
                entry["rows"][row]["whole_body_score"] = whole_body_score(
                    entry["rows"][row]["body"])
                result["load_average_end"] = list(os.getloadavg())
                result["choice"] = choose(result)
                write_json(out, result)
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m studies.body_data",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--scene", action="append", required=True,
                        help="scene TOML whose runs/<name>/reference.h5 is computed (repeat)")
    parser.add_argument("--variants", default=",".join(VARIANTS),
                        help="comma-separated calibration.body_data values")
    parser.add_argument("--folder", type=Path, default=FOLDER, help="run folders' parent")
    parser.add_argument("--out", type=Path, default=OUT, help="the results as JSON")
    parser.add_argument("--volume", choices=VOLUMES, action="append",
                        help="another particle.volume than the scenes' (rows named so; "
                             "repeat: each, and the choice is among them)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    study(args.scene, tuple(args.variants.split(",")), args.folder, args.out,
          tuple(args.volume) if args.volume else (None,))


if __name__ == "__main__":
    main()
