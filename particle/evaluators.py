"""Batch evaluators of the particle model's force curves: the API calibration codes against.

An evaluator is built once per model and set of test points and then called
with many parameter sets (one per call, or a sequence of them in one call,
:meth:`~_PointEvaluator.evaluate_many`); it returns the force curves on
exactly the samples the FE reference uses (sign conventions as in docs/data-files.md:
the test vertex is pushed along its inward normal by depth d >= 0, the
reported force is the force the indenter applies to it, ``force_normal =
force . inward_normal``; no gravity). A flat punch holds several particles (its
footprint, all moved by ``depth * normal``) and its force is the sum of their reactions.

Each test point keeps a cache: its Newton solver with the last LU
factorisation, and the equilibria of the previous call, which warm-start the
next call (calibration moves parameters by small steps, so the previous
solution is an excellent guess and the old factorisation a good one).
Evaluators pickle (caches are rebuilt in the receiving process) so
calibration can run them in worker processes.

Where a point's loading path reaches a fold of the model (a weakly held particle snaps
through; :mod:`particle.statics`), the curve follows the model to the state it snaps to
(:meth:`~particle.statics.EquilibriumSolver.settle`), as a slow physical push would: the
curve is the path's from rest. Near such a fold the model has two equilibria, so from the
first sample where the previous call's or this call's path snapped on, a point's samples are
not warm-started (a warm start could land on the other one): they follow this call's path.
"""

from __future__ import annotations

import logging
from typing import Sequence

import numpy as np

from forcecal.errors import ConvergenceError, ParameterError
from particle.model import Model
from particle.nodal_volume import element_arm_recursion, element_arm_recursions
from particle.params import ConnectorParams, arm_recursions
from particle.statics import (ArmStep, Equilibrium, EquilibriumSolver, TangentPattern,
                              VolumeArmStep, check_stiffness, continuation, reaching)

log = logging.getLogger(__name__)


