"""Under its own weight, does the particle model's stiffness follow the body's change of shape
as the FE's does, and is the gap in the stress the load leaves or in the shape it makes?

The punch scenes fit the FE's modes about the organ's weight along each axis perpendicular to
the scene's gravity (experiment ``body``, ``loaded_modes``); the calibrated punch liver's
lowest mode is 2 % below the FE's at rest and 8 % below about the first load, and its springs'
strain law is not why (``studies.load_softening``). The stiffness of small motions about a
loaded state has two parts: the *initial-stress* part, what the load's stress adds (a taut
string's stiffness; FE ``int grad(du) S : grad(v)``, a connector's ``(F/l)(I - e e^T)``, a
tet's ``P d^2V/dx^2``), and the *material* part at the loaded shape (FE ``int F dS : grad v``,
a connector's ``s e e^T``, a tet's ``k/V0 g g^T``). Per load, the lowest modes
(instantaneous moduli, as the FE's ``loaded_modes``):

* **FE** (the scene's element, and the P1 displacement-pressure element ``ANP`` on the
  particle mesh, the discretisation floor's, also with the bulk modulus that makes the
  material's Poisson's ratio a central-force network's 1/4): about the load with its full
  tangent, without its initial-stress part, and the stress-free body of the loaded shape (a
  new FE model on the displaced mesh: the shape alone);
* **networks** (the closed-form baseline from the scene's material, and the calibrated model
  of a finished run when ``--run`` has one): about their own equilibrium under the load
  with the full tangent and without its initial-stress part, and without it at the FE's
  loaded shape (the material part on the same shape as the FE's); the closed-form network
  also re-derived by its rule on the FE's loaded shape (the network's analogue of the
  stress-free body of that shape). A network that finds no equilibrium under the whole load
  records the fraction it carried;
* per load, the MAC of the lowest mode about it (full tangent, and without its initial
  stress) with the lowest mode at rest: near 1, the frequencies above compare one mode; low,
  the load changed which mode is the lowest;
* per load, the smallest volume ratio ``V / V0`` of the particle mesh's tets: at each
  network's equilibrium (or where it stopped), and through the FE's displaced vertices
  (straight tets; the FE's own cells may curve): how far the load squeezes the body where a
  network's volume term is far softer than the tissue's bulk modulus.

Nothing is fitted and no gravity-test data are read; the FE part recomputes the loads' static
solves (seconds on the punch scenes; ``--refined`` adds the scene's element on its mesh refined
once more, minutes, to say how far the FE's numbers are converged).

``python -m studies.shape_response --scene scenes/liver_punch.toml [--run DIR] [--refined]
[--out FILE]`` (default ``runs/studies/shape_response_<scene name>.json``).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import scipy.sparse as sp

from particle.volume import signed_volumes
from studies._finished_run import run_folder, study_main

log = logging.getLogger(__name__)

#: modes per state (the lowest; the answer quotes the first)
MODES = 3
#: the FE elements compared: the scene's own, then the floor's element on the particle mesh
FLOOR_ELEMENT = "ANP"


def shift(loaded, rest) -> float:
    """``f_loaded / f_rest - 1`` of the lowest mode."""
    return float(loaded[0] / rest[0] - 1.0)


def fe_response(scene, problem, element: str | None = None, refine: int | None = None,
                kappa: float | None = None) -> dict:
    """The FE's lowest modes at rest (instantaneous moduli) and, per body load, about it
    (full tangent, without its initial-stress part) and of the stress-free body of the loaded
    shape, with the loaded displacement at the particle vertices (N, 3) [m]: the scene's FE,
    or ``element`` on the particle mesh, or the scene's element with ``refine`` uniform
    refinements; ``kappa`` [Pa]: that bulk modulus instead of the material's."""
    from forcecal.problem import body_load_directions
    from reference_fe import body
    from reference_fe.experiments import gravity_static
    from reference_fe.model import FEModel
    from reference_fe.refine import fe_problem

    section = scene.fe
    if element is not None:
        section = dataclasses.replace(section, element=element, refine=0)
    if refine is not None:
        section = dataclasses.replace(section, refine=refine)
    material = scene.material if kappa is None else dataclasses.replace(scene.material,
                                                                         kappa=kappa)
    fe = fe_problem(problem, section)
    mesh, fixed = fe.problem.mesh, fe.problem.fixed
    model = FEModel(mesh, material, section)
    rest, rest_shapes = body.natural_modes(model, fixed, MODES, "instantaneous")
    g = np.asarray(scene.gravity.acceleration, float)
    loads = []
    for d in body_load_directions(g):
        what = f"the weight along {np.round(d, 3).tolist()}"
        u, state = gravity_static(model, fixed, np.linalg.norm(g) * d, scene.body.load_steps,
                                  with_state=True, what=what)
        loaded, loaded_shapes = body.loaded_modes(model, fixed, state.u, MODES)
        without, without_shapes = body.loaded_modes(model, fixed, state.u, MODES,
                                                    initial_stress=False)
        row = {"direction": d.tolist(), "loaded": loaded.tolist(),
               "without_initial_stress": without.tolist(), "displacement": u[fe.vertex_map],
               "lowest_mode_mac": {"loaded": mac(loaded_shapes[0], rest_shapes[0]),
                                   "without_initial_stress": mac(without_shapes[0],
                                                                 rest_shapes[0])},
               # straight tets through the displaced vertices (the FE's own cells may curve)
               "min_volume_ratio": float((signed_volumes(mesh.vertices + u, mesh.tets)
                                          / signed_volumes(mesh.vertices, mesh.tets)).min())}
        inverted = inverted_tets(mesh.vertices + u, mesh.tets)
        if inverted:
            row["stress_free_on_loaded_shape_failed"] = inverted
        else:
            moved = FEModel(dataclasses.replace(mesh, vertices=mesh.vertices + u), material,
                            section)
            shaped, _ = body.natural_modes(moved, fixed, MODES, "instantaneous")
            moved.destroy()
            row["stress_free_on_loaded_shape"] = shaped.tolist()
        loads.append(row)
    dofs = int(model.n_dofs)
    model.destroy()
    return {"element": section.element, "dofs": dofs, "rest": rest.tolist(), "loads": loads}


