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
[--sag-levels 0 1 2] [--element TH] [--workers N] [--out FILE.json]`` runs it alone (the
levels found so far are written to ``--out`` as each force or sag finishes, so a long run can
be followed and interrupted). Every punch force and sag is computed on its own, so the bench
runs them on both cores (:data:`WORKERS`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
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
# ``make bench``'s sag levels: level 2 alone takes most of the full study's wall time
HEADLINE_SAG_LEVELS = (0, 1)
WORKERS = 2  # processes of the bench's study: the machine's two cores


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


def _level_scene(scene: Scene, level: int) -> Scene:
    """``scene`` with ``fe.local_refine = level``."""
    return dataclasses.replace(scene, fe=dataclasses.replace(scene.fe, local_refine=level))


def punch_force(scene: Scene, problem: Problem, level: int, vertex: int) -> dict:
    """Full-depth punch force [N] along the normal at test point ``vertex``, on its FE mesh
    refined ``level`` times near the punch's rim: ``{force, dofs, wall_s}``."""
    from reference_fe import experiments
    from reference_fe.refine import fe_problem
    from reference_fe.run import indenter_dofs, punch_model

    t0 = time.perf_counter()
    scene = _level_scene(scene, level)
    k = {int(v): k for k, v in enumerate(problem.test_points)}[int(vertex)]
    fe, model = punch_model(scene, problem, fe_problem(problem, scene.fe), k)
    normal = problem.normals[k]
    try:
        curve = experiments.held_indentation_curve(
            model, fe.problem.fixed, indenter_dofs(model, scene, problem, fe, k), normal,
            indentation_depths(scene.indentation), f"punch at vertex {vertex}")
        dofs = model.n_dofs
    finally:
        model.destroy()  # its memory now: the levels' models grow x2-3.5 each (FEModel.destroy)
    return {"force": float(curve[-1] @ normal), "dofs": dofs,
            "wall_s": time.perf_counter() - t0}


def max_sag(scene: Scene, problem: Problem, level: int) -> dict:
    """Largest static gravity sag [m] (read at the particle vertices) on the mesh refined
    ``level`` times near the clamp's rim: ``{max_sag, dofs, wall_s}``."""
    from reference_fe import experiments
    from reference_fe.model import FEModel
    from reference_fe.refine import fe_problem, rim_refined_problem

    t0 = time.perf_counter()
    scene = _level_scene(scene, level)
    fe = rim_refined_problem(fe_problem(problem, scene.fe), problem.mesh, problem.fixed, level)
    model = FEModel(fe.problem.mesh, scene.material, scene.fe)
    g = scene.gravity
    u = experiments.gravity_static(model, fe.problem.fixed, g.acceleration,
                                   g.static_load_steps)[fe.vertex_map]
    return {"max_sag": float(np.linalg.norm(u, axis=1).max()), "dofs": model.n_dofs,
            "wall_s": time.perf_counter() - t0}


@dataclasses.dataclass(frozen=True)
class Item:
    """One independent computation of the study: a punch force (``vertex`` given) or a sag."""

    level: int
    vertex: int | None = None

    def cost(self) -> float:
        """Relative compute time, for longest-first scheduling: measured on the liver punch
        scene (TH), a punch takes ~2x longer per rim level (1-2 s at level 0, 26 s at 4) and
        the sag ~10x per clamp-rim level (1 s, 6 s, 102 s: its crushed rim cells need many
        load-step halvings)."""
        return 2.0 ** self.level if self.vertex is not None else 10.0 ** self.level

    def run(self, scene: Scene, problem: Problem) -> dict:
        if self.vertex is None:
            return max_sag(scene, problem, self.level)
        return punch_force(scene, problem, self.level, self.vertex)

    def describe(self) -> str:
        return (f"clamp rim level {self.level}" if self.vertex is None
                else f"rim level {self.level}, point {self.vertex}")


def _run_item(item: Item, scene: Scene, problem: Problem) -> dict:
    """Worker entry point (module level: the spawned workers import it)."""
    return item.run(scene, problem)


def level_rows(results: dict[Item, dict], points: np.ndarray, levels: Sequence[int],
               sag_levels: Sequence[int], element: str) -> list[dict]:
    """One row per level from the finished items (a level with an unfinished item is left
    out): punch forces in the order of ``points``, each level's compute seconds."""
    rows = []
    for level in sorted(set(levels) | set(sag_levels)):
        punches = [Item(level, int(v)) for v in points] if level in levels else []
        sag = [Item(level)] if level in sag_levels else []
        if not all(i in results for i in punches + sag):
            continue
        punch = [results[i] for i in punches]
        sagged = results[sag[0]] if sag else None
        rows.append({
            "level": level, "element": element, "dofs": [r["dofs"] for r in punch],
            "sag_dofs": None if sagged is None else sagged["dofs"],
            "wall_s": sum(r["wall_s"] for r in punch) + (sagged["wall_s"] if sagged else 0.0),
            "wall_s_punch_per_point": (float(np.mean([r["wall_s"] for r in punch]))
                                       if punch else None),
            "wall_s_sag": None if sagged is None else sagged["wall_s"],
            "punch_force": [r["force"] for r in punch] or None,
            "max_sag": None if sagged is None else sagged["max_sag"]})
    return rows


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
                sag_levels: Sequence[int] = SAG_LEVELS, workers: int = 1) -> dict:
    """The study on ``scene`` (a punch scene): the punch forces on ``levels``, the sag on
    ``sag_levels`` (empty: none).

    Every punch force and sag is an independent item; ``workers`` > 1 runs them in that many
    spawned processes (each one FE model at a time; memory is checked for all of them). A
    level's ``wall_s`` is the compute time of its items (with ``workers`` > 1 they ran side
    by side with others); ``wall_s`` of the result is the study's own.
    """
    from reference_fe.refine import check_memory

    t0 = time.perf_counter()
    problem = build_problem(scene)
    points = (study_points(problem, scene.indentation.radius) if points is None
              else np.asarray(points, dtype=np.int64))
    finest = max(set(levels) | set(sag_levels))
    check_memory(problem.mesh, _level_scene(scene, finest).fe, ranks=max(1, workers))
    items = [Item(level, int(v)) for level in levels for v in points]
    items += [Item(level) for level in sag_levels]
    # side by side: largest first, so the last to finish are short; alone: cheapest first,
    # so an interrupted run has its coarse levels complete
    items.sort(key=(lambda i: -i.cost()) if workers > 1 else (lambda i: i.cost()))
    results: dict[Item, dict] = {}
    result: dict = {}

    def finished(item: Item, value: dict) -> None:
        nonlocal result
        results[item] = value
        what = ("%.6g N" % value["force"] if item.vertex is not None
                else "max sag %.6g m" % value["max_sag"])
        log.info("fe_convergence: %s (%d dofs): %s (%.0f s; %d of %d items)", item.describe(),
                 value["dofs"], what, value["wall_s"], len(results), len(items))
        rows = level_rows(results, points, levels, sag_levels, scene.fe.element)
        result = {"scene": scene.name, "points": points.tolist(),
                  "radius_m": scene.indentation.radius, "depth_m": scene.indentation.depth,
                  "workers": workers, **summarise(rows, scene.fe.local_refine, scene.fe.refine),
                  "wall_s": time.perf_counter() - t0}
        if out is not None:
            out.write_text(json.dumps(result, indent=1))

    if workers <= 1:
        for item in items:
            finished(item, item.run(scene, problem))
        return result
    # spawned, not forked: the parent may already hold MPI (dolfinx) state
    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
        futures = {pool.submit(_run_item, item, scene, problem): item for item in items}
        for future in as_completed(futures):
            finished(futures[future], future.result())
    return result