def normal_force(forces: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(P, S) normal components ``force . n`` [N] of (P, S, 3) force vectors [N] along the
    (P, 3) unit normals of their points: what every normal-force curve is."""
    return np.einsum("psc,pc->ps", forces, normals)


def force_components(forces: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(P, D S) components [N] of (P, S, 3) force vectors [N] along each of the (D, 3)
    ``directions``, direction-major (column ``d S + j``: direction d at sample j): the
    outputs of a component fit and of their Jacobian
    (:meth:`particle.sensitivity._Adjoint.jacobian`)."""
    forces = np.asarray(forces, dtype=np.float64)
    return np.einsum("psc,dc->pds", forces, directions).reshape(len(forces), -1)


def checked_footprints(model: Model, nodes: np.ndarray,
                       footprints: Sequence[np.ndarray] | None) -> tuple[np.ndarray, ...]:
    """Held particles of each test point ``nodes`` (k,) (default: the point alone, the paper's
    indenter), checked: each footprint holds its point."""
    if footprints is None:
        return tuple(nodes[k:k + 1] for k in range(len(nodes)))
    if len(footprints) != len(nodes):
        raise ParameterError(f"{len(nodes)} test points but {len(footprints)} footprints")
    out = []
    for node, held in zip(nodes, footprints):
        held = model.check_nodes(held, f"footprint of test point {node}")
        if node not in held:
            raise ParameterError(f"the footprint of test point {node} does not hold it")
        out.append(held)
    return tuple(out)


def checked_normals_and_depths(nodes: np.ndarray, normals: np.ndarray, depths: np.ndarray
                               ) -> tuple[np.ndarray, np.ndarray]:
    """(normals (k, 3), depths (D,) [m]) as float64, checked: one unit normal per test point,
    depths finite and >= 0."""
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if len(normals) != len(nodes):
        raise ParameterError(f"{len(nodes)} test points but {len(normals)} normals")
    lengths = np.linalg.norm(normals, axis=1)
    bad = np.nonzero(~(np.abs(lengths - 1.0) < 1e-6))[0]
    if len(bad):
        raise ParameterError(f"normal of test point {nodes[bad[0]]} has length "
                             f"{lengths[bad[0]]}; unit vectors are expected")
    depths = np.asarray(depths, dtype=np.float64).reshape(-1)
    if len(depths) == 0 or not np.all(np.isfinite(depths)) or np.any(depths < 0):
        raise ParameterError(f"depths must be finite and >= 0, got {depths}")
    return normals, depths


def check_depth_scale(model: Model, depths: np.ndarray) -> None:
    """Refuse indentation depths [m] beyond the model's size (its bounding-box diagonal): no
    indenter pushes a particle through the whole organ, so such a depth is a unit mistake
    (mm for m). :class:`ParameterError` with the size and a units hint. (Scenes have the
    stricter rule of :func:`forcecal.problem.check_depths`, below half the mean edge
    length; an API call may strain a lone connector further, so it gets only this one.)"""
    size = float(np.linalg.norm(np.ptp(model.rest_positions, axis=0)))
    deepest = float(depths.max())
    if not deepest <= size:
        raise ParameterError(f"depth {deepest:g} m is beyond the model's size (bounding-box "
                             f"diagonal {size:.3g} m): depths are in metres (5 mm is 0.005); "
                             "a value in mm?")


def warm_guess(warm: np.ndarray, solutions: np.ndarray, s: int) -> np.ndarray:
    """Previous call's equilibrium at sample ``s``, shifted by this call's change at ``s - 1``.

    The change a parameter update causes varies smoothly along the curve,
    so the shift removes most of the warm start's error.
    """
    return warm[s] if s == 0 else warm[s] + (solutions[s - 1] - warm[s - 1])


class _PointEvaluator:
    """Test points, their caches, parameter checks; subclasses define one point's curve."""

    def __init__(self, model: Model, nodes: np.ndarray, normals: np.ndarray,
                 depths: np.ndarray, *, strain_range: tuple[float, float] | None, rtol: float,
                 footprints: Sequence[np.ndarray] | None = None):
        self.model = model
        self.nodes = model.check_nodes(nodes, "test points")
        if len(self.nodes) == 0:
            raise ParameterError("no test points: an evaluator needs at least one test particle")
        self.footprints = checked_footprints(model, self.nodes, footprints)
        self.normals, self.depths = checked_normals_and_depths(self.nodes, normals, depths)
        check_depth_scale(model, self.depths)
        if strain_range is None:
            reach = float(self.depths.max() / model.incident_min_length(self.nodes).min())
            strain_range = (-min(reach, 0.9), reach)
        self.strain_range = strain_range
        self.rtol = self._own_rtol = rtol
        self._pattern = TangentPattern.of(model)
        self._solvers: dict[int, EquilibriumSolver] = {}
        self._warm: dict[int, np.ndarray] = {}
        self._factors: dict[int, list] = {}
        # point -> the first sample where its last call's path snapped (module docstring)
        self._snapped: dict[int, int] = {}

    def forget(self) -> None:
        """Drop every point's warm start and factorisations: the next call starts cold.

        Warm starts make a result depend (within the Newton tolerance) on the calls
        before it; calibration forgets them wherever it checkpoints, so a resumed fit
        repeats the uninterrupted one bit for bit.
        """
        self._solvers.clear()
        self._warm.clear()
        self._factors.clear()
        self._snapped.clear()

    def set_tolerance(self, rtol: float | None) -> None:
        """Newton tolerance of the next calls, relative to the indenter force (None: the one
        the evaluator was built with); starts them cold (:meth:`forget`), so no equilibrium
        solved to another tolerance seeds them."""
        rtol = self._own_rtol if rtol is None else rtol
        if not 0.0 < rtol < 1.0:
            raise ParameterError(f"Newton tolerance {rtol!r} must lie in (0, 1)")
        self.rtol = rtol
        self.forget()

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_factors"] = {}  # factorisations are not shipped; rebuilt on demand
        return state

    def _indices(self, points: Sequence[int] | None) -> np.ndarray:
        if points is None:
            return np.arange(len(self.nodes))
        idx = np.atleast_1d(np.asarray(points))
        if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer) or np.any(
                (idx < 0) | (idx >= len(self.nodes))):
            raise ParameterError(f"points {np.asarray(points).tolist()} must index the "
                                 f"{len(self.nodes)} test points")
        return idx.astype(np.int64)

    def _solver(self, k: int) -> EquilibriumSolver:
        if k not in self._solvers:
            self._solvers[k] = EquilibriumSolver(self.model, self.footprints[k], self._pattern,
                                                 rtol=self.rtol)
        return self._solvers[k]

    def force_vectors(self, params: ConnectorParams,
                      points: Sequence[int] | None = None) -> np.ndarray:
        """(P', S, 3) indenter forces [N] of the selected points (indices into ``nodes``)."""
        idx = self._indices(points)
        params.validate(self.strain_range, self.model.edges, self.model.tets)
        model = self.model.with_params(params)
        prepared = self._prepare(model.params)  # the volume arms broadcast to every tet
        return np.stack([self._curve(model, prepared, int(k)) for k in idx])

    def __call__(self, params: ConnectorParams, points: Sequence[int] | None = None) -> np.ndarray:
        """(P', S) normal forces [N] of the selected points (all if None).

        Raises ParameterError (non-physical parameters) or ConvergenceError; never NaN.
        """
        idx = self._indices(points)
        forces = self.force_vectors(params, idx)
        return normal_force(forces, self.normals[idx])

    def strain_extremes(self, points: Sequence[int] | None = None) -> np.ndarray:
        """(P', 2) the smallest and the largest connector strain [1] over every sample of the
        selected points' last curves: the strains their spring laws were evaluated at.
        :class:`ParameterError` for a point without a curve yet."""
        idx = self._indices(points)
        model = self.model
        out = np.empty((len(idx), 2))
        for row, k in enumerate(idx):
            x = self._warm.get(int(k))
            if x is None:
                raise ParameterError(f"test point {self.nodes[k]} has no curve yet")
            d = x[:, model.edges[:, 1]] - x[:, model.edges[:, 0]]
            strain = np.sqrt(np.sum(d * d, axis=2)) / model.rest_lengths - 1.0
            out[row] = strain.min(), strain.max()
        return out

    def evaluate_many(self, param_sets: Sequence[ConnectorParams],
                      points: Sequence[int] | None = None) -> np.ndarray:
        """(M, P', S) normal forces [N] of M parameter sets at the selected points (all if None).

        Exactly what M calls of the evaluator in this order return (each set
        warm-starts from the one before, as calibration's nearby sets do); every
        set is validated before the first is evaluated, so a bad one costs no
        work. Raises ParameterError or ConvergenceError; never NaN.
        """
        idx = self._indices(points)
        sets = list(param_sets)
        for params in sets:
            params.validate(self.strain_range, self.model.edges, self.model.tets)
        if not sets:
            return np.empty((0, len(idx), len(self.depths)))
        return np.stack([self(params, idx) for params in sets])

    def _prepare(self, params: ConnectorParams):
        """Per-call data shared by every point (nothing by default)."""
        return None

    def _curve(self, model: Model, prepared, k: int) -> np.ndarray:
        raise NotImplementedError

    def _samples(self, k: int, solver: EquilibriumSolver, n: int):
        """Sample indices 0..n-1 of point ``k``, each with last call's factorisation for it.

        The tangent changes along a curve much more than between two nearby
        parameter sets, so the factorisation that served sample ``s`` in the
        previous call is the best one to start sample ``s`` with; this avoids
        most refactorisations.
        """
        previous = self._factors.get(k)
        used = []
        for s in range(n):
            if previous is not None:
                solver.factorization = previous[s]
            yield s
            used.append(solver.factorization)
        self._factors[k] = used

    def _snaps(self, k: int, n: int) -> "_Snaps":
        """Point ``k``'s record of where its path snaps, for a call over ``n`` samples."""
        return _Snaps(self._snapped.get(k, n), n)

    def _target(self, k: int, depth: float) -> np.ndarray:
        """(K, 3) positions of point ``k``'s held particles at ``depth`` [m]."""
        return self.model.rest_positions[self.footprints[k]] + depth * self.normals[k]

    def _force(self, eq: Equilibrium, k: int) -> np.ndarray:
        """(3,) indenter force [N]: the sum of the held particles' reactions."""
        return eq.reaction(self.footprints[k]).sum(axis=0)