def volume_ratio(model, x: np.ndarray) -> float:
    """The smallest ``V / V0`` of ``model``'s tets at positions ``x`` [1] (negative: one is
    inverted)."""
    return float((signed_volumes(x, model.tets) / model.rest_volumes).min())


def inverted_tets(x: np.ndarray, tets: np.ndarray) -> str | None:
    """None, or what says how many of the straight-sided ``tets`` are inverted or flat at
    positions ``x`` (a shape no stress-free model can be built on)."""
    bad = int(np.count_nonzero(signed_volumes(x, tets) <= 0.0))
    return f"{bad} tet(s) inverted at the loaded vertices" if bad else None


def network_tangent(model, pattern, x: np.ndarray, initial_stress: bool = True
                    ) -> sp.csc_matrix:
    """(n, n) the tangent of small motions about the (relaxed) state ``x`` on the free dofs
    [N/m], at the instantaneous stiffness (arms relaxed, their stiffness added:
    :func:`particle.body.incremental_tangent`); without ``initial_stress``, the connectors'
    ``(F/l)(I - e e^T)`` and the tets' ``P d^2V/dx^2`` left out (their tension and pressure
    set to zero, the material part ``s e e^T`` and ``k/V0 g g^T`` kept)."""
    from particle import kernels
    from particle.statics import net_forces, spring_terms
    from particle.volume import add_volume_tangent

    p = model.params
    _, tension, *_ = net_forces(model, x, p, not p.is_linear, None, None,
                                (np.zeros(model.n_tets), np.full(model.n_tets, np.inf)))
    data = np.empty(len(pattern.indices))
    a, b = spring_terms(p, not p.is_linear)
    kernels.assemble_tangent(x, model.edges, model.rest_lengths, p.K0, a, b, p.k1 + p.k2,
                             tension if initial_stress else np.zeros_like(tension),
                             pattern.slots, data)
    if p.kv is not None:
        arms = p.kv1 + p.kv2 if p.has_volume_arms else np.zeros_like(p.kv)
        rest_volumes, scale = model.rest_volumes, np.ones_like(p.kv)
        if not initial_stress:
            # the same k/V0 with no pressure: the kernel's P = kv (V/V0 - 1) vanishes when
            # its V0 is the current volume, kv and the arms scaled to keep k/V0
            rest_volumes = signed_volumes(x, model.tets)
            scale = rest_volumes / model.rest_volumes
        add_volume_tangent(x, model.tets, rest_volumes, p.kv * scale, pattern.tet_slots, data,
                           (arms * scale, np.zeros_like(p.kv)))
    return sp.csc_matrix((data, pattern.indices, pattern.indptr),
                         shape=(pattern.n_dofs, pattern.n_dofs))


