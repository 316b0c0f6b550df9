"""The calibrated model's error against the contact size: fit at one, used at another.

The punch scene (``scenes/liver_punch.toml``; a scene without a punch is given one of 1.5
mean surface edge lengths) is calibrated once per contact size, in a folder of its own, on
indentation curves only: the vertex indenter (the paper's) and flat punches of 1, 1.5 and 2
mean surface edge lengths ``h`` (each with the scene's FE settings but at most
:data:`RIM_LEVELS` rim refinements; the vertex has no rim to refine). Every size uses the
same test points (those whose footprint is valid at every punch radius: >= 3 particles, off
the clamp), split into calibration and held-out points as the scene splits them. Each
fitted model (its ``calibrated`` connectors) is then evaluated at every size's held-out
footprints against that size's FE curves: the diagonal is the model used at the contact
size it was fitted at, the rest the cross terms. Held-out points are never fitted.

The result (JSON): ``rows`` ``{radius_m, radius_edges, fitted_radius_m,
fitted_radius_edges, held_out_error, calibration_error}`` (``radius_m`` = 0 is the vertex;
errors are mean relative RMS errors of the normal-force curves, as in ``report.json``;
``calibration_error`` is null for a cross term), with the scene, ``h``, the points and each
fit's wall times.

``python -m studies.indenter_radius [--scene scenes/liver_punch.toml] [--work
runs/studies/indenter_radius] [--out runs/studies/indenter_radius.json]`` (four FE
references and calibrations: minutes on the punch scene; a stage whose inputs did not change
is not recomputed).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from forcecal.errors import ForcecalError, SceneError
from forcecal.indenter import mean_surface_edge, punch_footprint
from forcecal.point_selection import free_surface_vertices
from forcecal.problem import Problem, build_problem
from forcecal.scene import Scene, load_scene

log = logging.getLogger(__name__)

#: contact sizes in mean surface edge lengths; 0 is the vertex indenter
RADII_EDGES = (0.0, 1.0, 1.5, 2.0)
#: rim refinements of every punch's FE mesh (``fe.local_refine``; the punch scene has 3): at 3
#: the 1-edge punch inverts rim cells at 3.25 of 5 mm (vertex 78: a finer rim shears harder
#: around a bonded punch's edge), at 2 every size reaches 5 mm; level 2's force is 1-3 %
#: above level 4's (fe_convergence), far below the errors this study compares
RIM_LEVELS = 2
WORK = Path("runs/studies/indenter_radius")
OUT = Path("runs/studies/indenter_radius.json")


def common_points(problem: Problem, radii: list[float]) -> tuple[list[int], list[int]]:
    """Calibration and held-out points whose punch footprint is valid at every radius of
    ``radii`` (> 0): the scene's own that are, and, if fewer than
    :data:`~forcecal.scene.MIN_HELD_OUT` of its held-out points are, free surface vertices
    that are (never a calibration point), each the farthest from the points chosen so far."""
    from forcecal.scene import MIN_HELD_OUT

    mesh = problem.mesh

    def valid(vertex: int) -> bool:
        normal = mesh.inward_normals(np.array([vertex]))[0]
        try:
            for radius in radii:
                punch_footprint(mesh, vertex, normal, radius, fixed=problem.fixed)
        except SceneError:
            return False
        return True

    calibration = [int(v) for v in problem.calibration if valid(int(v))]
    held_out = [int(v) for v in problem.held_out if valid(int(v))]
    taken = set(calibration) | set(held_out)
    spare = [int(v) for v in free_surface_vertices(mesh, problem.fixed) if int(v) not in taken]
    spare = [v for v in spare if valid(v)]
    while len(held_out) < MIN_HELD_OUT and spare:
        chosen = mesh.vertices[calibration + held_out]
        gap = [float(np.linalg.norm(chosen - mesh.vertices[v], axis=1).min()) for v in spare]
        held_out.append(spare.pop(int(np.argmax(gap))))
    if len(calibration) < 3 or len(held_out) < MIN_HELD_OUT:
        raise SceneError(f"indenter radius study: only {len(calibration)} calibration and "
                         f"{len(held_out)} held-out points have valid footprints at radii "
                         f"{[round(r, 4) for r in radii]} m")
    return calibration, held_out


def size_scene(base: Scene, radius: float, points: tuple[list[int], list[int]],
               folder: Path) -> Scene:
    """``base`` indented by a punch of ``radius`` (0: the vertex) at ``points``, indentation
    only, written to ``folder/scene.toml``."""
    from pipelines.bench.configs import derived_scene

    indentation = ({"indenter": "vertex", "radius": 0.0} if radius == 0.0
                   else {"indenter": "punch", "radius": radius})
    fe = {"local_refine": 0 if radius == 0.0 else min(RIM_LEVELS, base.fe.local_refine)}
    name = f"{base.name}-r{radius * 1e3:.1f}mm"
    return derived_scene(base, name, {"indentation": indentation, "fe": fe,
                                      "test_points": {"calibration": points[0],
                                                      "held_out": points[1]}},
                         folder, experiments=("indentation",))


def cross_curves(fitted: Any, scene: Scene, reference: Any,
                 strain_range: tuple[float, float]) -> np.ndarray:
    """(P, S) normal-force curves of the connectors ``fitted`` at every test point of
    ``scene`` with its indenter, at the depths of its ``reference``.

    ``strain_range`` is where the fit kept every spring's K(eps) positive (its
    ``params.h5``): the parameters are checked there, and the strains another contact size
    actually reaches are checked at every equilibrium (a K(eps) <= 0 there is refused and
    the cross term reported as failed), rather than refusing the model a priori over the
    evaluator's default +-(depth / shortest connector), strains no indentation reaches."""
    from forcecal.indenter import indenter_footprints
    from particle.evaluators import IndentationEvaluator
    from particle.model import build_model

    problem = reference.problem
    ind = scene.indentation
    held = indenter_footprints(problem.mesh, problem.fixed, problem.test_points,
                               problem.normals, ind.indenter, ind.radius)
    model = build_model(problem, scene.material.density, fitted)
    evaluator = IndentationEvaluator(model, problem.test_points, problem.normals,
                                     reference.indentation.displacement, footprints=held,
                                     strain_range=strain_range)
    return np.asarray(evaluator(fitted, list(range(len(problem.test_points)))))