class IndentationEvaluator(_PointEvaluator):
    """Static indentation curves: equilibrium at each depth, long-term (spring-only) model.

    Args:
        model: the particle model (its parameters are ignored; each call brings its own).
        nodes: (P,) test particles.
        normals: (P, 3) inward unit normals (indentation directions).
        depths: (S,) indentation depths [m].
        strain_range: range over which K(eps) must stay positive; default
            +-(max depth / shortest connector at a test point).
        rtol: Newton tolerance relative to the indenter force.
        footprints: (P,) arrays of the particles each indenter holds (the test point
            among them), all moved by ``depth * normal``; the force is the sum of their
            reactions (a flat punch, :func:`forcecal.indenter.indenter_footprints`).
            None: the test point alone (the paper's indenter).
    """

    def __init__(self, model: Model, nodes: np.ndarray, normals: np.ndarray, depths: np.ndarray,
                 *, strain_range: tuple[float, float] | None = None, rtol: float = 1e-8,
                 footprints: Sequence[np.ndarray] | None = None):
        super().__init__(model, nodes, normals, depths, strain_range=strain_range, rtol=rtol,
                         footprints=footprints)

    def _curve(self, model: Model, prepared, k: int) -> np.ndarray:
        solver = self._solver(k)
        node, held = self.nodes[k], self.footprints[k]
        warm = self._warm.get(k)
        params = model.params

        def solve_at(x: np.ndarray, depth: float) -> Equilibrium:
            guess = x.copy()
            guess[held] = self._target(k, depth)
            return solver.solve(guess, params)

        def step(eq: Equilibrium, _: float, depth: float) -> Equilibrium:
            return solve_at(eq.x, depth)

        def settle(eq: Equilibrium, _: float, depth: float) -> Equilibrium:
            guess = eq.x.copy()
            guess[held] = self._target(k, depth)
            return snaps.settled(s, solver.settle(guess, params))

        solutions = np.empty((len(self.depths), model.n_particles, 3))
        forces = np.empty((len(self.depths), 3))
        eq, reached = Equilibrium.at_rest(model), 0.0
        snaps = self._snaps(k, len(self.depths))
        for s in self._samples(k, solver, len(self.depths)):
            depth = self.depths[s]
            warm_eq = None
            if warm is not None and snaps.warm(s):
                try:
                    warm_eq = solve_at(warm_guess(warm, solutions, s), depth)
                except ConvergenceError:
                    log.debug("point %d depth %g: warm start failed, continuing cold", node, depth)
            with reaching(lambda: reached):
                eq = warm_eq or continuation(step, eq, reached, depth, settle=settle,
                                             what=f"indentation of particle {node}")
                check_stiffness(model, eq.dx / model.rest_lengths, f"test point {self.nodes[k]}")
            reached = depth
            solutions[s] = eq.x
            forces[s] = self._force(eq, k)
        self._warm[k] = solutions
        self._snapped[k] = snaps.first
        return forces