def network_modes(model, operators, stiffness) -> tuple[np.ndarray, np.ndarray]:
    """((MODES,) the lowest frequencies [Hz], (n,) the lowest mode's shape on the free dofs)
    of ``stiffness`` with the model's lumped masses."""
    from particle.body import model_modes

    values, vectors, _ = model_modes(model, operators, "instantaneous", MODES, stiffness)
    return np.sqrt(values) / (2.0 * np.pi), vectors[:, 0]


def mac(a: np.ndarray, b: np.ndarray) -> float:
    """The modal assurance criterion of two shapes (any matching layout): 1 for the same shape,
    0 for orthogonal ones (unweighted: a check of which mode is the lowest, not a metric)."""
    a, b = np.ravel(a), np.ravel(b)
    return float((a @ b) ** 2 / ((a @ a) * (b @ b)))


def network_response(model, accelerations: np.ndarray, load_steps: int,
                     fe_displacements: list[np.ndarray]) -> dict:
    """A network's lowest modes at rest and, per load, about its own equilibrium (full,
    without its initial-stress part) and without it at the FE's loaded shape."""
    from forcecal.errors import ConvergenceError
    from particle.body import RestOperators
    from particle.statics import weight_equilibrium

    ops = RestOperators.of(model)
    pat = ops.pattern
    rest, rest_shape = network_modes(model, ops, network_tangent(model, pat,
                                                                  model.rest_positions))
    loads = []
    for g, u_fe in zip(accelerations, fe_displacements):
        row = {}
        try:
            x = weight_equilibrium(model, np.asarray(g, float), load_steps)
        except ConvergenceError as exc:  # a network that does not carry the load: a result
            row["failed"] = str(exc)
            row["carried"] = exc.reached  # the fraction of the load it had carried
            if exc.reached:  # how far its tets were squeezed where it stopped
                reached = weight_equilibrium(model, exc.reached * np.asarray(g, float),
                                             load_steps)
                row["min_volume_ratio"] = volume_ratio(model, reached)
        else:
            loaded, loaded_shape = network_modes(model, ops, network_tangent(model, pat, x))
            without, without_shape = network_modes(
                model, ops, network_tangent(model, pat, x, initial_stress=False))
            row["loaded"], row["without_initial_stress"] = loaded.tolist(), without.tolist()
            row["lowest_mode_mac"] = {"loaded": mac(loaded_shape, rest_shape),
                                      "without_initial_stress": mac(without_shape, rest_shape)}
            row["max_displacement_m"] = float(np.abs(x - model.rest_positions).max())
            row["min_volume_ratio"] = volume_ratio(model, x)
        at_fe = model.rest_positions + u_fe
        inverted = inverted_tets(at_fe, model.tets)
        if inverted:
            row["fe_shape_failed"] = inverted
        else:
            row["fe_shape_without_initial_stress"] = network_modes(
                model, ops, network_tangent(model, pat, at_fe, initial_stress=False))[0].tolist()
        loads.append(row)
    return {"rest": rest.tolist(), "loads": loads}


