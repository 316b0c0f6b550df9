"""FE convergence of the punch reference: ``fe_convergence`` in ``bench.json``.

For three test points of the punch scene (``scenes/liver_punch.toml``; ``--quick``:
the tiny liver with a punch), the full-depth punch force on its FE mesh refined 0, 1, ...
times near the punch's rim (``fe.local_refine``, :func:`reference_fe.refine.rim_refined_problem`:
where a rigid punch's stress is singular), and the largest static gravity sag (read at the
particle vertices) on the mesh refined 0, 1, ... times near the clamp's rim (the gravity
runs' singular line), with dofs and wall time of each level. ``punch_force_change`` is the
relative change of the scene's ``fe.local_refine`` against the finest level computed
(largest over the points), ``sag_change`` that of the gravity runs' mesh (no rim
refinement: the scene's ``fe.refine``) against the finest sag level, and
``*_change_two_finest`` those between the two finest levels of each quantity.

``python -m pipelines.bench.fe_convergence [--scene FILE] [--levels 0 1 2 3 4]
[--sag-levels 0 1 2] [--element TH] [--out FILE.json]`` runs it alone (each level is
written to ``--out`` as it finishes, so a long run can be followed and interrupted).
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
LEVELS = (0, 1, 2, 3, 4)  # punch rim refinements: TH 5k-6k, 8k, 13k, 24k, 46k dofs
SAG_LEVELS = (0, 1, 2)  # clamp rim refinements: TH 5k, 15k, 38k dofs


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
    """Full-depth punch force at ``points`` on their meshes refined ``level`` times near the
    punch's rim and (``sag``) the largest static sag on the mesh refined ``level`` times near
    the clamp's rim (``points`` empty: the sag alone)."""
    from reference_fe import experiments
    from reference_fe.model import FEModel
    from reference_fe.refine import check_memory, fe_problem, rim_refined_problem
    from reference_fe.run import indenter_dofs, punch_model

    fe_section = dataclasses.replace(scene.fe, local_refine=level)
    scene = dataclasses.replace(scene, fe=fe_section)
    check_memory(problem.mesh, fe_section)
    t0 = time.perf_counter()
    base = fe_problem(problem, fe_section)
    depths = indentation_depths(scene.indentation)
    index = {int(v): k for k, v in enumerate(problem.test_points)}
    forces, dofs = [], []
    for vertex in points:
        k = index[int(vertex)]
        fe, model = punch_model(scene, problem, base, k)
        normal = problem.normals[k]
        curve = experiments.held_indentation_curve(model, fe.problem.fixed,
                                                   indenter_dofs(model, scene, problem, fe, k),
                                                   normal, depths, f"punch at vertex {vertex}")
        forces.append(float(curve[-1] @ normal))
        dofs.append(model.n_dofs)
        log.info("fe_convergence: rim level %d, point %d (%d dofs): %.6g N", level, vertex,
                 model.n_dofs, forces[-1])
    t1 = time.perf_counter()
    g = scene.gravity
    max_sag = sag_dofs = None
    if sag:
        fe = rim_refined_problem(base, problem.mesh, problem.fixed, level)
        model = FEModel(fe.problem.mesh, scene.material, fe_section)
        u = experiments.gravity_static(model, fe.problem.fixed, g.acceleration,
                                       g.static_load_steps)[fe.vertex_map]
        max_sag, sag_dofs = float(np.linalg.norm(u, axis=1).max()), model.n_dofs
        log.info("fe_convergence: clamp rim level %d (%d dofs): max sag %.6g m", level,
                 sag_dofs, max_sag)
    t2 = time.perf_counter()
    return {"level": level, "element": fe_section.element, "dofs": dofs, "sag_dofs": sag_dofs,
            "wall_s": t2 - t0,
            "wall_s_punch_per_point": (t1 - t0) / len(points) if len(points) else None,
            "wall_s_sag": t2 - t1 if sag else None,
            "punch_force": forces or None, "max_sag": max_sag}


