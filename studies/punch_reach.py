"""Does the flat punch hold only the tissue its face reaches, and does it matter to the FE?

A flat punch (:mod:`forcecal.indenter`) holds every surface node that projects within its
radius on the test point's tangent plane, faces the same way (outward normals less than 90
degrees apart) and is connected to the point through such nodes. On a curved surface that
set can hold nodes lying far below the punch's face: nodes a rigid flat punch pushed to the
scene's depth never touches, dragged along as if glued to it. The FE reference and the
particle model share the rule, so a calibration stays consistent; the question is how far
the rule is from a punch, and whether the FE's failures follow it.

Two parts:

* **geometry** (each ``--scene`` with a punch, no FE): per test point, the footprint's
  particles, those farther from the plane of the punch's face than the scene's deepest
  indentation (``beyond``: out of the punch's reach), the largest such distance
  (``max_gap_m``) and the largest angle between a held node's outward normal and the test
  point's (``max_normal_angle_deg``);
* **FE** (``--fe SCENE:VERTEX``): that test point's static indentation and relaxation
  (:func:`reference_fe.run.compute_item`, the scene's FE settings, one process), each with
  three footprints: the scene's (``rule``), the same radius holding only the nodes within
  the scene's depth of the face (``reach``: the rule plus that condition, on the particle
  mesh and on the refined FE mesh alike; a what-if, not the product's rule) and the rule at
  ``--radius`` (``radius``). Each run records whether it reached its end, how far it got,
  its wall time and the normal force at its end.

``python -m studies.punch_reach --scene scenes/liver_punch.toml [--scene ...] [--fe
runs/corpus_recipe/scenes/torus.toml:6 --radius 0.008] [--out
runs/studies/punch_reach.json]`` (the geometry takes seconds per scene; an FE run on the
corpus torus takes 0.3-6 min).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import time
from pathlib import Path
from typing import Any, Iterator
from unittest import mock

import numpy as np

from calibration.reach import experiment_depths
from forcecal import indenter
from forcecal.problem import Problem, build_problem
from forcecal.scene import Scene, load_scene, replace

log = logging.getLogger(__name__)


def deepest(scene: Scene) -> float:
    """The deepest indentation the scene's punch makes [m] (of the experiments the
    calibration fits, :func:`calibration.reach.experiment_depths`)."""
    return max(experiment_depths(scene).values())


def point_geometry(problem: Problem, slot: int, radius: float, depth: float
                   ) -> dict[str, Any]:
    """The footprint of test point ``slot`` for a punch of ``radius`` [m] pushed ``depth``
    [m]: ``vertex``, ``nodes`` (footprint particles), ``beyond`` (those farther than
    ``depth`` from the plane of the punch's face), ``max_gap_m`` [m] and
    ``max_normal_angle_deg`` [deg] (module docstring)."""
    mesh = problem.mesh
    vertex, normal = int(problem.test_points[slot]), problem.normals[slot]
    held = indenter.punch_footprint(mesh, vertex, normal, radius, fixed=problem.fixed)
    gap = indenter.face_gaps(mesh, vertex, normal, held)
    outward = mesh.vertex_normals[held] / np.linalg.norm(mesh.vertex_normals[held],
                                                         axis=1)[:, None]
    centre = mesh.vertex_normals[vertex] / np.linalg.norm(mesh.vertex_normals[vertex])
    angle = np.degrees(np.arccos(np.clip(outward @ centre, -1.0, 1.0)))
    return {"vertex": vertex, "nodes": int(len(held)), "beyond": int(np.sum(gap > depth)),
            "max_gap_m": float(gap.max()), "max_normal_angle_deg": float(angle.max())}


def footprint_geometry(scene: Scene, problem: Problem | None = None) -> list[dict[str, Any]]:
    """:func:`point_geometry` of every test point of a punch scene (calibration points
    first), with the scene's radius and :func:`deepest` depth."""
    problem = build_problem(scene) if problem is None else problem
    return [point_geometry(problem, slot, scene.indentation.radius, deepest(scene))
            for slot in range(len(problem.test_points))]


def summary(rows: list[dict[str, Any]], depth: float) -> dict[str, Any]:
    """What :func:`footprint_geometry`'s rows say in a few numbers."""
    gaps = np.array([r["max_gap_m"] for r in rows])
    return {"points": len(rows),
            "points_beyond": int(sum(r["beyond"] > 0 for r in rows)),
            "nodes": int(sum(r["nodes"] for r in rows)),
            "nodes_beyond": int(sum(r["beyond"] for r in rows)),
            "max_gap_m": float(gaps.max()), "median_max_gap_m": float(np.median(gaps)),
            "max_gap_over_depth": float(gaps.max() / depth),
            "median_max_normal_angle_deg": float(np.median(
                [r["max_normal_angle_deg"] for r in rows]))}


@contextlib.contextmanager
def within_reach(depth: float) -> Iterator[None]:
    """The footprint rule holding only the nodes within ``depth`` [m] of the plane of the
    punch's face (the ``reach`` footprint), on every mesh, while the context lasts."""
    tangential = indenter._tangential_distance

    def distance(mesh, vertex, normal):
        off_face = indenter.face_gaps(mesh, vertex, normal, np.arange(mesh.n_vertices))
        return np.where(off_face <= depth, tangential(mesh, vertex, normal), np.inf)

    with mock.patch.object(indenter, "_tangential_distance", distance):
        yield


def fe_run(scene: Scene, problem: Problem, slot: int, kind: str) -> dict[str, Any]:
    """One FE indentation or relaxation of test point ``slot`` (:func:`compute_item`, one
    process): ``completed``, ``reached`` (depth [m] or time [s] of the last converged step),
    ``wall_s``, ``normal_force_n`` at the end (None if not completed) and ``error``."""
    from forcecal.errors import ConvergenceError
    from reference_fe.model import FEModel
    from reference_fe.refine import fe_problem
    from reference_fe.run import WorkItem, compute_item

    fe = fe_problem(problem, scene.fe)
    model = FEModel(fe.problem.mesh, scene.material, scene.fe)
    start = time.perf_counter()
    row: dict[str, Any] = {"kind": kind, "completed": False, "reached": None,
                           "normal_force_n": None, "error": None}
    try:
        force = compute_item(model, scene, problem, WorkItem(kind, slot, 0.0), fe)["force"]
    except ConvergenceError as exc:
        row["reached"], row["error"] = getattr(exc, "reached", None), str(exc)[:300]
    else:
        n = problem.normals[slot] / np.linalg.norm(problem.normals[slot])
        end = (scene.indentation.depth if kind == "indentation"
               else scene.relaxation.ramp_time + scene.relaxation.hold_time)
        row.update(completed=True, reached=end, normal_force_n=float(force[-1] @ n))
    finally:
        model.destroy()
    row["wall_s"] = time.perf_counter() - start
    return row


def fe_comparison(scene_path: Path, vertex: int, radius: float) -> dict[str, Any]:
    """:func:`fe_run` of both experiments at test vertex ``vertex`` with each of the module
    docstring's three footprints (``rule``, ``reach``, ``radius``), with the footprint's
    :func:`point_geometry`. The test points are the scene's (its rule picks them); only
    this point's footprint changes."""
    scene = load_scene(scene_path)
    problem = build_problem(scene)
    slots = np.flatnonzero(problem.test_points == vertex)
    if not len(slots):
        raise SystemExit(f"vertex {vertex} is not a test point of {scene_path}")
    slot, depth = int(slots[0]), deepest(scene)
    variants = {"rule": (scene, contextlib.nullcontext()),
                "reach": (scene, within_reach(depth)),
                "radius": (replace(scene, indentation={"radius": radius}),
                           contextlib.nullcontext())}
    out: dict[str, Any] = {"scene": str(scene_path), "vertex": vertex, "depth_m": depth,
                           "radius_m": scene.indentation.radius, "smaller_radius_m": radius,
                           "variants": {}}
    for name, (variant, context) in variants.items():
        with context:
            here = point_geometry(problem, slot, variant.indentation.radius, depth)
            runs = []
            for kind in ("indentation", "relaxation"):
                log.info("%s footprint: %s at vertex %d", name, kind, vertex)
                runs.append(fe_run(variant, problem, slot, kind))
        out["variants"][name] = {"footprint": here, "runs": runs}
    return out


def measure(scenes: list[Path], fe: str | None, radius: float) -> dict[str, Any]:
    """The study's result (module docstring)."""
    result: dict[str, Any] = {"scenes": {}}
    for path in scenes:
        scene = load_scene(path)
        if scene.indentation.indenter != "punch":
            log.info("%s: no punch, skipped", path)
            continue
        rows, depth = footprint_geometry(scene), deepest(scene)
        result["scenes"][str(path)] = {"radius_m": scene.indentation.radius, "depth_m": depth,
                                       "summary": summary(rows, depth), "points": rows}
    if fe:
        path, _, vertex = fe.rpartition(":")
        result["fe"] = fe_comparison(Path(path), int(vertex), radius)
    return result


def main(argv: list[str] | None = None) -> int:
    from studies.viscoelastic_volume import write_json

    ap = argparse.ArgumentParser(prog="python -m studies.punch_reach",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, action="append", default=[],
                    help="a punch scene whose footprints to measure (repeatable)")
    ap.add_argument("--fe", help="SCENE:VERTEX, a test point whose FE runs to compare")
    ap.add_argument("--radius", type=float, default=0.008,
                    help="the smaller punch radius of the FE comparison [m]")
    ap.add_argument("--out", type=Path, default=Path("runs/studies/punch_reach.json"))
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    result = measure(args.scene, args.fe, args.radius)
    result["command"] = ("python -m studies.punch_reach"
                         + "".join(f" --scene {s}" for s in args.scene)
                         + (f" --fe {args.fe} --radius {args.radius:g}" if args.fe else ""))
    write_json(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
