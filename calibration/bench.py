"""Benchmark of the calibration: wall time and model evaluations of a full run.

:func:`bench_calibration` runs :func:`calibration.core.calibrate` on a scene
against its reference and returns a JSON-able dict (the pipelines write it to
``runs/bench/bench.json``). Goal on the default liver: <= 300 s on 2 cores (the
paper: 8 h). Without an FE reference (``synthetic=True``) the reference is made
by the particle model itself with known ring-perturbed parameters
(:func:`calibration.synthetic.ring_perturbed_params`), which times the same
work and also reports how well those curves are recovered.

``python -m calibration.bench [--scene S] [--reference R | --synthetic] [--out DIR]``
"""

from __future__ import annotations

import argparse
import json
import logging
import os
from pathlib import Path

import numpy as np

from calibration.baseline import van_gelder_params
from calibration.core import calibrate
from calibration.parametrisation import GlobalParams, StrainRange
from calibration.synthetic import ring_perturbed_params, synthetic_reference
from forcecal.errors import DataFileError
from forcecal.problem import build_problem
from forcecal.scene import load_scene

log = logging.getLogger(__name__)

GOAL_SECONDS = 300.0
PAPER_SECONDS = 8 * 3600.0


def _synthetic_liver_reference(scene, path: Path) -> None:
    """Reference from the baseline's mean stiffness, mild stiffening and ring factors."""
    problem = build_problem(scene)
    base = van_gelder_params(problem.mesh, scene.material)
    K0 = float(np.mean(base.K0))
    glob = GlobalParams(K0=K0, alpha=0.5, beta=2.0, k1=float(np.mean(base.k1)),
                        tau1=float(np.mean(base.tau1)), k2=float(np.mean(base.k2)),
                        tau2=float(np.mean(base.tau2)))
    params, _, _ = ring_perturbed_params(problem, glob, StrainRange(-0.3, 0.3))
    synthetic_reference(scene, params, path)


def bench_calibration(scene_path: str | Path = "scenes/liver.toml",
                      reference_path: str | Path | None = None,
                      out_dir: str | Path = "runs/bench/calibration", *,
                      synthetic: bool = False, workers: int | None = None,
                      progress: bool = False) -> dict:
    """Time one full calibration; returns wall time, evaluations and errors.

    Args:
        scene_path: the scene (default liver).
        reference_path: its FE reference; default ``runs/<scene name>/reference.h5``.
        out_dir: where params.h5 (and a synthetic reference) go.
        synthetic: fit a particle-made reference instead of the FE one.
        workers: parallel workers (None = the scene's setting).
    """
    scene = load_scene(scene_path)
    out_dir = Path(out_dir)
    if synthetic:
        reference_path = out_dir / "synthetic_reference.h5"
        _synthetic_liver_reference(scene, reference_path)
    elif reference_path is None:
        reference_path = Path("runs") / scene.name / "reference.h5"
    if not Path(reference_path).is_file():
        raise DataFileError(f"{reference_path} does not exist: compute the FE reference first "
                            "(make reference) or benchmark with synthetic=True")
    result = calibrate(scene, reference_path, out_dir / "params.h5", progress=progress,
                       workers=workers)
    cost_evaluations = {k: v for k, v in result.evaluations.items() if k != "point_curves"}
    return {"scene": scene.name, "reference": str(reference_path), "synthetic": synthetic,
            "workers": scene.calibration.workers if workers is None else workers,
            "cpu_count": os.cpu_count(), "wall_time_s": result.wall_time,
            "goal_s": GOAL_SECONDS, "paper_s": PAPER_SECONDS,
            "speedup_vs_paper": PAPER_SECONDS / result.wall_time,
            "point_curve_evaluations": result.evaluations["point_curves"],
            "cost_evaluations": cost_evaluations,
            "errors": result.error_summary(), "warnings": list(result.warnings)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m calibration.bench")
    parser.add_argument("--scene", default="scenes/liver.toml")
    parser.add_argument("--reference", default=None)
    parser.add_argument("--synthetic", action="store_true")
    parser.add_argument("--out", default="runs/bench/calibration")
    parser.add_argument("--workers", type=int, default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    report = bench_calibration(args.scene, args.reference, args.out, synthetic=args.synthetic,
                               workers=args.workers, progress=True)
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
