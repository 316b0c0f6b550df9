"""Which calibration setting predicts points it was not fitted to: k-fold cross-validation of
whole calibrations over a scene's calibration points.

The gradient method chooses its smoothness weight by cross-validation on one linearisation
at the global fit (:func:`calibration.gradient_solver.cross_validate`), which is reliable
only near that fit. A choice of the fit's *structure*, such as whether each tet's ``kv`` is
fitted (``calibration.kv_per_tet``), is judged here the slow, plain way: per variant and
fold, the whole calibration (global fits, gradient fit, gravity check) of the scene with the
fold's calibration points taken out, which then predicts the fold's curves. The folds are
the gradient method's own (:func:`calibration.gradient_solver.folds_of`, ``calibration.
cv_folds`` of them). The scene's held-out points are never fitted (as in every calibration)
and never read: a scene needs :data:`forcecal.scene.MIN_HELD_OUT` held-out points, so the
derived scenes hold them out next to the fold, and only the fold's errors are taken; the FE
reference is sliced to the scene's points (:func:`pipelines.bench.configs.sliced_reference`).

The score of a variant is the mean over every calibration point (each predicted once, by
the fit that did not see it) of its relative RMS errors, indentation and relaxation
averaged; the lowest wins. ``score_vector`` (and ``mean_vector``, ``per_point_vector``) is
the same of the whole force vector's error (:func:`calibration.metrics.force_vector_errors`,
what ``report.json`` quotes as ``force_vector_errors``), reported beside it, not chosen by.

``python -m studies.fold_cv --scene scenes/liver_punch.toml [--run DIR] [--variants JSON]
[--work DIR] [--out FILE]`` (5 x 2 calibrations, minutes on the punch scene); ``--variants``
maps a label to ``[calibration]`` changes, by default ``{"kv per tet": {}, "kv global":
{"kv_per_tet": false}}``; a change whose value is a table changes that section instead
(``{"nodal": {"particle": {"volume_element": "nodal"}}}``), for choices outside the
calibration such as the volume term's element. The committed results are ``runs/studies/fold_cv*.json``
(``docs/studies.md`` lists each with its command and its choice).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from calibration.metrics import force_vector_errors
from forcecal.h5io import read_reference, write_reference
from forcecal.scene import load_scene
from studies._finished_run import parse_study, run_folder, study_parser, write_result
from pipelines.runners.common import PARAMS, REFERENCE

log = logging.getLogger(__name__)

EXPERIMENTS = ("indentation", "relaxation")
DEFAULT_VARIANTS = {"kv per tet": {}, "kv global": {"kv_per_tet": False}}


def sections(changes: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """A variant's ``changes`` by scene section: a table value is that section's changes, the
    other keys are ``[calibration]``'s."""
    out = {name: dict(value) for name, value in changes.items() if isinstance(value, dict)}
    bare = {name: value for name, value in changes.items() if not isinstance(value, dict)}
    if bare:
        out.setdefault("calibration", {}).update(bare)
    return out


def study(scene_path: str | Path, run: str | Path | None, variants: dict[str, dict[str, Any]],
          work: str | Path | None = None) -> dict[str, Any]:
    """The cross-validation of ``variants`` (label -> ``[calibration]`` changes) on the
    calibration points of the scene's finished run folder ``run`` (its ``reference.h5``);
    calibrations are written under ``work`` (default ``<run>/cache/fold_cv``)."""
    from calibration.core import calibrate
    from calibration.gradient_solver import folds_of
    from pipelines.bench.configs import derived_scene, sliced_reference

    scene = load_scene(scene_path)
    run = run_folder(scene, run)
    work = Path(work) if work is not None else run / "cache" / "fold_cv"
    reference = read_reference(run / REFERENCE)
    points = np.array([int(p) for p in reference.problem.calibration])
    held_out = [int(p) for p in reference.problem.held_out]  # along for the minimum, unread
    folds = folds_of(len(points), scene.calibration.cv_folds)
    out: dict[str, Any] = {"scene": scene.name, "points": points.tolist(),
                           "folds": [points[f].tolist() for f in folds], "variants": {}}
    for label, changes in variants.items():
        predicted = {e: np.full(len(points), np.nan) for e in (*EXPERIMENTS, "global")}
        vector = {e: np.full(len(points), np.nan) for e in EXPERIMENTS}
        seconds = []
        for k, fold in enumerate(folds):
            train = np.setdiff1d(points, points[fold])
            folder = work / label.replace(" ", "_") / f"fold{k}"
            sub = derived_scene(scene, f"{scene.name}_cv", {
                "test_points": {"calibration": train.tolist(),
                                "held_out": points[fold].tolist() + held_out},
                **sections(changes)}, folder)
            sub_reference = sliced_reference(reference, sub)
            write_reference(folder / REFERENCE, sub_reference)
            log.info("fold cv: %s, fold %d/%d: fitted to %d points, predicting %s", label,
                     k + 1, len(folds), len(train), points[fold].tolist())
            t = time.perf_counter()
            result = calibrate(sub, folder / REFERENCE, folder / PARAMS, progress=False)
            seconds.append(time.perf_counter() - t)
            row = {int(v): i for i, v in enumerate(result.problem.test_points)}
            at = [row[int(v)] for v in points[fold]]
            for e in EXPERIMENTS:
                predicted[e][fold] = result.variants["calibrated"].errors[e][at]
                vector[e][fold] = force_vector_errors(
                    result.variants["calibrated"].forces[e][at],
                    getattr(sub_reference, e).force[at], sub_reference.problem.normals[at])[0]
            predicted["global"][fold] = np.mean(
                [result.variants["global"].errors[e][at] for e in EXPERIMENTS], axis=0)
        means = {e: float(predicted[e].mean()) for e in EXPERIMENTS}
        vector_means = {e: float(vector[e].mean()) for e in EXPERIMENTS}
        out["variants"][label] = {
            "changes": changes, "per_point": {e: predicted[e].tolist() for e in EXPERIMENTS},
            "mean": means, "score": float(np.mean(list(means.values()))),
            "per_point_vector": {e: vector[e].tolist() for e in EXPERIMENTS},
            "mean_vector": vector_means, "score_vector": float(np.mean(list(
                vector_means.values()))),
            "global_fit_score": float(predicted["global"].mean()),
            "calibration_s": seconds}
    out["chosen"] = min(out["variants"], key=lambda v: out["variants"][v]["score"])
    return out


def main(argv: list[str] | None = None) -> None:
    parser = study_parser("studies.fold_cv", __doc__)
    parser.add_argument("--variants", type=json.loads, default=DEFAULT_VARIANTS,
                        help="JSON: label -> [calibration] changes (a table value: that section's)")
    parser.add_argument("--work", help="folder of the fold calibrations")
    args = parse_study(parser, argv)
    result = study(args.scene, args.run, args.variants, args.work)
    print(f"{'variant':16s} {'indentation %':>14s} {'relaxation %':>13s} {'score %':>8s} "
          f"{'global fit %':>13s} {'vector score %':>15s}")
    for label, v in result["variants"].items():
        print(f"{label:16s} {100 * v['mean']['indentation']:14.2f} "
              f"{100 * v['mean']['relaxation']:13.2f} {100 * v['score']:8.2f} "
              f"{100 * v['global_fit_score']:13.2f} {100 * v['score_vector']:15.2f}")
    print(f"chosen: {result['chosen']}")
    write_result(parser, args.out, result)


if __name__ == "__main__":
    main()