def summarise(rows: list[dict], default_level: int, default_sag_level: int = 0) -> dict:
    """The changes of the module docstring from the measured levels (each quantity against
    the finest level that has it)."""
    out: dict = {"levels": rows, "default_level": default_level,
                 "default_sag_level": default_sag_level}
    for quantity, default, name in (("punch_force", default_level, "punch_force_change"),
                                    ("max_sag", default_sag_level, "sag_change")):
        have = {r["level"]: np.atleast_1d(np.asarray(r[quantity], dtype=float))
                for r in rows if r.get(quantity) is not None}
        if not have:
            continue
        finest = max(have)
        out["finest_level" if quantity == "punch_force" else "finest_sag_level"] = finest

        def change(level: int) -> float:
            return float(np.max(np.abs(have[level] / have[finest] - 1.0)))

        if default in have:
            out[name] = change(default)
        if len(have) >= 2:
            out[name + "_two_finest"] = change(sorted(have)[-2])
    return out


def convergence(scene: Scene, levels: Sequence[int], *, out: Path | None = None,
                points: Sequence[int] | None = None,
                sag_levels: Sequence[int] = SAG_LEVELS) -> dict:
    """The study on ``scene`` (a punch scene), one level after the other, coarsest first:
    the punch forces on ``levels``, the sag on ``sag_levels`` (empty: none)."""
    problem = build_problem(scene)
    points = (study_points(problem, scene.indentation.radius) if points is None
              else np.asarray(points, dtype=np.int64))
    rows: list[dict] = []
    result: dict = {}
    for level in sorted(set(levels) | set(sag_levels)):
        rows.append(measure_level(scene, problem, points if level in levels else points[:0],
                                  level, sag=level in sag_levels))
        result = {"scene": scene.name, "points": points.tolist(),
                  "radius_m": scene.indentation.radius, "depth_m": scene.indentation.depth,
                  **summarise(rows, scene.fe.local_refine, scene.fe.refine)}
        if out is not None:
            out.write_text(json.dumps(result, indent=1))
        log.info("fe_convergence: level %d done (%.0f s)", level, rows[-1]["wall_s"])
    return result


def study(scene: Scene, cache_folder: Path, quick: bool) -> dict:
    """``make bench`` item: ``{"fe_convergence": ...}`` on the punch scene (the bench scene
    with ``--quick``, given a punch of 1.5 mean surface edge lengths if it has none)."""
    punch = load_scene(PUNCH_SCENE) if not quick else _with_punch(scene)
    levels, sag_levels = (LEVELS, SAG_LEVELS) if not quick else ((0, 1, 2), (0, 1))
    return {"fe_convergence": convergence(punch, levels, sag_levels=sag_levels,
                                          out=Path(cache_folder) / "fe_convergence.json")}


def _with_punch(scene: Scene) -> Scene:
    from forcecal.indenter import mean_surface_edge

    if scene.indentation.indenter == "punch":
        return scene
    h = mean_surface_edge(build_problem(scene).mesh)
    return replace(scene, indentation={"indenter": "punch", "radius": 1.5 * h},
                   fe={"element": "TH", "local_refine": 1})


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipelines.bench.fe_convergence",
                                     description="FE convergence of the punch reference (JSON)")
    parser.add_argument("--scene", default=str(PUNCH_SCENE), help="a punch scene TOML file")
    parser.add_argument("--levels", type=int, nargs="+", default=list(LEVELS),
                        help="punch rim refinements (fe.local_refine)")
    parser.add_argument("--sag-levels", type=int, nargs="*", default=list(SAG_LEVELS),
                        help="clamp rim refinements of the sag (none: no sag)")
    parser.add_argument("--element", help="override fe.element (P2, TH)")
    parser.add_argument("--out", help="JSON file, rewritten after every level")
    parser.add_argument("--points", type=int, nargs="*", help="test vertices (default: 3 "
                        "spread through the scene's list)")
    args = parser.parse_args(argv)
    configure_logging(loggers=(log.name,))
    try:
        scene = load_scene(args.scene)
        if args.element:
            scene = replace(scene, fe={"element": args.element})
        result = convergence(scene, args.levels, out=Path(args.out) if args.out else None,
                             points=args.points, sag_levels=args.sag_levels)
    except ForcecalError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