def closed_form_network(problem, material, vertices: np.ndarray | None = None):
    """The closed-form (Van Gelder) network of the scene's material on ``problem``'s mesh, or
    on that mesh moved to ``vertices`` (re-derived there: rest lengths, volumes, masses and
    springs of the moved shape)."""
    from calibration.baseline import van_gelder_params
    from particle.model import build_model

    if vertices is not None:
        problem = dataclasses.replace(problem, mesh=dataclasses.replace(problem.mesh,
                                                                        vertices=vertices))
    return build_model(problem, material.density, van_gelder_params(problem.mesh, material))


def study(scene_path, run=None, refined: bool = False) -> dict:
    """The FE's and the networks' loaded modes (module docstring); ``refined``: also the
    scene's element on its mesh refined once more (how far the FE's numbers are converged)."""
    from forcecal.problem import build_problem, body_load_directions
    from forcecal.scene import load_scene
    from pipelines.runners.common import PARAMS

    scene = load_scene(scene_path)
    problem = build_problem(scene)
    g = np.asarray(scene.gravity.acceleration, float)
    accelerations = np.linalg.norm(g) * body_load_directions(g)
    # a central-force network's Poisson's ratio, 1/4, at the modes' (instantaneous) shear
    # modulus mu: kappa = 2 mu (1 + nu) / (3 (1 - 2 nu)) = 5 mu / 3
    quarter = 5.0 * scene.material.shear_modulus / 3.0
    fe = {"scene element": fe_response(scene, problem),
          "floor element": fe_response(scene, problem, FLOOR_ELEMENT),
          "floor element, Poisson's ratio 1/4": fe_response(scene, problem, FLOOR_ELEMENT,
                                                            kappa=quarter)}
    if refined:
        fe["scene element, refined once"] = fe_response(scene, problem,
                                                        refine=scene.fe.refine + 1)
    shapes = [load.pop("displacement") for load in fe["scene element"]["loads"]]
    for name in set(fe) - {"scene element"}:
        for load in fe[name]["loads"]:
            load.pop("displacement")
    steps = scene.body.load_steps
    closed = closed_form_network(problem, scene.material)
    networks = {"closed form": network_response(closed, accelerations, steps, shapes)}
    for load, u in zip(networks["closed form"]["loads"], shapes):
        if "fe_shape_failed" not in load:
            moved = closed_form_network(problem, scene.material, problem.mesh.vertices + u)
            load["re_derived_on_fe_shape"] = network_modes(
                moved, *_operators_and_tangent(moved))[0].tolist()
    folder = run_folder(scene, run)
    if (folder / PARAMS).is_file():
        from calibration import read_params
        from calibration.loading import calibrated_model

        model = calibrated_model(read_params(folder / PARAMS), "calibrated",
                                 folder / PARAMS).model
        networks["calibrated"] = network_response(model, accelerations, steps, shapes)
    else:
        log.info("%s: no %s, the calibrated model left out", folder, PARAMS)
    return {"scene": scene.name, "modes": MODES, "refined": refined,
            "load_accelerations": accelerations.tolist(), "fe": fe, "networks": networks}


def _operators_and_tangent(model):
    """(operators, rest tangent) of ``model`` (for :func:`network_modes`)."""
    from particle.body import RestOperators

    ops = RestOperators.of(model)
    return ops, network_tangent(model, ops.pattern, model.rest_positions)


def main(argv: list[str] | None = None) -> int:
    return study_main("studies.shape_response", __doc__, study, argv, switch=(
        "--refined", "refined", "also the scene's FE element on its mesh refined once more "
        "(minutes: the loads' static solves on 8x the cells)"))


if __name__ == "__main__":
    raise SystemExit(main())
