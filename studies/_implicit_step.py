"""A linearised implicit haptic step (the subject of the study :mod:`studies.implicit_haptics`).

One step per device period ``h``, in residual form (its fixed point is the exact nonlinear
equilibrium; only the dynamics carry the linearisation error):

* Newmark's average acceleration (the trapezoidal rule: no numerical damping, period error
  ``(omega h)^2 / 12``), its HHT-alpha variant ``M a_{n+1} + (1 + alpha) f(x_{n+1}) - alpha
  f(x_n) = 0``, ``beta = (1 - alpha)^2 / 4``, ``gamma = 1/2 - alpha`` (``alpha`` in [-1/3, 0]
  damps the modes near the Nyquist rate), or backward Euler ``M (x_{n+1} - x_n - h v_n) / h^2
  = f(x_{n+1})`` (an undamped mode keeps ``(1 + (omega h)^2)^(-1/2)`` of its amplitude a step);
* one solve ``(m M + k K0) dx = R(x_n)`` (``m = 1/(beta h^2)``, ``k = 1 + alpha``; backward
  Euler ``1/h^2``, 1), ``K0`` the tangent at rest with the arms' step coefficients ``c_i = k_i
  b_i / (k_i h + b_i)`` and the volume term's (:func:`particle.statics.tangent_data`),
  factorised once per tool (:mod:`particle.sparse_ldl`; the tool's dofs constrained, its move
  entering the right-hand side through the matrix's columns);
* ``R(x_n)`` the exact nonlinear forces at the step's start (the arms advanced by the model's
  own recursion ``F = r F_n + c (dx - dx_n)``) minus the inertia the kinematics give for
  ``x_{n+1} = x_n``; after the solve one pass at ``x_{n+1}`` (:func:`end_of_step`) commits the
  arms and writes the next residual's forces and the force on the tool.

For a linear network the step is exact Newmark (or backward Euler); a nonlinear one leaves the
residual ``(K(x) - K0) dx`` each step. ``iterations`` > 1 repeats the solve on the residual at
the iterate (modified Newton on the one factor): the converged scheme, whose error is the
time discretisation's alone.
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass

import numba
import numpy as np
from numba import njit

from forcecal.errors import MeshError, ParameterError, StabilityError
from particle.integrator import incident
from particle.kernels import JIT, add_gravity, index_view, internal_forces, node_force
from particle.model import Model, check_gravity
from particle.sparse_ldl import _solve_one
from particle.statics import (ArmStep, TangentPattern, VolumeArmStep, ldl_factor, net_forces,
                              tangent_data)
from particle.volume import add_volume_forces, node_volume_force, tet_name

PERIOD = 1e-3  # s: the device period, one implicit step


@dataclass(frozen=True)
class Scheme:
    """One implicit scheme: ``name``, HHT's ``alpha`` (0: Newmark's average acceleration) or
    ``euler`` (backward Euler), and the modified Newton ``iterations`` per step (1: the
    linearised step)."""
    name: str
    alpha: float = 0.0
    euler: bool = False
    iterations: int = 1

    def __post_init__(self) -> None:
        if not -1.0 / 3.0 <= self.alpha <= 0.0:
            raise ParameterError(f"HHT alpha = {self.alpha} must be in [-1/3, 0]")
        if self.euler and self.alpha != 0.0:
            raise ParameterError("backward Euler has no HHT alpha")
        if not (isinstance(self.iterations, int) and self.iterations >= 1):
            raise ParameterError(f"iterations = {self.iterations!r} must be an integer >= 1")

    @property
    def beta(self) -> float:
        return (1.0 - self.alpha) ** 2 / 4.0

    @property
    def gamma(self) -> float:
        return 0.5 - self.alpha

    def coefficients(self, h: float) -> tuple[float, float]:
        """(mass, stiffness) factors of the step's matrix ``m M + k K0``."""
        if self.euler:
            return 1.0 / h ** 2, 1.0
        return 1.0 / (self.beta * h * h), 1.0 + self.alpha


NEWMARK = Scheme("newmark")