def study(scene: Scene, cache_folder: Path, quick: bool,
          sag_levels: Sequence[int] = SAG_LEVELS) -> dict:
    """``make bench-full`` item: ``{"fe_convergence": ...}`` on the punch scene (the bench
    scene with ``--quick``, given a punch of 1.5 mean surface edge lengths if it has none),
    the sag on ``sag_levels``."""
    punch = load_scene(PUNCH_SCENE) if not quick else with_punch(scene)
    levels, sag_levels = (LEVELS, sag_levels) if not quick else ((0, 1, 2), (0, 1))
    return {"fe_convergence": convergence(punch, levels, sag_levels=sag_levels,
                                          out=Path(cache_folder) / "fe_convergence.json",
                                          workers=WORKERS)}


def headline_study(scene: Scene, cache_folder: Path, quick: bool) -> dict:
    """``make bench``'s item: :func:`study` with the sag on :data:`HEADLINE_SAG_LEVELS`."""
    return study(scene, cache_folder, quick, HEADLINE_SAG_LEVELS)


def with_punch(scene: Scene) -> Scene:
    """``scene`` if it indents with a punch, else the same scene with a punch of 1.5 mean
    surface edge lengths (Taylor-Hood FE, one rim refinement): the small punch scene of
    ``--quick`` runs."""
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
    parser.add_argument("--out", help="JSON file, rewritten as each force or sag finishes")
    parser.add_argument("--points", type=int, nargs="*", help="test vertices (default: 3 "
                        "spread through the scene's list)")
    parser.add_argument("--workers", type=int, default=1,
                        help="processes running the levels' items side by side")
    args = parser.parse_args(argv)
    configure_logging(loggers=(log.name,))
    try:
        scene = load_scene(args.scene)
        if args.element:
            scene = replace(scene, fe={"element": args.element})
        result = convergence(scene, args.levels, out=Path(args.out) if args.out else None,
                             points=args.points, sag_levels=args.sag_levels,
                             workers=args.workers)
    except ForcecalError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