def study(base: Scene, work: Path) -> dict[str, Any]:
    """The rows and their details (module docstring) of the punch scene ``base``; each size's
    pipeline runs in ``work/r<edges>h/``."""
    from calibration import read_params
    from calibration.metrics import relative_rms_error
    from forcecal.h5io import read_reference
    from pipelines.cache import Cache
    from pipelines.runners.common import PARAMS, REFERENCE
    from pipelines.stages import run_pipeline

    problem = build_problem(base)
    h = mean_surface_edge(problem.mesh)
    radii = [e * h for e in RADII_EDGES]
    points = common_points(problem, [r for r in radii if r > 0])
    log.info("indenter radius: h = %.4g m, %d calibration + %d held-out points", h,
             len(points[0]), len(points[1]))
    fits, details = [], []
    for edges, radius in zip(RADII_EDGES, radii):
        folder = Path(work) / f"r{edges:g}h"
        sized = size_scene(base, radius, points, folder)
        detail = {"radius_edges": edges, "radius_m": radius, "failed": None}
        try:
            run_pipeline(sized, folder, until="calibrate", progress=False)
        except ForcecalError as exc:  # a size the model cannot be fitted at is a result too
            log.warning("indenter radius: %g h: %s", edges, exc)
            detail["failed"] = str(exc).splitlines()[0]
        stages = Cache(folder)
        detail.update(reference_s=stages.elapsed("reference"),
                      calibration_s=stages.elapsed("calibrate"))
        details.append(detail)
        reference = read_reference(folder / REFERENCE) if (folder / REFERENCE).is_file() else None
        params = read_params(folder / PARAMS) if detail["failed"] is None else None
        fits.append((edges, radius, sized, reference, params))
    rows = []
    for f_edges, f_radius, _, _, params in fits:
        for e_edges, e_radius, e_scene, e_ref, _ in fits:
            errors = calibration_error = None
            if params is None or e_ref is None:
                pass  # that size's fit or FE reference failed (its detail says why)
            elif e_radius == f_radius:
                own = params.variants["calibrated"].curves["indentation"]
                errors = relative_rms_error(own, e_ref.indentation.force_normal)
                calibration_error = float(errors[params.is_calibration].mean())
            else:
                try:
                    curves = cross_curves(params.connectors["calibrated"], e_scene, e_ref,
                                          params.strain.bounds)
                    errors = relative_rms_error(curves, e_ref.indentation.force_normal)
                except ForcecalError as exc:  # e.g. K(eps) not positive at the larger strains
                    log.warning("indenter radius: fitted at %.4g m, evaluated at %.4g m: %s",
                                f_radius, e_radius, exc)
            held_out_error = (None if errors is None
                              else float(errors[~params.is_calibration].mean()))
            rows.append({"radius_m": e_radius, "radius_edges": e_edges,
                         "fitted_radius_m": f_radius, "fitted_radius_edges": f_edges,
                         "held_out_error": held_out_error,
                         "calibration_error": calibration_error})
            log.info("indenter radius: fitted at %g h, used at %g h: held-out %s", f_edges,
                     e_edges, "failed" if held_out_error is None else f"{held_out_error:.3%}")
    return {"rows": rows, "scene": base.name, "mean_surface_edge_m": h,
            "calibration_points": points[0], "held_out_points": points[1], "fits": details}


def markdown(result: dict[str, Any]) -> list[str]:
    """The held-out error of each fitted size (rows) used at each size (columns) as Markdown
    table lines; on the diagonal, held-out / calibration error."""
    from pipelines.bench.tables import table

    rows = result["rows"]
    sizes = sorted({r["radius_edges"] for r in rows})

    def label(edges: float) -> str:
        return "vertex" if edges == 0 else f"{edges:g} h"

    def entry(fitted: float, used: float) -> str:
        row = next((r for r in rows if r["fitted_radius_edges"] == fitted
                    and r["radius_edges"] == used), None)
        if row is None or row["held_out_error"] is None:
            return "failed"
        text = f"{100 * row['held_out_error']:.1f} %"
        if row["calibration_error"] is not None:
            text = f"**{text}** / {100 * row['calibration_error']:.1f} %"
        return text

    return table(["fitted at \\ used at"] + [label(e) for e in sizes],
                 [[label(f)] + [entry(f, e) for e in sizes] for f in sizes])


def main(argv: list[str] | None = None) -> None:
    import argparse
    import json

    from forcecal.h5io import atomic_path
    from pipelines.bench.fe_convergence import PUNCH_SCENE, with_punch

    parser = argparse.ArgumentParser(prog="python -m studies.indenter_radius",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, default=PUNCH_SCENE,
                        help="the scene (given a punch of 1.5 h if it has none)")
    parser.add_argument("--work", type=Path, default=WORK, help="the sizes' run folders")
    parser.add_argument("--out", type=Path, default=OUT, help="the result as JSON")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    result = study(with_punch(load_scene(args.scene)), args.work)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(args.out) as tmp:
        tmp.write_text(json.dumps(result, indent=1) + "\n")
    print("\n".join(markdown(result)))


if __name__ == "__main__":
    main()