def rest_tangent(model: Model, h: float, pattern: TangentPattern, arms: bool = True
                 ) -> np.ndarray:
    """CSC data [N/m] of the tangent at the rest state in ``pattern``'s storage, the arms'
    (and the volume arms') step coefficients at the step ``h`` [s] included (``arms``
    False: without them, the tangent of a run whose arms are held at zero)."""
    p = model.params
    step, volume_arm = arm_step(model, h) if arms else (None, None)
    return tangent_data(model, pattern, model.rest_positions, np.zeros(model.n_connectors), p,
                        not p.is_linear, step, volume_arm)


def arm_step(model: Model, h: float, state: tuple | None = None
             ) -> tuple[ArmStep, np.ndarray | None]:
    """(the statics' arm step of ``model``'s arms at the step ``h`` [s] from ``state`` =
    (arm forces (E, 2), elongations (E,), volume pressures (T, 2), volume strains (T,)),
    None: at rest; zero volume pressures (T, 2) with volume arms, else None)."""
    p, e, t = model.params, model.n_connectors, model.n_tets
    state = state or (np.zeros((e, 2)), np.zeros(e), np.zeros((t, 2)), np.zeros(t))
    step = ArmStep(*p.arm_recursion(h), state[0], state[1])
    if p.kv is None or not p.has_volume_arms:
        return step, None
    vr, vc = p.volume_arm_recursion(h)
    step.volume = VolumeArmStep(vr, vc, state[2], state[3])
    return step, np.zeros_like(vr)


@njit(**JIT)
def end_of_step(x, springs, arms, volume, loads, forces, tool, tool_force):
    """The force pass at the end of a step, at ``x`` (N, 3) [m], with the explicit step's own
    kernels: commits the arms' step and writes ``g_next`` (N, 3) [N], the net force the next
    step's residual starts from (its arms advanced by the next step's recursion to ``r F``:
    the pass runs with ``r^2, r c`` and stores ``r F``, divided by ``r`` after), with
    ``need_end`` ``g_end`` (N, 3) [N], the net force with the committed arms (HHT's
    ``f(x_n)``, a second pass), and ``tool_force`` (3,) [N], the connectors' and tets' force
    on ``tool`` = (particle (-1: none), its connectors, its tets) with the committed arms
    (what the explicit session's probe returns).

    ``springs`` = (edges, rest lengths, K0, a, b, elongations scratch (E,)); ``arms`` = (r,
    c, r^2, r c, forces (E, 2), elongations (E,), scratch (E, 2), ones (E, 2), zeros (E, 2))
    or None (no arms); ``volume`` = (tets, rest volumes, kv, v_lo = 0, v_hi = inf, the commit
    pass's arms, the probe's, the second pass's (each None without volume arms), r (M, 2),
    pressures (M, 2), scratch (M, 2)) or None (no volume term); ``loads`` = (masses (N,),
    gravity (3,), free particles); ``forces`` = (g_next, g_end, need_end). Returns the first
    inverted tet, -1 if none.
    """
    edges, rest_lengths, K0, a, b, dx_scratch = springs
    g_next, g_end, need_end = forces
    masses, gravity, free = loads
    if arms is None:
        internal_forces(x, edges, rest_lengths, K0, a, b, None, None, None, None, g_next,
                        None, None, dx_scratch)
    else:
        r, c, r2, rc, arm, dx, scratch, ones, zeros = arms
        internal_forces(x, edges, rest_lengths, K0, a, b, r2, rc, arm, dx, g_next, None,
                        scratch, dx)
        divide(scratch, r, arm)
    inverted = -1
    if volume is not None:
        tets, rest_volumes, kv, v_lo, v_hi, commit, probe, end, vr, pressure, held = volume
        inverted, _ = add_volume_forces(x, tets, rest_volumes, kv, v_lo, v_hi, g_next, commit)
        divide(held, vr, pressure)
    add_gravity(g_next, masses, gravity, free)
    if tool[0] >= 0:
        if arms is None:
            node_force(x, tool[0], tool[1], edges, rest_lengths, K0, a, b, None, None, None,
                       None, tool_force)
        else:
            node_force(x, tool[0], tool[1], edges, rest_lengths, K0, a, b, ones, zeros, arm,
                       dx, tool_force)
        if volume is not None:
            node_volume_force(x, tool[0], tool[2], tets, rest_volumes, kv, probe, tool_force)
    if need_end:
        if arms is None:
            internal_forces(x, edges, rest_lengths, K0, a, b, None, None, None, None, g_end,
                            None, None, dx_scratch)
        else:
            internal_forces(x, edges, rest_lengths, K0, a, b, ones, zeros, arm, dx, g_end,
                            None, scratch, dx_scratch)
        if volume is not None:
            add_volume_forces(x, tets, rest_volumes, kv, v_lo, v_hi, g_end, end)
        add_gravity(g_end, masses, gravity, free)
    return inverted