class RelaxationEvaluator(_PointEvaluator):
    """Ramp-and-hold relaxation curves by the quasi-static path (inertia dropped).

    At each sample time the equilibrium of springs + Maxwell arms (and the volume
    term's arms, when it has them) is solved,
    the arms advanced by the exact exponential recursion for the sample step
    (``r = exp(-dt/tau)``, ``c = k tau (1 - r)/dt``, see
    :meth:`ConnectorParams.arm_recursion`). The indenter follows the depth
    schedule linearly between samples. A sample whose Newton solve fails is
    split into two half-steps (recursively).

    Why not the paper's recursion at the sample steps: its backward-Euler
    coefficients are first order in dt/tau, and the FE's samples are coarse
    (dt/tau_1 = 0.1 on the default liver's ramp, up to 16 late in the hold).
    Against the full explicit Verlet run (paper's recursion at dt ~ 1 ms), the
    exact recursion is within 0.08-0.11 % (relative RMS) on the default liver
    (uniform parameters, two test points, linear and nonlinear springs) and
    0.32 % on the box of the test, the paper's at the sample steps 0.76 % and
    1.4-1.5 %: as large as the calibrated model's whole relaxation error
    against the FE (0.80 %), and above the test's 1 % tolerance. So this
    fast path departs from the paper's recursion on purpose: it integrates the
    same continuous Maxwell arm exactly for an elongation linear within the
    step (the paper's recursion is its first-order approximation); the explicit
    runs keep the paper's recursion.

    Args:
        model, nodes, normals, strain_range, rtol, footprints: as :class:`IndentationEvaluator`.
        times: (S,) increasing sample times [s] (first > 0; the test starts at rest at 0).
        depths: (S,) indentation depth at those times [m].
    """

    def __init__(self, model: Model, nodes: np.ndarray, normals: np.ndarray, times: np.ndarray,
                 depths: np.ndarray, *, strain_range: tuple[float, float] | None = None,
                 rtol: float = 1e-8, footprints: Sequence[np.ndarray] | None = None):
        super().__init__(model, nodes, normals, depths, strain_range=strain_range, rtol=rtol,
                         footprints=footprints)
        times = np.asarray(times, dtype=np.float64).reshape(-1)
        if times.shape != self.depths.shape or not np.all(np.diff(np.r_[0.0, times]) > 0):
            raise ParameterError("relaxation times must be increasing, > 0 and match the depths")
        self.times = times

    def _prepare(self, params: ConnectorParams) -> list[tuple]:
        """Each sample step's arm coefficients: (r, c, the volume arms' (r, c) or None)."""
        steps = np.diff(np.r_[0.0, self.times])
        r, c = arm_recursions(params, steps, exact=True)
        volume = (list(zip(*element_arm_recursions(self.model.with_params(params), steps,
                                                   exact=True)))
                  if params.has_volume_arms else [None] * len(steps))
        return list(zip(r, c, volume))

    def _curve(self, model: Model, prepared, k: int) -> np.ndarray:
        solver = self._solver(k)
        node, held = self.nodes[k], self.footprints[k]
        params = model.params
        warm = self._warm.get(k)
        times = np.r_[0.0, self.times]
        depths = np.r_[0.0, self.depths]
        solutions = np.empty((len(self.times), model.n_particles, 3))
        forces = np.empty((len(self.times), 3))
        eq = Equilibrium.at_rest(model)
        snaps = self._snaps(k, len(self.times))
        for sample in self._samples(k, solver, len(self.times)):
            whole = (times[sample], times[sample + 1])

            def step(eq: Equilibrium, t0: float, t1: float, sample=sample, whole=whole,
                     settling=False):
                full = (t0, t1) == whole
                warm_start = full and warm is not None and snaps.warm(sample) and not settling
                guess = (warm_guess(warm, solutions, sample) if warm_start else eq.x).copy()
                guess[held] = self._target(k, np.interp(t1, times, depths))
                coeffs = (prepared[sample] if full
                          else arm_coefficients(params, t1 - t0, model=model))
                if settling:
                    return snaps.settled(sample, solver.settle(guess, params,
                                                               arms=arm_step(coeffs, eq)))
                return solver.solve(guess, params, arms=arm_step(coeffs, eq))

            with reaching(lambda: whole[0]):
                eq = continuation(step, eq, *whole, what=f"relaxation of particle {node}",
                                  settle=lambda eq, t0, t1, step=step: step(eq, t0, t1,
                                                                            settling=True))
                check_stiffness(model, eq.dx / model.rest_lengths, f"test point {self.nodes[k]}")
            solutions[sample] = eq.x
            forces[sample] = self._force(eq, k)
        self._warm[k] = solutions
        self._snapped[k] = snaps.first
        return forces


