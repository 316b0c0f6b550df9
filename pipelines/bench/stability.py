"""Numerical stability of the explicit particle step: the estimated limit against the real one.

:func:`critical_time_step` (eigenvalue bound, see :mod:`particle.integrator`)
must never exceed the step at which the explicit run really blows up.
:func:`empirical_critical_step` finds that step by bisection: a run of
``steps`` steps from a slightly perturbed state is *blown up* when the
integrator's divergence guard fires (a non-finite position, or kinetic energy
beyond :func:`particle.integrator.energy_bound`, i.e. 100 x the energy the
start state and the loads hold). Just above the true limit the unstable mode
grows by a factor ``1 + sqrt(8 delta)`` per step (central difference with
``omega dt = 2 (1 + delta)``), so 3000 steps amplify the energy 100 x as soon
as ``delta`` exceeds ~1e-7: the bisection's own tolerance, not the run length,
sets the resolution.

:func:`stability_cases` are the meshes x parameter sets the test suite
(``tests/test_stability_particle.py``) and ``make bench`` (``BENCH.md``,
"Stability") both use, so the ratio estimate/empirical reported is the one
tested.
"""

from __future__ import annotations

import logging
from typing import Callable

import numpy as np

from forcecal.errors import StabilityError
from forcecal.mesh import TetMesh, box_mesh, fixed_nodes, generate_liver
from particle.integrator import VerletIntegrator, critical_time_step
from particle.model import Model, State, build_model
from particle.testing import viscoelastic_params

log = logging.getLogger(__name__)

K0 = 50.0  # N/m, the particle tests' connector stiffness
DENSITY = 1060.0  # kg/m^3
# (K0 multiplier, a/K0, b/K0, Prony g): the parameter sets of the stability study
PARAMETER_SETS: dict[str, tuple[float, float, float, tuple[float, float]]] = {
    "linear": (1.0, 0.0, 0.0, (0.35, 0.25)),
    "stiff nonlinear": (1.0, -2.0, 40.0, (0.35, 0.25)),
    "strong arms": (1.0, 0.0, 0.0, (0.45, 0.45)),
}
# strains (inside the estimate's default range +-0.5) at which the clamped cube is prestrained
PRESTRAINS = (-0.4, 0.0, 0.4)


def sliver_mesh(height: float = 1e-3, size: float = 0.02) -> TetMesh:
    """Six vertices, five tets around one sliver of relative volume ``height``/3.

    The sliver A B C D has its four vertices within ``height x size`` of a
    plane (diagonals AB at z = 0 and CD at z = height x size); an apex E above
    and F below close it into a solid with one well-shaped tet on each of its
    faces. F and A are meant to be held.
    """
    v = size * np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [1.0, 0.0, height],
                         [0.0, 1.0, height], [0.5, 0.5, 1.0], [0.5, 0.5, -1.0]])
    tets = np.array([[0, 1, 2, 3], [0, 2, 3, 4], [1, 2, 3, 4], [0, 1, 2, 5], [0, 1, 3, 5]])
    x = v[tets]
    volume = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]),
                       x[:, 3] - x[:, 0])
    tets[volume < 0] = tets[volume < 0][:, [0, 2, 1, 3]]  # positive orientation
    return TetMesh(v, tets)


def stability_meshes(quick: bool = False) -> dict[str, tuple[TetMesh, np.ndarray]]:
    """Meshes of the study and their clamped vertices: three box aspects, a sliver, a liver."""
    out = {}
    for name, n, size in (("cube 3x3x2", (3, 3, 2), (0.03, 0.03, 0.03)),
                          ("bar 8x2x2", (8, 2, 2), (0.08, 0.02, 0.02)),
                          ("plate 4x4x1", (4, 4, 1), (0.04, 0.04, 0.005))):
        mesh = box_mesh(n, size)
        out[name] = (mesh, np.nonzero(np.isclose(mesh.vertices[:, 0], 0.0))[0])
    out["sliver"] = (sliver_mesh(), np.array([0, 5]))
    if not quick:
        liver = generate_liver(0.04)
        out["liver h=0.04"] = (liver, fixed_nodes(liver))
    return out


def case_model(mesh: TetMesh, fixed: np.ndarray, parameter_set: str, *,
               density: float = DENSITY) -> Model:
    """Particle model of ``mesh`` with one of :data:`PARAMETER_SETS` (K0 scaled by mean edge)."""
    scale, a, b, g = PARAMETER_SETS[parameter_set]
    k0 = scale * K0 * float(mesh.edge_lengths.mean()) / 0.01  # same material on every mesh
    params = viscoelastic_params(len(mesh.edges), k0, a=a * k0, b=b * k0, g=g, tau=(0.05, 0.5))
    return build_model(mesh, density, params, fixed=fixed)