@njit(**JIT)
def divide(values, by, out):
    """``out = values / by`` ((M, 2) arrays)."""
    for k in range(values.shape[0]):
        out[k, 0] = values[k, 0] / by[k, 0]
        out[k, 1] = values[k, 1] / by[k, 1]


@njit(**JIT)
def residual(forces, g_end, v, acc, offset, mass, flat, scheme, rhs):
    """``rhs`` (n,) = the step's residual [N] at the iterate ``x_n + offset`` (``offset``
    (n,) [m] per dof): ``(1 + alpha) f - alpha f_n - M a`` with ``f`` = ``forces`` (3N,) [N]
    there, ``f_n`` = ``g_end`` (3N,), ``a`` the acceleration the scheme's kinematics give
    (``v``, ``acc`` (3N,) the state's; ``flat`` (n,) each dof's index in them; ``mass`` (n,)
    [kg]; ``scheme`` = (h, alpha, beta, gamma, euler))."""
    h, alpha, beta, gamma, euler = scheme
    for k in range(flat.shape[0]):
        f = flat[k]
        if euler:
            inertia = (offset[k] - h * v[f]) / (h * h)
        else:
            inertia = (offset[k] - h * v[f] - h * h * (0.5 - beta) * acc[f]) / (beta * h * h)
        rhs[k] = (1.0 + alpha) * forces[f] - alpha * g_end[f] - mass[k] * inertia


@njit(**JIT)
def update(v, acc, delta, flat, scheme):
    """The velocities and accelerations (3N,) after the motion ``delta`` (n,) [m] per dof (the
    caller moves the positions). Returns False if a motion is not finite."""
    h, alpha, beta, gamma, euler = scheme
    total = 0.0
    for k in range(flat.shape[0]):
        f = flat[k]
        d = delta[k]
        total += d
        if euler:
            v[f] = d / h
        else:
            a_new = (d - h * v[f] - h * h * (0.5 - beta) * acc[f]) / (beta * h * h)
            v[f] += h * ((1.0 - gamma) * acc[f] + gamma * a_new)
            acc[f] = a_new
    return np.isfinite(total)


@njit(**JIT)
def first_solve(state, forces, scheme, factor, constraint, target, scratch):
    """The step's first solve from ``x_n``: :func:`residual` of ``g_next``, the tool's move
    through the matrix's coupling entries, the substitution; the positions moved by ``delta``
    (n,), left with the motion (the tool's to ``target`` (3,) [m] included).

    ``state`` = (x (N, 3), its flat view, v (3N,), a (3N,)), ``forces`` = (g_next, g_end)
    flat, ``factor`` = :func:`~particle.sparse_ldl._solve_one`'s seven leading arrays,
    ``constraint`` = (tool (-1: none), its three dofs, the coupled dofs (k,), the tool's
    component of each, the matrix entries there, its connectors, its tets), ``scratch`` =
    (masses per dof (n,), each dof's flat index, zeros, rhs, delta).
    """
    x, xf, v, acc = state
    tool, tool_dofs, rows, comps, values = constraint[:5]
    mass, flat, offset, rhs, delta = scratch
    residual(forces[0], forces[1], v, acc, offset, mass, flat, scheme, rhs)
    if tool >= 0:
        for p in range(rows.shape[0]):
            rhs[rows[p]] -= values[p] * (target[comps[p]] - x[tool, comps[p]])
        for q in range(3):
            rhs[tool_dofs[q]] = 0.0
    _solve_one(factor[0], factor[1], factor[2], factor[3], factor[4], factor[5], factor[6],
               rhs, delta)
    if tool >= 0:  # its identity rows left 0 there: its prescribed move instead
        for q in range(3):
            delta[tool_dofs[q]] = target[q] - x[tool, q]
    for k in range(flat.shape[0]):
        xf[flat[k]] += delta[k]


