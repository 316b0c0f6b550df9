"""Synthetic references made by the particle model itself, for parameter-recovery studies.

A calibration fitted to curves that the particle model produced with known
parameters must give those curves (and, where identifiable, those parameters)
back: :func:`synthetic_reference` writes such a ``reference.h5``;
:func:`ring_perturbed_params` makes known non-uniform parameters of exactly the
form local tuning searches (global values times ring factors), and
:func:`noisy_params` ones that are not (an independent random factor on every
connector, which neither the global nor the local parametrisation can
represent); :func:`box_scene` makes a small scene on a structured box mesh to
run them on.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Sequence

import meshio
import numpy as np

from calibration.parametrisation import GlobalParams, StrainRange, build_rings, local_params
from forcecal.errors import ParameterError
from forcecal.h5io import (BODY_MODULI, BodyResult, GravityResult, IndentationCurves, Reference,
                           RelaxationCurves, SecondSupportResult, write_reference)
from forcecal.indenter import indenter_footprints
from forcecal.mesh import box_mesh
from forcecal.problem import Problem, body_load_directions, build_problem, second_support
from forcecal.scene import Scene, load_scene
from forcecal.schedules import indentation_depths, record_times, relaxation_schedule
from particle.evaluators import IndentationEvaluator, RelaxationEvaluator, normal_force
from particle.body import RestOperators, incremental_tangent, model_modes, unsupported_model
from particle.model import Model, build_model
from particle.params import ConnectorParams
from particle.statics import weight_equilibrium


def box_scene(directory: str | Path, *, cells: tuple[int, int, int] = (3, 3, 2),
              size: tuple[float, float, float] = (0.06, 0.06, 0.02),
              **sections: dict[str, Any]) -> Scene:
    """A scene on ``box_mesh(cells, size)``, base z = 0 fixed, written to ``directory``.

    The mesh goes to ``box.vtu`` and the scene to ``box.toml`` (usable with the
    command line); ``sections`` set scene tables, e.g. ``test_points={"n_calibration": 4}``.
    """
    directory = Path(directory).resolve()
    directory.mkdir(parents=True, exist_ok=True)
    mesh = box_mesh(cells, size)
    path = directory / "box.vtu"
    meshio.write(path, meshio.Mesh(mesh.vertices, [("tetra", mesh.tets)]))
    tables: dict[str, dict[str, Any]] = {"mesh": {"source": str(path)},
                                         "fixed": {"tolerance": 1e-4}}
    for name, table in sections.items():
        tables[name] = {**tables.get(name, {}), **table}
    # JSON scalars and lists of them are valid TOML values
    text = 'name = "box"\n' + "".join(
        f"\n[{name}]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in table.items())
        for name, table in tables.items())
    toml = directory / "box.toml"
    toml.write_text(text)
    return load_scene(toml)


def synthetic_body(model: Model, acceleration: np.ndarray, modes: int, load_steps: int
                   ) -> BodyResult:
    """The experiment ``body`` of ``model`` itself (what :mod:`reference_fe.body` computes
    for the FE): its ``modes`` lowest modes at both moduli (shapes mass-normalised with its
    lumped masses), its static equilibria under the weight along the two directions
    perpendicular to ``acceleration``, the modes about each of them and the unsupported
    body's modes."""
    ops = RestOperators.of(model, unsupported=True)

    def lowest(modulus: str, stiffness=None, free: bool = False
               ) -> tuple[np.ndarray, np.ndarray]:
        which, which_ops = (unsupported_model(model), ops.unsupported) if free else (model, ops)
        values, vectors, _ = model_modes(which, which_ops, modulus, modes, stiffness,
                                         free_free=free)
        full = np.zeros((modes, model.n_particles, 3))
        full[:, which.free_nodes] = vectors.T.reshape(modes, -1, 3)
        return np.sqrt(values) / (2.0 * np.pi), full

    frequencies, shapes = zip(*(lowest(modulus) for modulus in BODY_MODULI))
    free_f, free_phi = zip(*(lowest(modulus, free=True) for modulus in BODY_MODULI))
    directions = body_load_directions(acceleration)
    magnitude = float(np.linalg.norm(acceleration))
    positions = [weight_equilibrium(model, magnitude * d, load_steps) for d in directions]
    loaded_f, loaded_phi = zip(*(lowest("loaded", incremental_tangent(model, ops.pattern, x))
                                 for x in positions))
    return BodyResult(np.stack(frequencies), np.stack(shapes), directions, magnitude,
                      np.stack([x - model.rest_positions for x in positions]),
                      np.stack(loaded_f), np.stack(loaded_phi), np.stack(free_f),
                      np.stack(free_phi))


