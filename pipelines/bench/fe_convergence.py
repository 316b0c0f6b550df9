"""FE convergence of the punch reference: ``fe_convergence`` in ``bench.json``.

For three test points of the punch scene (``scenes/liver_punch.toml``; ``--quick``:
the tiny liver with a punch), the full-depth punch force and the largest static
gravity sag (read at the particle vertices) on several uniform refinements of the
particle mesh (``fe.refine``, :mod:`reference_fe.refine`), with dofs and wall time of
each level. ``punch_force_change`` and ``sag_change`` are the relative changes of the
scene's own level against the finest computed (largest over the points), and
``*_change_two_finest`` those between the two finest levels.

``python -m pipelines.bench.fe_convergence [--scene FILE] [--levels 0 1 2] [--element TH]
[--out FILE.json]`` runs it alone (each level is appended to ``--out`` as it finishes,
so a long run can be followed and interrupted).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from forcecal.errors import ForcecalError
from forcecal.logs import configure_logging
from forcecal.problem import Problem, build_problem
from forcecal.scene import Scene, load_scene, replace
from forcecal.schedules import indentation_depths

log = logging.getLogger("pipelines.bench.fe_convergence")  # also when run as __main__

ROOT = Path(__file__).resolve().parents[2]
PUNCH_SCENE = ROOT / "scenes" / "liver_punch.toml"
LEVELS = (0, 1, 2)  # the default liver's TH: 5k, 36k, 261k dofs


def study_points(problem: Problem, radius: float, n: int = 3) -> np.ndarray:
    """``n`` test points spread through the scene's list (first, middle, last) among those
    whose punch footprint is valid (>= 3 particles, off the clamp)."""
    from forcecal.errors import SceneError
    from forcecal.indenter import punch_footprint

    valid = []
    for vertex, normal in zip(problem.test_points, problem.normals):
        try:
            punch_footprint(problem.mesh, vertex, normal, radius, fixed=problem.fixed)
        except SceneError:
            continue
        valid.append(int(vertex))
    if len(valid) < n:
        raise SceneError(f"only {len(valid)} test points have a valid footprint of "
                         f"indentation.radius = {radius} m; the study needs {n}")
    return np.asarray(valid)[np.linspace(0, len(valid) - 1, n).round().astype(int)]


def measure_level(scene: Scene, problem: Problem, points: np.ndarray, level: int, *,
                  sag: bool = True) -> dict:
    """Full-depth punch force at ``points`` and (``sag``) the largest static sag on
    ``fe.refine = level``."""
    from reference_fe import experiments
    from reference_fe.model import FEModel
    from reference_fe.refine import check_memory, fe_problem
    from reference_fe.run import indenter_dofs

    fe_section = dataclasses.replace(scene.fe, refine=level)
    check_memory(problem.mesh, fe_section)
    t0 = time.perf_counter()
    fe = fe_problem(problem, fe_section)
    model = FEModel(fe.problem.mesh, scene.material, fe_section)
    depths = indentation_depths(scene.indentation)
    index = {int(v): k for k, v in enumerate(problem.test_points)}
    forces = []
    for vertex in points:
        k = index[int(vertex)]
        dofs = indenter_dofs(model, scene, problem, fe, k)
        normal = problem.normals[k]
        curve = experiments.held_indentation_curve(model, fe.problem.fixed, dofs, normal, depths,
                                                   f"punch at vertex {vertex}")
        forces.append(float(curve[-1] @ normal))
        log.info("fe_convergence: level %d, point %d: %.6g N", level, vertex, forces[-1])
    t1 = time.perf_counter()
    g = scene.gravity
    max_sag = None
    if sag:
        u = experiments.gravity_static(model, fe.problem.fixed, g.acceleration,
                                       g.static_load_steps)[fe.vertex_map]
        max_sag = float(np.linalg.norm(u, axis=1).max())
    t2 = time.perf_counter()
    return {"level": level, "element": fe_section.element, "dofs": model.n_dofs,
            "fe_vertices": fe.problem.mesh.n_vertices, "wall_s": t2 - t0,
            "wall_s_punch_per_point": (t1 - t0) / max(len(points), 1), "wall_s_sag": t2 - t1,
            "punch_force": forces, "max_sag": max_sag}


def summarise(rows: list[dict], default_level: int) -> dict:
    """The changes of the module docstring from the measured levels."""
    by_level = {r["level"]: r for r in rows}
    finest = by_level[max(by_level)]

    def change(a: dict, b: dict) -> tuple[float, float]:
        f = np.asarray(a["punch_force"]) / np.asarray(b["punch_force"]) - 1.0
        return float(np.max(np.abs(f))), float(abs(a["max_sag"] / b["max_sag"] - 1.0))

    out = {"levels": rows, "default_level": default_level, "finest_level": finest["level"]}
    if default_level in by_level:
        out["punch_force_change"], out["sag_change"] = change(by_level[default_level], finest)
    if len(rows) >= 2:
        second = by_level[sorted(by_level)[-2]]
        out["punch_force_change_two_finest"], out["sag_change_two_finest"] = change(second,
                                                                                    finest)
    return out


def convergence(scene: Scene, levels: Sequence[int], *, out: Path | None = None,
                points: Sequence[int] | None = None, sag: bool = True) -> dict:
    """The study on ``scene`` (a punch scene), one level after the other, coarsest first.

    ``points`` and ``sag=False`` restrict it (to split a level over several processes: the
    changes are then left out, :func:`summarise` needs every quantity)."""
    problem = build_problem(scene)
    points = (study_points(problem, scene.indentation.radius) if points is None
              else np.asarray(points, dtype=np.int64))
    rows: list[dict] = []
    result: dict = {}
    for level in sorted(levels):
        rows.append(measure_level(scene, problem, points, level, sag=sag))
        result = {"scene": scene.name, "points": points.tolist(),
                  "radius_m": scene.indentation.radius, "depth_m": scene.indentation.depth,
                  **(summarise(rows, scene.fe.refine) if sag else {"levels": rows})}
        if out is not None:
            out.write_text(json.dumps(result, indent=1))
        log.info("fe_convergence: level %d done (%d dofs, %.0f s)", level, rows[-1]["dofs"],
                 rows[-1]["wall_s"])
    return result


def study(scene: Scene, cache_folder: Path, quick: bool) -> dict:
    """``make bench`` item: ``{"fe_convergence": ...}`` on the punch scene (the bench scene
    with ``--quick``, given a punch of 1.5 mean surface edge lengths if it has none)."""
    punch = load_scene(PUNCH_SCENE) if not quick else _with_punch(scene)
    return {"fe_convergence": convergence(punch, LEVELS,
                                          out=Path(cache_folder) / "fe_convergence.json")}


def _with_punch(scene: Scene) -> Scene:
    from forcecal.indenter import surface_edges

    if scene.indentation.indenter == "punch":
        return scene
    mesh = build_problem(scene).mesh
    x = mesh.vertices[surface_edges(mesh)]
    h = float(np.linalg.norm(x[:, 1] - x[:, 0], axis=1).mean())
    return replace(scene, indentation={"indenter": "punch", "radius": 1.5 * h},
                   fe={"element": "TH"})


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipelines.bench.fe_convergence",
                                     description="FE convergence of the punch reference (JSON)")
    parser.add_argument("--scene", default=str(PUNCH_SCENE), help="a punch scene TOML file")
    parser.add_argument("--levels", type=int, nargs="+", default=list(LEVELS))
    parser.add_argument("--element", help="override fe.element (P2, TH)")
    parser.add_argument("--out", help="JSON file, rewritten after every level")
    parser.add_argument("--points", type=int, nargs="*", help="test vertices (default: 3 "
                        "spread through the scene's list); a partial run has no summary")
    parser.add_argument("--no-sag", action="store_true", help="skip the static sag")
    args = parser.parse_args(argv)
    configure_logging(loggers=(log.name,))
    try:
        scene = load_scene(args.scene)
        if args.element:
            scene = replace(scene, fe={"element": args.element})
        result = convergence(scene, args.levels, out=Path(args.out) if args.out else None,
                             points=args.points, sag=not args.no_sag)
    except ForcecalError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