def stability_cases(quick: bool = False) -> dict[str, Model]:
    """Every mesh of :func:`stability_meshes` with every parameter set, named ``mesh / set``."""
    return {f"{m} / {p}": case_model(mesh, fixed, p)
            for m, (mesh, fixed) in stability_meshes(quick).items() for p in PARAMETER_SETS}


def perturbed_state(model: Model, amplitude: float, seed: int = 0,
                    prestrain: float = 0.0) -> State:
    """A state at rest, dilated by ``1 + prestrain`` about the centroid, then perturbed.

    Every particle (clamped ones too) is dilated, so every connector starts at
    strain ``prestrain`` with unloaded arms; the free particles are then moved
    randomly by ``amplitude`` x the model's size.
    """
    rng = np.random.default_rng(seed)
    state = model.state()
    centre = model.rest_positions.mean(axis=0)
    state.x[:] = centre + (1.0 + prestrain) * (model.rest_positions - centre)
    state.dx_prev[:] = prestrain * model.rest_lengths
    size = float(np.ptp(model.rest_positions))
    free = model.free_nodes
    state.x[free] += amplitude * size * rng.standard_normal((len(free), 3))
    state.x_prev[:] = state.x
    return state


def blows_up(model: Model, dt: float, *, steps: int = 3000, amplitude: float = 1e-6,
             seed: int = 0, prestrain: float = 0.0, gravity: np.ndarray | None = None) -> bool:
    """Whether ``steps`` explicit steps of ``dt`` [s] from a perturbed state diverge
    (under ``gravity`` [m/s^2] if given)."""
    state = perturbed_state(model, amplitude, seed, prestrain)
    try:
        VerletIntegrator().simulate(model, state, dt, steps, gravity=gravity, _check_dt=False)
    except StabilityError:
        return True
    return False


def bisect(unstable: Callable[[float], bool], stable: float, *, rel_tol: float = 1e-3,
           max_growth: int = 12) -> float:
    """Boundary [s] between stable and unstable steps, starting from a ``stable`` step.

    Doubles until a step is unstable (at most ``max_growth`` times: a model
    that never blows up then reports that bound), then bisects to ``rel_tol``.
    Every loop is bounded, so this cannot hang.
    """
    if unstable(stable):
        raise StabilityError(f"the starting step {stable:.4g} s is already unstable")
    lo, hi = stable, 2.0 * stable
    for _ in range(max_growth):
        if unstable(hi):
            break
        lo, hi = hi, 2.0 * hi
    else:
        return lo
    while hi - lo > rel_tol * lo:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if unstable(mid) else (mid, hi)
    return lo


def empirical_critical_step(model: Model, *, steps: int = 3000, rel_tol: float = 1e-3,
                            seed: int = 0, prestrain: float = 0.0) -> float:
    """Largest stable explicit step [s] found by bisection (see the module docstring).

    ``prestrain``: the run starts dilated (:func:`perturbed_state`); with every
    surface particle clamped a uniform dilation of a Kuhn box is an equilibrium
    (each interior particle's connectors come in opposite pairs), so the limit
    found is the one of the tangent at that strain. Starts from the estimate
    :func:`critical_time_step` x 0.5, which must be stable.
    """
    return bisect(lambda dt: blows_up(model, dt, steps=steps, seed=seed, prestrain=prestrain),
                  0.5 * critical_time_step(model), rel_tol=rel_tol)


def clamped_cube(parameter_set: str) -> Model:
    """A 4x4x4 Kuhn box with every surface particle clamped (the prestrain study's model)."""
    mesh = box_mesh((4, 4, 4), (0.04, 0.04, 0.04))
    return case_model(mesh, mesh.surface_vertices, parameter_set)


def stability_table(quick: bool = False) -> list[dict]:
    """Estimated vs empirical limit for every :func:`stability_cases` model (JSON-ready rows)."""
    rows = []
    for name, model in stability_cases(quick).items():
        estimate = critical_time_step(model)
        empirical = empirical_critical_step(model)
        rows.append(_row(name, model, estimate, empirical))
    for parameter_set in PARAMETER_SETS:
        model = clamped_cube(parameter_set)
        estimate = critical_time_step(model)
        for strain in PRESTRAINS:
            empirical = empirical_critical_step(model, prestrain=strain)
            rows.append(_row(f"clamped cube at strain {strain:+.1f} / {parameter_set}", model,
                             estimate, empirical))
    return rows


def _row(name: str, model: Model, estimate: float, empirical: float) -> dict:
    log.info("stability %-44s estimate %.4g s, empirical %.4g s, ratio %.3f", name, estimate,
             empirical, estimate / empirical)
    return {"case": name, "connectors": model.n_connectors, "estimate_s": estimate,
            "empirical_s": empirical, "ratio": estimate / empirical}