def synthetic_reference(scene: Scene, params: ConnectorParams, path: str | Path, *,
                        gravity: bool = False) -> Reference:
    """Write (and return) a ``reference.h5`` whose curves are the particle model's with ``params``.

    The curves are sampled exactly like the FE's (scene schedules). With ``gravity`` the
    gravity test too: the static sag and the release at the FE's record times, run as the
    gravity stage runs a particle model (:func:`calibration.gravity_check.gravity_outcome`,
    ``params`` positive on +-0.5), and the second support's when the scene's experiments
    include ``second_support``; otherwise gravity is not computed. The whole-body data
    (:func:`synthetic_body`) when the scene runs the experiment ``body``. The stage timings
    (``timings_s``) of a reference the FE did not compute are zero.
    """
    problem = build_problem(scene)
    model = build_model(problem, scene.material.density, params,
                        volume_element=scene.particle.volume_element)
    nodes, normals = problem.test_points, problem.normals
    depths = indentation_depths(scene.indentation)
    times, relax_depths = relaxation_schedule(scene.relaxation)
    ind = scene.indentation
    held = indenter_footprints(problem.mesh, problem.fixed, nodes, normals, ind.indenter,
                               ind.radius)
    static = IndentationEvaluator(model, nodes, normals, depths,
                                  footprints=held).force_vectors(params)
    relax = RelaxationEvaluator(model, nodes, normals, times, relax_depths,
                                footprints=held).force_vectors(params)
    ref = Reference(problem=problem, material=scene.material,
                    indentation=IndentationCurves(depths, static, normal_force(static, normals),
                                                  indenter=ind.indenter, radius=ind.radius),
                    relaxation=RelaxationCurves(times, relax_depths, relax,
                                                  normal_force(relax, normals)),
                    gravity=synthetic_gravity(scene, problem, params) if gravity else None,
                    second_support=(synthetic_second_support(scene, problem, params)
                                    if gravity and scene.runs("second_support") else None),
                    meta={"source": "particle model (synthetic reference)",
                          "timings_s": json.dumps(dict.fromkeys(
                              ("mesh", "total", "gravity_static", "gravity_dynamic",
                               "second_support"), 0.0))},
                    body=synthetic_body(model, np.asarray(scene.gravity.acceleration, float),
                                        scene.body.modes, scene.body.load_steps)
                    if scene.runs("body") else None)
    write_reference(path, ref)
    return ref


def synthetic_gravity(scene: Scene, problem: Problem, params: ConnectorParams) -> GravityResult:
    """The particle model's gravity test with ``params`` as a reference's gravity runs."""
    from calibration.gravity_check import gravity_outcome

    times = record_times(scene.gravity.duration, scene.gravity.record_interval)
    run, failure = gravity_outcome(scene, problem, params, times, (-0.5, 0.5), "calibrated")
    if failure is not None:
        raise ParameterError(f"the synthetic reference's gravity test failed: {failure.reason}")
    settings = dataclasses.replace(scene.gravity, tracked_node=problem.tracked_node)
    return GravityResult(run.static_displacement, times, run.displacement, settings)


def synthetic_second_support(scene: Scene, problem: Problem, params: ConnectorParams
                             ) -> SecondSupportResult:
    """The particle model's gravity test with ``params`` and the scene's second support
    (:func:`forcecal.problem.second_support`) as a reference's ``second_support``."""
    support = second_support(scene, problem)
    clamped = dataclasses.replace(problem, fixed=support.fixed,
                                  tracked_node=support.tracked_node)
    return SecondSupportResult(scene.second_support, support.fixed,
                               synthetic_gravity(scene, clamped, params))


def ring_perturbed_params(problem: Problem, glob: GlobalParams, strain: StrainRange, *,
                          amplitude: float = 0.3, seed: int = 1,
                          footprints: Sequence[np.ndarray] | None = None
                          ) -> tuple[ConnectorParams, np.ndarray, np.ndarray]:
    """Global parameters with random ring offsets of the calibration points.

    Offsets are uniform in ``[-amplitude, amplitude]`` (factors exp(+-0.3) = x0.74..x1.35
    on K0, k_i and tau_i by default), alpha/beta offsets 0.3 times that. ``footprints``:
    the calibration points' punch footprints (their rings, :func:`build_rings`), None for
    the vertex indenter.

    Returns:
        params: the per-connector parameters;
        z_static: (Pc, 3) and z_relaxation: (Pc, 4), the offsets used.
    """
    rng = np.random.default_rng(seed)
    n = len(problem.calibration)
    z_static = rng.uniform(-amplitude, amplitude, (n, 3)) * np.array([1.0, 0.3, 0.3])
    z_relaxation = rng.uniform(-amplitude, amplitude, (n, 4))
    rings = build_rings(problem.mesh, problem.calibration, footprints)
    return local_params(glob, rings, strain, z_static, z_relaxation), z_static, z_relaxation


def noisy_params(glob: GlobalParams, n_connectors: int, *, sigma: float = 0.1,
                 seed: int = 1) -> ConnectorParams:
    """Global parameters with an independent log-normal factor per connector and quantity.

    ``K0``, ``k1``, ``tau1``, ``k2`` and ``tau2`` of every connector are multiplied by
    ``exp(N(0, sigma^2))`` (x0.90..x1.11 at one standard deviation by default);
    ``alpha`` and ``beta`` stay global (``a = alpha K0``, ``b = beta K0``), so every
    spring keeps the global shape ``K(eps) / K0``.
    """
    rng = np.random.default_rng(seed)
    K0, k1, tau1, k2, tau2 = (value * np.exp(rng.normal(0.0, sigma, n_connectors))
                              for value in (glob.K0, glob.k1, glob.tau1, glob.k2, glob.tau2))
    return ConnectorParams(K0=K0, a=glob.alpha * K0, b=glob.beta * K0, k1=k1, b1=tau1 * k1,
                           k2=k2, b2=tau2 * k2)
