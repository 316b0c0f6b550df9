"""Small models with closed-form answers and their energies, for the particle tests."""

from __future__ import annotations

import numpy as np

from forcecal.mesh import box_mesh
from particle.model import Model, ModelBuilder, Prescribed, State, build_model
from particle.params import ConnectorParams, viscoelastic_params


def two_particle_model(rest_length: float = 0.02, mass: float = 0.01,
                       params: ConnectorParams | None = None,
                       direction: tuple[float, float, float] = (1.0, 0.0, 0.0)) -> Model:
    """Particle 0 fixed at the origin, particle 1 at ``rest_length`` along ``direction``."""
    builder = ModelBuilder()
    builder.add_particle((0.0, 0.0, 0.0), mass, fixed=True)
    builder.add_particle(rest_length * np.asarray(direction) / np.linalg.norm(direction), mass)
    builder.add_connector(0, 1)
    return builder.finalize(viscoelastic_params(1) if params is None else params)


def box_model(n: tuple[int, int, int] = (3, 3, 2), size: float = 0.03, density: float = 1000.0,
              fixed_bottom: bool = True, **param_kwargs) -> Model:
    """Box of side ``size`` [m] (Kuhn-split cells), bottom face (z = 0) fixed if asked."""
    mesh = box_mesh(n, (size,) * 3)
    fixed = np.nonzero(np.isclose(mesh.vertices[:, 2], 0.0))[0] if fixed_bottom else None
    return build_model(mesh, density, viscoelastic_params(len(mesh.edges), **param_kwargs),
                       fixed=fixed)


def top_centre(model: Model) -> int:
    """The particle of the top face (max z) nearest to the face's centre."""
    x = model.rest_positions
    top = np.nonzero(np.isclose(x[:, 2], x[:, 2].max()))[0]
    centre = x[top].mean(axis=0)
    return int(top[np.argmin(np.linalg.norm(x[top] - centre, axis=1))])


def spring_energy(model: Model, x: np.ndarray) -> float:
    """Sum over connectors of int_0^dx K(s/L) s ds = K0 dx^2/2 + a dx^3/(3L) + b dx^4/(4L^2) [J]."""
    p, L = model.params, model.rest_lengths
    dx = np.linalg.norm(x[model.edges[:, 1]] - x[model.edges[:, 0]], axis=1) - L
    return float(np.sum(p.K0 * dx ** 2 / 2 + p.a * dx ** 3 / (3 * L)
                        + p.b * dx ** 4 / (4 * L ** 2)))


def mechanical_energy(model: Model, state: State, gravity: np.ndarray) -> tuple[float, float]:
    """(total, stored) energy [J]: total = kinetic + spring + arm spring + gravitational,
    zero at rest undeformed; stored = kinetic + spring + arm spring (what is in motion).

    Position Verlet's velocity lives at half steps: v = (x^n - x^{n-1})/dt, so the
    potentials are averaged over x^n and x^{n-1}; the arm forces of the state belong to
    x^{n-1} (their spring holds F^2/(2k)). The dashpots only dissipate, so the total can
    only fall, up to the integrator's bounded O((omega dt)^2) energy error.
    """
    m = model.masses
    v = (state.x - state.x_prev) / state.dt
    kinetic = 0.5 * float(np.sum(m[:, None] * v ** 2))
    springs = 0.5 * (spring_energy(model, state.x) + spring_energy(model, state.x_prev))
    arms = float(np.sum(state.arm_force ** 2 / (2.0 * model.params.arm_stiffness)))
    mid = 0.5 * (state.x + state.x_prev) - model.rest_positions
    stored = kinetic + springs + arms
    return stored - float(np.sum(m[:, None] * mid * gravity)), stored


def deformed_start_and_push(model: Model, dt: float, seed: int = 2
                            ) -> tuple[State, Prescribed]:
    """The start of the compiled-vs-numpy step comparisons: the model at rest but deformed (free
    particles moved by 0.1 mm normal noise, ``x_prev = x``: exercises the start-up step) and the
    top-centre particle pushed 1 mm down over 20 steps of ``dt`` [s], then held."""
    state = model.state()
    state.x[model.free_nodes] += 1e-4 * np.random.default_rng(seed).standard_normal(
        (len(model.free_nodes), 3))
    state.x_prev[:] = state.x
    node = top_centre(model)
    start = state.x[node]
    motion = Prescribed([node], [0.0, 20 * dt], [[start], [start + [0.0, 0.0, -1e-3]]])
    return state, motion


def volume_pass(x: np.ndarray, tets: np.ndarray, rest_volumes: np.ndarray, kv: np.ndarray,
                forces: np.ndarray, arms: tuple | None = None) -> tuple[int, float]:
    """:func:`particle.volume.add_volume_forces` of every tet, no volume range (``(0, inf]``),
    typed as a run calls it (the tets an unsigned read-only index view, rest volumes and kv
    read-only, the volumes stored): the tests share the runs' compiled pass, each other
    typing of which costs ~4 s of compilation."""
    from particle.kernels import index_view
    from particle.volume import add_volume_forces

    def fixed(a, dtype=np.float64):
        out = np.array(a, dtype=dtype)
        out.flags.writeable = False
        return out

    n = len(tets)
    return add_volume_forces(x, fixed(index_view(np.ascontiguousarray(tets, dtype=np.int64)),
                                      np.uint64),
                             fixed(rest_volumes), fixed(kv), np.zeros(n), np.full(n, np.inf),
                             forces, arms, np.empty(n))


def compiled_and_numpy_steps(model: Model, gravity: np.ndarray, n_steps: int = 50,
                             damping: float = 3.0, **record) -> tuple[State, State, object]:
    """(the compiled loop's state, the numpy twin's, the recording) after ``n_steps`` steps
    of half the stable step from :func:`deformed_start_and_push`, under ``gravity`` with
    ``damping`` [1/s]; ``record``: the recording's ``record_nodes``/``record_steps``."""
    from particle.integrator import VerletIntegrator
    from particle.reference_numpy import step_numpy
    from particle.stability import critical_time_step
    dt = 0.5 * critical_time_step(model, damping=damping)
    compiled, motion = deformed_start_and_push(model, dt)
    reference = compiled.copy()
    recorded = VerletIntegrator(damping).simulate(model, compiled, dt, n_steps,
                                                  gravity=gravity, prescribed=motion, **record)
    for _ in range(n_steps):
        step_numpy(model, reference, dt, gravity=gravity, damping=damping, prescribed=motion)
    return compiled, reference, recorded


def haptic_push(model: Model, depth: float = 5e-4, periods: int = 3) -> tuple:
    """(session, tool particle, the force of the last period [N]): a haptic session at half
    the stable step holding the top-centre particle ``depth`` [m] down for ``periods``
    periods, and the force :meth:`Run.force_on` gives at its final state, which must equal
    it bit for bit (asserted here)."""
    from particle.haptics import HapticSession
    from particle.stability import critical_time_step
    node = top_centre(model)
    session = HapticSession(model, 0.5 * critical_time_step(model))
    target = model.rest_positions[node] + [0.0, 0.0, -depth]
    for _ in range(periods):
        force = session.step(node, target)
    np.testing.assert_array_equal(force, session._run(node)[0].force_on(session.state, node))
    return session, node, force
