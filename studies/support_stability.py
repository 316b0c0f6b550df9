"""Whether a support holds the organ under its whole weight, or the organ tips over on it.

A static gravity sag whose Newton solve stops converging part-way (a tiny first residual, then
a diverging iterate, at every halving of the load increment) is either a solver weakness or a
physical limit point: the loaded body has no stable equilibrium beyond that load (an organ
standing on a small seat tips over like an inverted pendulum on a compliant base; the weight
above the seat, displaced sideways, makes a moment that grows faster than the seat's
resistance). The two are told apart by the tangent stiffness along the load path: at a limit
point its lowest eigenvalue goes to zero. This study marches the FE reference's static sag
(:func:`reference_fe.experiments.gravity_static`'s steps: long-term material, the same Newton
solver and step cutting) through the load factors asked for and, at each converged one,
computes the eigenvalues nearest zero of ``K(u) phi = lambda M phi``: ``K(u)`` the tangent a
quasi-static Newton step sees there (the long-term material at the loaded state: its
geometric part carries the weight's moment), ``M`` the consistent mass, the support's clamp
removed (:func:`reference_fe.body.eigenvalues_nearest_zero`; ``lambda = omega^2`` [1/s^2] of
small motions about the loaded state, negative when it is unstable). The lowest mode is
described by the rigid rotation about the seat's centroid that fits it best (mass-weighted
least squares): its axis and the share of the mode it explains (1: the body turns rigidly
about its seat, i.e. it tips), and the static sag by its tilt [deg] about the same point.

Each support (``--support axis:side:tolerance``, repeat: the ``[second_support]`` keys'
rule, :func:`forcecal.point_selection.fixed_nodes`; default the scene's own) also gets the mesh
preflight's linear check (:func:`forcecal.preflight.check_support`) and is marched through
the same load factors (default :data:`FACTORS`): which of them have an equilibrium under the
whole weight, and how far from a limit point (the lowest eigenvalue against the rest
state's). Nothing of the particle model is read: a support is judged by the geometry and the
FE alone (the second support's test is held out).

``python -m studies.support_stability --scene scenes/user_organ_punch.toml
[--support y:min:0.01 ...] [--factors 0.25,0.5,0.75,1] [--out FILE]`` (default
``runs/studies/support_stability_<scene name>.json``; one to four minutes per support on the
user organ's 521 vertices, Taylor-Hood, 10,445 dofs, on a loaded machine).
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from pathlib import Path

import numpy as np

from forcecal.errors import ConvergenceError, StabilityError
from forcecal.point_selection import fixed_nodes
from forcecal.preflight import check_support
from forcecal.problem import Problem, build_problem
from forcecal.scene import Scene, load_scene
from studies._finished_run import write_result

log = logging.getLogger(__name__)

#: load factors [x gravity] of every support's march: close to the load the FE static sag of
#: the user organ standing on its bottom stopped converging at (0.53125), then on to the whole
#: weight
FACTORS = (0.25, 0.4, 0.5, 0.52, 0.53, 0.531, 0.6, 0.7, 0.75, 1.0)
#: eigenvalues nearest zero computed at each load factor
COUNT = 4


def rotation_fit(displacement: np.ndarray, positions: np.ndarray, centre: np.ndarray,
                 weights: np.ndarray) -> tuple[np.ndarray, float]:
    """The small rigid rotation ``omega x (x - centre)`` that fits the (N, 3) ``displacement``
    of the vertices at (N, 3) ``positions`` best, weighted by (N,) ``weights`` (masses): the
    rotation vector ``omega`` (3,) [rad per unit of the displacement's scale] and the share
    of the displacement's weighted square norm it explains (1: a rigid rotation about
    ``centre``)."""
    r = positions - centre
    # omega x r = -[r]_x omega: one (3, 3) block per vertex
    blocks = np.zeros((len(r), 3, 3))
    blocks[:, 0, 1], blocks[:, 0, 2] = r[:, 2], -r[:, 1]
    blocks[:, 1, 0], blocks[:, 1, 2] = -r[:, 2], r[:, 0]
    blocks[:, 2, 0], blocks[:, 2, 1] = r[:, 1], -r[:, 0]
    root = np.sqrt(weights)[:, None, None]
    A = (root * blocks).reshape(-1, 3)
    b = (root[:, :, 0] * displacement).ravel()
    omega = np.linalg.lstsq(A, b, rcond=None)[0]
    total = float(b @ b)
    residual = b - A @ omega
    return omega, (1.0 - float(residual @ residual) / total) if total > 0 else 0.0


def load_path(scene: Scene, problem: Problem, fixed: np.ndarray, factors: tuple[float, ...],
              what: str, count: int = COUNT) -> dict:
    """The static gravity march with ``fixed`` clamped through ``factors`` [x the scene's
    gravity] and the tangent's ``count`` eigenvalues nearest zero at each converged factor
    and at rest (module docstring); the march's failure, if any, with the last converged
    factor."""
    from reference_fe.body import eigenvalues_nearest_zero, stiffness_and_mass
    from reference_fe.experiments import march
    from reference_fe.model import FEModel, Load, clamp, initial_state, solve_step
    from reference_fe.refine import fe_clamp, fe_problem

    fe = fe_problem(problem, scene.fe)
    model = FEModel(fe.problem.mesh, scene.material, scene.fe)
    fe_fixed = fe_clamp(problem, fixed, fe, scene.fe)
    held = clamp(model.clamp_dofs(fe_fixed))
    g = np.asarray(scene.gravity.acceleration, float)
    mesh = problem.mesh
    masses = mesh.lumped_masses(scene.material.density)
    centre = mesh.vertices[fixed].mean(axis=0)
    at_particles = fe.vertex_map

    def step(state, previous, factor):
        return solve_step(model, state, Load(held, factor * g), factor, dt=None)

    def row(factor: float, u: np.ndarray) -> dict:
        stiffness, mass = stiffness_and_mass(model, "long_term", u)
        values, vectors = eigenvalues_nearest_zero(model, fe_fixed, stiffness, mass, count,
                                                   f"{what} at {factor:g} x gravity")
        mode = vectors[model.vertex_dofs[at_particles], 0]  # (N, 3) the lowest mode
        axis, share = rotation_fit(mode, mesh.vertices, centre, masses)
        sag = model.vertex_values(u)[at_particles]
        tilt, tilt_share = rotation_fit(sag, mesh.vertices, centre, masses)
        out = {"factor": factor, "eigenvalues_per_s2": values.tolist(),
               "frequencies_hz": (np.sign(values) * np.sqrt(np.abs(values))
                                  / (2 * np.pi)).tolist(),
               "lowest_mode_rotation_share": share,
               "lowest_mode_rotation_axis": (axis / np.linalg.norm(axis)).tolist(),
               "max_sag_mm": float(np.linalg.norm(sag, axis=1).max() * 1e3),
               "tilt_deg": float(np.degrees(np.linalg.norm(tilt))),
               "tilt_axis": (tilt / max(np.linalg.norm(tilt), 1e-300)).tolist(),
               "sag_rotation_share": tilt_share}
        log.info("%s at %.4g g: lambda %s /s^2, lowest mode %.0f %% rotation about the seat, "
                 "sag %.3g mm, tilt %.3g deg", what, factor, np.round(values, 2).tolist(),
                 100 * share, out["max_sag_mm"], out["tilt_deg"])
        return out

    start = time.perf_counter()
    state = initial_state(model)
    rows = [row(0.0, state.u)]
    result = {"n_fixed": int(len(fixed)), "fe_dofs": model.n_dofs,
              "seat_extent_mm": (np.ptp(mesh.vertices[fixed], axis=0) * 1e3).tolist(),
              "seat_centre_m": centre.tolist(), "rows": rows, "failure": None,
              "reached": None}
    try:
        for state in march(state, np.asarray(factors, float), step,
                           max_cuts=scene.fe.max_step_cuts, what=f"{what} static",
                           unit="x gravity"):
            rows.append(row(float(state.progress), state.u))
    except (ConvergenceError, StabilityError) as exc:
        result["failure"], result["reached"] = str(exc), float(exc.reached)
        log.info("%s", exc)
    else:
        result["reached"] = float(factors[-1])
    lowest = np.array([r["eigenvalues_per_s2"][0] for r in rows])
    result["lowest_eigenvalue_vs_rest"] = (lowest / lowest[0]).tolist()
    result["limit_factor_estimates"] = limit_estimates(
        np.array([r["factor"] for r in rows]), lowest)
    result["seconds"] = time.perf_counter() - start
    return result


def limit_estimates(factors: np.ndarray, lowest: np.ndarray) -> dict:
    """Where the lowest eigenvalue ``lowest`` [1/s^2] at the load ``factors`` reaches zero,
    extrapolated from its last two values: linearly (a bifurcation) and with its square
    linear in the load (a fold, where it falls as the square root of the distance to the
    limit); None when it does not fall."""
    if len(factors) < 2 or lowest[-1] >= lowest[-2]:
        return {"linear": None, "fold": None}
    (f0, f1), (l0, l1) = factors[-2:], lowest[-2:]
    linear = f1 + l1 * (f1 - f0) / (l0 - l1)
    fold = f1 + l1 ** 2 * (f1 - f0) / (l0 ** 2 - l1 ** 2) if l1 > 0 else None
    return {"linear": float(linear), "fold": None if fold is None else float(fold)}


def support(scene: Scene, problem: Problem, rule: str, factors: tuple[float, ...]) -> dict:
    """One support ``axis:side:tolerance`` [m] (the ``[second_support]`` keys' rule): its
    vertices, the preflight's linear check and the static march through ``factors``
    (:func:`load_path`), its sags checked as the FE reference's static sag checks them
    (:func:`reference_fe.experiments.check_sag`, here at the particle vertices: the refusal's
    message, or None); ``holds_full_gravity``: the march reached the last factor with every
    lowest eigenvalue positive, and neither check refuses the support."""
    from reference_fe.experiments import check_sag

    axis, side, tolerance = rule.split(":")
    fixed = fixed_nodes(problem.mesh, axis, side, float(tolerance), "second_support")
    check = check_support(problem.mesh, fixed, scene.material, scene.gravity.acceleration)
    path = load_path(scene, problem, fixed, factors, f"support {rule}")
    extent = float(np.linalg.norm(np.ptp(problem.mesh.vertices, axis=0)))
    loaded = path["rows"][1:]
    refusal = None
    for r in loaded:
        try:
            check_sag(r["max_sag_mm"] * 1e-3, r["factor"],
                      loaded[0]["max_sag_mm"] * 1e-3 / loaded[0]["factor"], extent, len(fixed),
                      "second_support")
        except StabilityError as exc:
            refusal = str(exc)
            break
    holds = (path["failure"] is None and check.holds and refusal is None
             and all(r["eigenvalues_per_s2"][0] > 0 for r in path["rows"]))
    return {"rule": {"axis": axis, "side": side, "tolerance": float(tolerance)},
            "linear_check": {"rigid_modes": check.rigid_modes,
                             "linear_sag_mm": check.sag_m * 1e3, "holds": check.holds},
            "sag_check_refusal": refusal, "holds_full_gravity": holds, **path}


def study(scene_path: str, factors: tuple[float, ...], rules: list[str]) -> dict:
    """:func:`support` of each of ``rules`` (none: the scene's ``[second_support]``)."""
    scene = load_scene(scene_path)
    problem = build_problem(scene)
    s = scene.second_support
    rules = rules or [f"{s.axis}:{s.side}:{s.tolerance}"]
    result = {"scene": scene.name, "load_average_start": list(os.getloadavg()),
              "element": scene.fe.element, "quadrature_degree": scene.fe.quadrature_degree,
              "factors": list(factors),
              "supports": [support(scene, problem, rule, factors) for rule in rules]}
    result["load_average_end"] = list(os.getloadavg())
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m studies.support_stability",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--scene", required=True, help="scene TOML with a [second_support]")
    parser.add_argument("--factors", default=",".join(map(str, FACTORS)),
                        help="load factors [x gravity] of the march")
    parser.add_argument("--support", action="append", default=[],
                        help="a support axis:side:tolerance [m] (repeat; default: the scene's "
                             "[second_support])")
    parser.add_argument("--out", type=Path, help="the result as JSON (default runs/studies/"
                        "support_stability_<scene name>.json)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    factors = tuple(float(f) for f in args.factors.split(","))
    write_result(parser, args.out, study(args.scene, factors, args.support))


if __name__ == "__main__":
    main()