class _Snaps:
    """Where the paths of a point's previous call and of this call snap (module docstring).

    Attributes:
        previous: the first sample whose path snapped in the previous call (the number of
            samples if none did).
        first: the same in this call, so far.
    """

    def __init__(self, previous: int, n: int):
        self.previous, self.first = previous, n

    def warm(self, sample: int) -> bool:
        """True if ``sample`` may be warm-started (it comes before every snap)."""
        return sample < min(self.previous, self.first)

    def settled(self, sample: int, eq: Equilibrium) -> Equilibrium:
        """Record that ``sample``'s path snapped to ``eq``; returns ``eq``."""
        self.first = min(self.first, sample)
        return eq


def arm_coefficients(params: ConnectorParams, dt: float, *, model: Model | None = None
                     ) -> tuple:
    """(r, c, the volume arms' (r, c) or None) of one exact arm step of ``dt`` [s]; the
    volume arms' rows are ``model``'s volume elements (its particles for the nodal term;
    None: per tet)."""
    volume = None
    if params.has_volume_arms:
        volume = (params.volume_arm_recursion(dt, exact=True) if model is None
                  else element_arm_recursion(model.with_params(params), dt, exact=True))
    return (*params.arm_recursion(dt, exact=True), volume)


def arm_step(coeffs: tuple, eq: Equilibrium) -> ArmStep:
    """The arm step with ``coeffs`` (:func:`arm_coefficients`) from the equilibrium ``eq``."""
    r, c, volume = coeffs
    return ArmStep(r, c, eq.arm_force, eq.dx, None if volume is None else
                   VolumeArmStep(*volume, eq.volume_arm, eq.volume_strain))
