"""How much the FE reference depends on its discretisation: :func:`discretisation_study`.

For a few calibration points (full-depth indentation force) and the static
gravity sag it compares P1, P2, Taylor-Hood and P2 on a uniformly refined mesh,
and P2 with quadrature degrees 2/4/6 (the degree study justifies
``fe.quadrature_degree``: the force should stop changing). Refinement uses
``dolfinx.mesh.refine`` (uniform, every tet split into 8, the original vertices
kept), so each test point is still a vertex: it is mapped by its coordinates,
its inward normal is unchanged (every face around it is split into four
coplanar ones) and the clamped base is the same surface (fixed vertices and
the midpoints of the edges between them). Meant for ``make bench``: at the
default liver size the refined P2 model has ~40 000 dofs and takes minutes.

Under MPI (``mpirun -n K``) the variants are shared out over the ranks, each
computed by one process as in a serial run (the refined one, which takes longest,
on rank 0, the others on the other ranks), and gathered on every rank: the study
then takes about as long as its refined variant.

``python -m reference_fe.sensitivity --scene FILE [--points ID ...] [--out FILE]``
prints the study as JSON (or writes it to ``FILE``; under MPI rank 0 does).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from typing import Sequence

import numpy as np
from mpi4py import MPI

from forcecal.errors import ForcecalError
from forcecal.h5io import atomic_path
from forcecal.logs import configure_logging
from forcecal.problem import Problem, build_problem
from forcecal.scene import Scene, load_scene
from forcecal.schedules import indentation_depths
from reference_fe import experiments
from reference_fe.model import FEModel
from reference_fe.refine import refine_problem, refine_uniformly  # noqa: F401 (re-exported)

log = logging.getLogger(__name__)


def _measure(scene: Scene, problem: Problem, points: np.ndarray, normals: np.ndarray,
             fe_changes: dict) -> dict:
    """Full-depth indentation forces at ``points`` and the static sag, with wall times."""
    fe = dataclasses.replace(scene.fe, **fe_changes)
    t0 = time.perf_counter()
    model = FEModel(problem.mesh, scene.material, fe)
    t1 = time.perf_counter()
    depths = indentation_depths(scene.indentation)
    forces = [float(experiments.indentation_curve(model, problem.fixed, int(p), n, depths)[-1]
                    @ n) for p, n in zip(points, normals)]
    t2 = time.perf_counter()
    g = scene.gravity
    sag = experiments.gravity_static(model, problem.fixed, g.acceleration, g.static_load_steps)
    t3 = time.perf_counter()
    return {"element": fe.element, "quadrature_degree": fe.quadrature_degree,
            "n_vertices": problem.mesh.n_vertices, "n_dofs": model.n_dofs,
            "indentation_force_N": forces,
            "max_sag_m": float(np.linalg.norm(sag, axis=1).max()),
            "wall_time_s": {"build": t1 - t0, "indentation_per_point": (t2 - t1) / len(points),
                            "gravity_static": t3 - t2}}


def discretisation_study(scene: Scene, points: Sequence[int] | None = None, *,
                         problem: Problem | None = None,
                         quadrature_degrees: Sequence[int] = (2, 4, 6)) -> dict:
    """Indentation force at full depth and max static sag for several discretisations.

    Args:
        points: test vertices (ids in the scene's mesh); default: three calibration
            points spread through the list.
        quadrature_degrees: degrees tried with P2 (the others use ``scene.fe``'s).

    Returns:
        A JSON-ready dict: ``points``, ``depth_m``, ``variants`` (label -> element,
        quadrature degree, vertices, dofs, ``indentation_force_N`` per point,
        ``max_sag_m``, wall times) and ``relative_to_scene_fe`` (label -> relative
        change of each force and of the sag against the scene's own discretisation),
        plus ``quadrature_change_4_to_6`` when degrees 4 and 6 are both tried.
    """
    problem = build_problem(scene) if problem is None else problem
    if points is None:
        cal = problem.calibration
        points = cal[np.linspace(0, len(cal) - 1, 3).round().astype(int)]
    points = np.asarray(points, dtype=np.int64)
    normals = problem.mesh.inward_normals(points)
    q = scene.fe.quadrature_degree
    degrees = sorted(set(quadrature_degrees) | {q})  # the scene's own degree is the baseline
    variants = {f"P2 q={d}": ("coarse", {"element": "P2", "quadrature_degree": d})
                for d in degrees}
    variants.update({f"P1 q={q}": ("coarse", {"element": "P1"}),
                     f"TH q={q}": ("coarse", {"element": "TH"}),
                     f"P2 q={q} refined": ("refined", {"element": "P2"})})
    comm = MPI.COMM_WORLD
    mine, error = {}, None
    try:
        for label, (which, changes) in variants.items():
            if variant_rank(which, list(variants).index(label), comm.size) != comm.rank:
                continue
            log.info("discretisation study: %s", label)
            if which == "refined":
                refined, vertex_map = refine_problem(problem, points)
                mine[label] = _measure(scene, refined, vertex_map[points], normals, changes)
            else:
                mine[label] = _measure(scene, problem, points, normals, changes)
    except ForcecalError as exc:
        if comm.size == 1:
            raise
        error = f"rank {comm.rank}: {type(exc).__name__}: {exc}"  # the others must not wait
    parts = comm.allgather((mine, error))
    errors = [e for _, e in parts if e is not None]
    if errors:
        raise ForcecalError(f"discretisation study failed: {errors[0]}")
    gathered = {k: v for part, _ in parts for k, v in part.items()}
    results = {label: gathered[label] for label in variants}  # the serial order
    base = results[f"{scene.fe.element} q={q}"]
    out = {"points": points.tolist(), "depth_m": scene.indentation.depth,
           "refinement": "dolfinx.mesh.refine, uniform (each tet into 8), points mapped by "
                         "coordinates",
           "variants": results,
           "relative_to_scene_fe": {
               label: {"force": (np.asarray(r["indentation_force_N"])
                                 / np.asarray(base["indentation_force_N"]) - 1).tolist(),
                       "sag": r["max_sag_m"] / base["max_sag_m"] - 1}
               for label, r in results.items()}}
    if {4, 6} <= set(degrees):
        f4 = np.asarray(results["P2 q=4"]["indentation_force_N"])
        f6 = np.asarray(results["P2 q=6"]["indentation_force_N"])
        out["quadrature_change_4_to_6"] = float(np.max(np.abs(f6 / f4 - 1)))
    return out


def variant_rank(which: str, index: int, size: int) -> int:
    """The rank (of ``size``) that computes variant number ``index`` (``which``: "coarse" or
    "refined"): the refined one on rank 0, the coarse ones round-robin over the others."""
    if size == 1:
        return 0
    return 0 if which == "refined" else 1 + index % (size - 1)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m reference_fe.sensitivity",
                                     description="FE discretisation study of a scene (JSON)")
    parser.add_argument("--scene", required=True, help="scene TOML file")
    parser.add_argument("--points", type=int, nargs="*", help="test vertex ids (default: 3 "
                        "calibration points)")
    parser.add_argument("--out", default=None, help="write the JSON here instead of printing it")
    args = parser.parse_args(argv)
    rank = MPI.COMM_WORLD.rank
    configure_logging(loggers=(__name__,), prefix=f"[rank {rank}] " if MPI.COMM_WORLD.size > 1
                      else "")
    try:
        study = discretisation_study(load_scene(args.scene), args.points or None)
    except ForcecalError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if rank == 0:
        if args.out:
            with atomic_path(args.out) as tmp:
                tmp.write_text(json.dumps(study, indent=1))
        else:
            print(json.dumps(study, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