@njit(**JIT)
def finish(state, scheme, delta, flat, model_groups, forces, tool, tool_force):
    """The step's end after its solves: velocities and accelerations from the motion
    ``delta`` (n,) (the tool's by the same kinematics: they enter no other row), and
    :func:`end_of_step`'s pass (``model_groups`` = its springs, arms, volume, loads;
    ``forces`` = (g_next, g_end, need_end); ``tool`` = (particle or -1, its connectors, its
    tets)). Returns (first inverted tet or -1, finite)."""
    finite = update(state[2], state[3], delta, flat, scheme)
    springs, arms, volume, loads = model_groups
    inverted = end_of_step(state[0], springs, arms, volume, loads, forces, tool, tool_force)
    return inverted, finite


@njit(**JIT)
def implicit_step(state, forces, scheme, factor, constraint, target, scratch, model_groups,
                  tool_force):
    """One linearised step: :func:`first_solve` then :func:`finish` (one compiled call).
    ``forces`` = (g_next (N, 3), g_end (N, 3), need_end)."""
    g_next, g_end, need_end = forces
    first_solve(state, (g_next.reshape(-1), g_end.reshape(-1)), scheme, factor, constraint,
                target, scratch)
    return finish(state, scheme, scratch[4], scratch[1], model_groups, forces,
                  (constraint[0], constraint[5], constraint[6]), tool_force)


class ImplicitSession:
    """A haptic session of one implicit step per period (module docstring), with the explicit
    :class:`~particle.haptics.HapticSession`'s interface: :meth:`step` moves a tool particle
    and returns the force on it; :meth:`advance` steps without a tool (a release).

    Args:
        model: the particle model (per-tet volume term, elastic or relaxing, or none).
        scheme: the implicit scheme.
        period: the step [s].
        gravity: (3,) [m/s^2] or None.
        arms: False holds the Maxwell arms (and the volume arms) at zero.

    Attributes: ``x``, ``v`` (N, 3) the positions [m] and velocities [m/s], ``t`` [s].
    Raises ParameterError (a bad period or gravity), MeshError (the nodal volume element,
    not supported; a tool that is not a free particle), StabilityError from :meth:`step` and
    :meth:`advance` (a non-finite update or an inverted tet: the session is then invalid).
    """

    def __init__(self, model: Model, scheme: Scheme = NEWMARK, *, period: float = PERIOD,
                 gravity: np.ndarray | None = None, arms: bool = True) -> None:
        if not (math.isfinite(period) and period > 0.0):
            raise ParameterError(f"implicit step = {period} s must be > 0")
        if model.params.kv is not None and model.volume_element != "tet":
            raise MeshError("the implicit step supports the per-tet volume term only")
        self.model, self.scheme, self.h, self.arms = model, scheme, float(period), arms
        self.gravity = check_gravity(gravity)
        p = model.params
        n, e = model.n_particles, model.n_connectors
        self.x = model.rest_positions.copy()
        self.v, self._acc = np.zeros((n, 3)), np.zeros((n, 3))
        self.t = 0.0
        springs = (index_view(model.edges), model.rest_lengths, p.K0,
                   None if p.is_linear else p.a, None if p.is_linear else p.b, np.empty(e))
        arm_groups = None
        force, dx = np.zeros((e, 2)), np.zeros(e)
        if arms:
            r, c = p.arm_recursion(self.h)
            arm_groups = (r, c, r * r, r * c, force, dx, np.empty((e, 2)), np.ones((e, 2)),
                          np.zeros((e, 2)))
        volume = None
        pressure, strain = np.zeros((0, 2)), np.zeros(0)
        if p.kv is not None:
            t = model.n_tets
            commit = probe = end = None
            vr = held = pressure
            if p.has_volume_arms and arms:
                vr, vc = p.volume_arm_recursion(self.h)
                pressure, strain, held = np.zeros((t, 2)), np.zeros(t), np.empty((t, 2))
                ones, zeros = np.ones((t, 2)), np.zeros((t, 2))
                commit = (vr * vr, vr * vc, pressure, strain, held, strain)
                probe = (ones, zeros, pressure, strain)
                end = (ones, zeros, pressure, strain, np.empty((t, 2)), np.empty(t))
            volume = (index_view(model.tets), model.rest_volumes,
                      np.broadcast_to(p.kv, (t,)).astype(np.float64), np.zeros(t),
                      np.full(t, np.inf), commit, probe, end, vr, pressure, held)
        self._arm_state = (force, dx, pressure, strain)
        loads = (model.masses, np.zeros(3) if self.gravity is None else self.gravity,
                 index_view(model.free_nodes))
        self._groups = (springs, arm_groups, volume, loads)
        self._g_next, self._g_end = np.zeros((n, 3)), np.zeros((n, 3))
        self._forces = (self._g_next, self._g_end, scheme.alpha != 0.0)
        self._tool_force = np.zeros(3)
        # the step matrix m M + k K0 (the arms' coefficients as stepped: none without arms)
        self.pattern = TangentPattern.of(model)
        mass_coef, stiff_coef = scheme.coefficients(self.h)
        free = model.free_nodes
        mass = np.repeat(model.masses[free], 3)
        self._matrix = stiff_coef * rest_tangent(model, self.h, self.pattern, arms)
        self._matrix[self.pattern.diagonal] += mass_coef * mass
        flat = (3 * free[:, None] + np.arange(3)).ravel()
        size = len(flat)
        self._scratch = (mass, flat, np.zeros(size), np.empty(size), np.empty(size))
        self._factors: dict[int, tuple] = {}
        # implicit_step's entry point by tool: its arguments' fingerprints are past the length
        # numba's dispatch caches intact (particle.dispatch); every call has the same types
        self._entries: dict[int, object] = {}
        self._scheme = (self.h, float(scheme.alpha), scheme.beta, scheme.gamma,
                        bool(scheme.euler))  # the kernels' scheme group
        # at rest: the forces, and the consistent initial acceleration M^-1 f(x_0)
        none = index_view(np.zeros(0, np.int64))
        end_of_step(self.x, springs, arm_groups, volume, loads,
                    (self._g_next, self._g_end, True), (-1, none, none), self._tool_force)
        self._acc[free] = self._g_end[free] / model.masses[free, None]
        self._state = (self.x, self.x.reshape(-1), self.v.reshape(-1), self._acc.reshape(-1))

    def _constraint(self, tool: int) -> tuple:
        """(factor arrays, constraint group) of tool particle ``tool`` (-1: none), cached: the
        step matrix with the tool's dofs replaced by identity rows, factorised, and the
        matrix's entries coupling the other dofs to the tool's move."""
        found = self._factors.get(tool)
        if found is not None:
            return found
        data = self._matrix.copy()
        pat = self.pattern
        dofs, coupled = np.zeros(3, np.int64), []
        edges = tets = index_view(np.zeros(0, np.int64))
        if tool >= 0:
            edges, tets = incident(self.model, tool, True)
            dofs = pat.dofs(np.array([tool]))
            coupled = [(pat.indices[k], q, data[k]) for q, d in enumerate(dofs)
                       for k in range(pat.indptr[d], pat.indptr[d + 1])
                       if pat.indices[k] not in dofs]
            slots, diagonal = pat.constraint_slots(np.array([tool]))
            data[slots] = 0.0
            data[diagonal] = 1.0
        f = ldl_factor(pat, data)
        s = f.symbolic
        found = self._factors[tool] = (
            (s.sup_ptr, s.row_ptr, s.rows, s.x_ptr, f.x, f.d, s.perm),
            (int(tool), np.asarray(dofs, np.int64),
             np.array([row for row, _, _ in coupled], np.int64),
             np.array([q for _, q, _ in coupled], np.int64),
             np.array([value for _, _, value in coupled], np.float64), edges, tets))
        return found

    def step(self, tool_node: int, tool_position: np.ndarray) -> np.ndarray:
        """Advance one period with particle ``tool_node`` moved to ``tool_position`` (3,) [m];
        the (3,) force the tissue exerts on it at the end of the period [N]."""
        try:
            node = operator.index(tool_node)
        except TypeError:
            raise MeshError(f"tool node {tool_node!r} must be an integer particle id") from None
        if not 0 <= node < self.model.n_particles or self.model.fixed[node]:
            raise MeshError(f"tool node {node} is not a free particle of the model")
        target = np.array(tool_position, dtype=np.float64)  # C-contiguous: the typed entry's
        if target.shape != (3,) or not np.all(np.isfinite(target)):
            raise ParameterError(f"tool position {tool_position!r} must be 3 finite "
                                 "coordinates [m]")
        self._advance(node, target)
        return self._tool_force.copy()

    def advance(self, steps: int = 1) -> None:
        """``steps`` periods without a tool."""
        for _ in range(steps):
            self._advance(-1, self._tool_force)

    def _advance(self, tool: int, target: np.ndarray) -> None:
        factor, constraint = self._constraint(tool)
        if self.scheme.iterations == 1:
            args = (self._state, self._forces, self._scheme, factor, constraint, target,
                    self._scratch, self._groups, self._tool_force)
            entry = self._entries.get(tool)
            if entry is None:  # typed once (numba.typeof: ~0.4 ms), then called directly
                inverted, finite = implicit_step(*args)
                signature = tuple(numba.typeof(a) for a in args)
                self._entries[tool] = implicit_step.overloads[signature].entry_point
            else:
                inverted, finite = entry(*args)
        else:
            inverted, finite = self._iterated(factor, constraint, target)
        self.t += self.h
        if not finite:
            raise StabilityError(f"implicit step ({self.scheme.name}) at t = {self.t:.6g} s: "
                                 "non-finite position update")
        if inverted >= 0:
            raise StabilityError(f"implicit step ({self.scheme.name}) at t = {self.t:.6g} s: "
                                 f"{tet_name(inverted, self.model.tets)} inverted")

    def _iterated(self, factor: tuple, constraint: tuple, target: np.ndarray) -> tuple:
        """The step with ``scheme.iterations`` solves (modified Newton on the one factor, the
        forces at each iterate from :func:`particle.statics.net_forces`)."""
        mass, flat, _, rhs, delta = self._scratch
        x_flat, start = self._state[1], self._state[1][flat].copy()
        first_solve(self._state, (self._g_next.reshape(-1), self._g_end.reshape(-1)),
                    self._scheme, factor, constraint, target, self._scratch)
        model, p = self.model, self.model.params
        step = arm_step(model, self.h, self._arm_state)[0] if self.arms else None
        limits = (np.zeros(model.n_tets), np.full(model.n_tets, np.inf))
        tool, tool_dofs = constraint[0], constraint[1]
        for _ in range(self.scheme.iterations - 1):
            forces = net_forces(model, self.x, p, not p.is_linear, step, self.gravity,
                                limits)[0]
            offset = x_flat[flat] - start
            residual(forces.reshape(-1), self._g_end.reshape(-1), self._state[2],
                     self._state[3], offset, mass, flat, self._scheme, rhs)
            if tool >= 0:
                rhs[tool_dofs] = 0.0
            _solve_one(*factor, rhs, delta)
            x_flat[flat] += delta
        motion = x_flat[flat] - start
        return finish(self._state, self._scheme, motion, flat, self._groups, self._forces,
                      (tool, constraint[5], constraint[6]), self._tool_force)
