"""Static equilibrium by Newton's method with the analytic sparse tangent.

The unknowns are the positions of the free particles that are not prescribed.
Each connector contributes the 3x3 tangent block ``s e e^T + (F/l)(I - e e^T)``
(axial tangent ``s = K0 + 2 a eps + 3 b eps^2`` plus, for a quasi-static arm
step, the arm coefficients ``sum_i c_i``; geometric term F/l). The matrix is
assembled by a compiled kernel straight into CSC storage through a
precomputed index map (:class:`TangentPattern`, no Python loop over
connectors); with the volume term (``params.kv``) each tet adds its 12x12
block ``kv/V0 g g^T + kv (V/V0 - 1) d^2V/dx^2``
(:func:`particle.volume.add_volume_tangent`) through the same map (a tet's vertex
pairs are connectors; the nodal term, :mod:`particle.nodal_volume`, couples each
particle's star, whose pairs :class:`NodalPattern` adds), and with its Maxwell arms in a
quasi-static arm step their
coefficients and pressures (:class:`VolumeArmStep`; without an arm step, as in the
long-term indentation curves and the static sag, the arms are relaxed: ``kv`` alone);
prescribed particles keep their rows and columns with an identity block, so one
pattern serves every test point. :mod:`particle.sparse_ldl`
factorises it (``L D L^T`` without pivoting, its ordering and symbolic analysis
done once per pattern: :attr:`TangentPattern.ldl`); :func:`superlu` is the
reference it replaced.

Factorisations are expensive next to a solve, so :class:`EquilibriumSolver`
runs a *modified* Newton iteration: it keeps its LU between iterations, load
steps and calls, and refactorises only when the residual stops contracting
fast (ratio above ``refactor_ratio``). A step that does not reduce the
residual with a fresh factorisation is backtracked (line search); a load step
that still fails is halved by :func:`continuation`. The iteration runs as one compiled
loop (:mod:`particle.statics_kernels`, factorisations included: on small meshes the cost
of calling the kernels from Python was most of it) that returns to Python only where a
tangent has a zero pivot (:func:`factorize`'s shifted retry).

Where the equilibrium being followed ends (a fold of the loading path: a weakly held
particle snaps through a face of its neighbours, the tangent's smallest eigenvalue going to
zero like the square root of the distance to the fold), no Newton iteration and no
shorter load step finds a nearby state: the model itself moves on to another one. A
physical push comes to rest there through its damping, and :meth:`EquilibriumSolver.settle`
computes that state by pseudo-transient continuation (implicit Euler steps of an overdamped
motion ending in Newton's iteration); :func:`continuation` calls it where halving ends.
"""

from __future__ import annotations

import contextlib
import logging
import math
from dataclasses import dataclass
from functools import cached_property
from typing import Callable, Iterator, TypeVar

import numpy as np
from numba import njit

from forcecal.errors import ConvergenceError, ParameterError, StabilityError
from particle import kernels, sparse_ldl
from particle.kernels import JIT
from particle.model import Model, check_gravity
from particle.params import ConnectorParams, connector_name
from particle.statics_kernels import CONVERGED, FACTORISE, converged, newton_iterations
from particle.nodal_kernels import add_nodal_volume_forces, add_nodal_volume_tangent
from particle.nodal_volume import element_coefficients, element_strains
from particle.volume import (add_volume_forces_grouped, add_volume_tangent, signed_volumes,
                             tet_name)
from particle.volume import tet_slots as volume_tet_slots

log = logging.getLogger(__name__)

T = TypeVar("T")
#: what the compiled Newton loop gets for no gravity and no factorisation's L, D yet (unread)
_NO_GRAVITY = np.zeros(3)
_NO_FACTOR = np.zeros(0)
#: the compiled loop's nodal pattern for a per-tet model (unread; typed as a nodal one's)
_NO_NODAL_PATTERN = (np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros((0, 4), np.int64),
                     np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros((0, 3, 3), np.int64))
#: most damped steps of :meth:`EquilibriumSolver.settle`, and most increases of its shift
#: in one step (4^30: the step is then a vanishing move along the force)
SETTLE_ITERATIONS, SETTLE_SHIFTS = 200, 30


@dataclass(frozen=True, eq=False)
class TangentPattern:
    """CSC sparsity of the tangent on the dofs of the non-fixed particles.

    Attributes:
        node_dof: (N,) int64, first dof (3 per particle) of each particle, -1 if fixed.
        indptr: (n + 1,) int32, CSC column pointers (n = 3 x non-fixed particles).
        indices: (nnz,) int32, CSC row indices.
        slots: (E, 4, 3, 3) int64, data index of each entry of the connector blocks
            (i,i), (j,j), (i,j), (j,i); -1 where a fixed particle is involved.
        tet_slots: (T, 4, 4, 3, 3) int64, data index of each entry of the tets'
            vertex blocks (a, b) (:func:`particle.volume.tet_slots`), -1 likewise.
        nodal: the nodal volume term's blocks (:class:`NodalPattern`: a particle's one-ring
            couples every pair of its star, so the pattern holds those pairs too), or None
            (a per-tet model: the pattern is the connectors').
    """
    node_dof: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    slots: np.ndarray
    tet_slots: np.ndarray | None = None
    nodal: "NodalPattern | None" = None

    @classmethod
    def of(cls, model: Model) -> "TangentPattern":
        node_dof = np.full(model.n_particles, -1, dtype=np.int64)
        node_dof[model.free_nodes] = 3 * np.arange(len(model.free_nodes))
        i, j = model.edges[:, 0], model.edges[:, 1]
        blocks = np.stack([np.column_stack(pair) for pair in ((i, i), (j, j), (i, j), (j, i))],
                          axis=1)  # (E, 4, 2): row node, column node
        r0 = node_dof[blocks[..., 0]][..., None, None] + np.arange(3)[:, None]
        c0 = node_dof[blocks[..., 1]][..., None, None] + np.arange(3)[None, :]
        rows, cols = np.broadcast_arrays(r0, c0)
        valid = (node_dof[blocks[..., 0]] >= 0) & (node_dof[blocks[..., 1]] >= 0)
        valid = np.broadcast_to(valid[..., None, None], rows.shape)
        n = 3 * len(model.free_nodes)
        keys = cols[valid] * n + rows[valid]
        stars = None
        if model.volume_element == "nodal" and model.n_tets:
            stars = NodalPattern.stars(model.tets, model.n_particles)
            keys = np.concatenate([keys, NodalPattern.keys(stars, node_dof, n)])
        unique = np.unique(keys)
        slots = np.full(rows.shape, -1, dtype=np.int64)
        slots[valid] = np.searchsorted(unique, keys[:int(valid.sum())])
        indptr = np.searchsorted(unique // n, np.arange(n + 1)).astype(np.int32)
        indices = (unique % n).astype(np.int32)
        return cls(node_dof=node_dof, indptr=indptr, indices=indices, slots=slots,
                   tet_slots=volume_tet_slots(model.tets, node_dof, indptr, indices),
                   nodal=None if stars is None else NodalPattern.of(stars, model.tets,
                                                                     node_dof, unique, n))

    @property
    def n_dofs(self) -> int:
        return len(self.indptr) - 1

    @cached_property
    def ldl(self) -> sparse_ldl.Symbolic:
        """Ordering and symbolic ``L D L^T`` analysis of the pattern (computed on first use,
        then kept: the pattern never changes, a tangent's values do at every call)."""
        return sparse_ldl.analyse(self.indptr, self.indices)

    def dofs(self, nodes: np.ndarray) -> np.ndarray:
        """(3k,) matrix dofs of non-fixed particles ``nodes``."""
        return (self.node_dof[nodes][:, None] + np.arange(3)).ravel()

    @property
    def diagonal(self) -> np.ndarray:
        """(n,) data indices of the diagonal entries."""
        cols = np.repeat(np.arange(self.n_dofs), np.diff(self.indptr))
        return np.nonzero(self.indices == cols)[0]

    def constraint_slots(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Data indices of the rows/columns of ``nodes``' dofs, and of their diagonal entries."""
        dofs = self.dofs(nodes)
        cols = np.repeat(np.arange(self.n_dofs), np.diff(self.indptr))
        in_row = np.isin(self.indices, dofs)
        in_col = np.isin(cols, dofs)
        diag = np.nonzero(in_row & (self.indices == cols))[0]
        return np.nonzero(in_row | in_col)[0], diag


@dataclass(frozen=True, eq=False)
class NodalPattern:
    """Where the nodal volume term's rank-one blocks go in a :class:`TangentPattern`.

    Particle n's term ``k_n/V0_n b_n b_n^T`` (:mod:`particle.nodal_volume`) couples every
    pair of its *star* (the particles of its tets). Attributes (the arrays of
    :func:`particle.nodal_kernels.add_nodal_volume_tangent`'s ``pattern``):

    * ``node_tet_ptr`` (N + 1,), ``node_tets`` (K,): each particle's tets, ascending (CSR);
    * ``node_tet_local`` (K, 4): the position of each of those tets' particles in the star;
    * ``star_ptr`` (N + 1,): the star sizes (CSR pointer; the stars are ascending ids);
    * ``block_ptr`` (N + 1,), ``block_slots`` (B, 3, 3): the data indices of the star's
      (i, j) blocks, row-major (i size + j), -1 where a fixed particle is involved.
    """
    node_tet_ptr: np.ndarray
    node_tets: np.ndarray
    node_tet_local: np.ndarray
    star_ptr: np.ndarray
    block_ptr: np.ndarray
    block_slots: np.ndarray

    @staticmethod
    def stars(tets: np.ndarray, n_particles: int) -> tuple:
        """(node_tet_ptr, node_tets, stars: a list of each particle's ascending star ids)."""
        owner = tets.ravel()
        order = np.argsort(owner, kind="stable")  # by particle, then tet (ascending)
        node_tets = (order // 4).astype(np.int64)
        ptr = np.zeros(n_particles + 1, dtype=np.int64)
        ptr[1:] = np.cumsum(np.bincount(owner, minlength=n_particles))
        return ptr, node_tets, [np.unique(tets[node_tets[ptr[m]:ptr[m + 1]]])
                                for m in range(n_particles)]

    @staticmethod
    def keys(stars: tuple, node_dof: np.ndarray, n: int) -> np.ndarray:
        """The CSC keys (column n + row) of every free entry of every star's blocks."""
        out = []
        for star in stars[2]:
            dof = node_dof[star]
            dof = dof[dof >= 0]
            rows = (dof[:, None] + np.arange(3)).ravel()
            out.append((rows[None, :] * n + rows[:, None]).ravel())
        return np.concatenate(out) if out else np.zeros(0, np.int64)

    @classmethod
    def of(cls, stars: tuple, tets: np.ndarray, node_dof: np.ndarray, unique: np.ndarray,
           n: int) -> "NodalPattern":
        """The pattern of ``stars`` (:meth:`stars`) in a CSC pattern of sorted ``unique`` keys
        (column n + row) on ``n`` dofs."""
        ptr, node_tets, star_list = stars
        sizes = np.array([len(s) for s in star_list], dtype=np.int64)
        star_ptr = np.r_[0, np.cumsum(sizes)].astype(np.int64)
        block_ptr = np.r_[0, np.cumsum(sizes ** 2)].astype(np.int64)
        local = np.empty((len(node_tets), 4), dtype=np.int64)
        slots = np.full((int(block_ptr[-1]), 3, 3), -1, dtype=np.int64)
        for m, star in enumerate(star_list):
            local[ptr[m]:ptr[m + 1]] = np.searchsorted(star, tets[node_tets[ptr[m]:ptr[m + 1]]])
            dof = node_dof[star]
            row = dof[:, None, None, None] + np.arange(3)[:, None]  # (s, 1, 3, 1)
            col = dof[None, :, None, None] + np.arange(3)[None, :]  # (1, s, 1, 3)
            row, col = np.broadcast_arrays(row, col)
            free = (row >= 0) & (col >= 0) & (dof[:, None, None, None] >= 0) & \
                (dof[None, :, None, None] >= 0)
            block = np.full(row.shape, -1, dtype=np.int64)
            block[free] = np.searchsorted(unique, col[free] * n + row[free])
            slots[block_ptr[m]:block_ptr[m + 1]] = block.reshape(-1, 3, 3)
        return cls(ptr, node_tets, local, star_ptr, block_ptr, slots)

    @property
    def arrays(self) -> tuple:
        """The kernels' ``pattern`` tuple."""
        return (self.node_tet_ptr, self.node_tets, self.node_tet_local, self.star_ptr,
                self.block_ptr, self.block_slots)


@dataclass
class VolumeArmStep:
    """One quasi-static step of the volume term's Maxwell arms: ``P = r P_prev + c (j -
    j_prev)`` in each tet's volume strain ``j = V/V0 - 1``.

    Attributes:
        r, c: (T, 2) float64, recursion coefficients [-], [Pa].
        pressure_prev: (T, 2) float64, arm pressures at the previous sample [Pa].
        strain_prev: (T,) float64, volume strains at the previous sample [1].
    """
    r: np.ndarray
    c: np.ndarray
    pressure_prev: np.ndarray
    strain_prev: np.ndarray

    @property
    def stiffness(self) -> np.ndarray:
        """(T,) float64, the arms' contribution c_1 + c_2 to the volume stiffness [Pa]."""
        return self.c.sum(axis=1)


@dataclass
class ArmStep:
    """One quasi-static step of the Maxwell arms: ``F = r F_prev + c (dx - dx_prev)``.

    Attributes:
        r, c: (E, 2) float64, recursion coefficients [-], [N/m].
        force_prev: (E, 2) float64, arm forces at the previous sample [N].
        dx_prev: (E,) float64, connector elongations at the previous sample [m].
        volume: the volume term's arms' step, or None (no volume arms).
    """
    r: np.ndarray
    c: np.ndarray
    force_prev: np.ndarray
    dx_prev: np.ndarray
    volume: VolumeArmStep | None = None

    @property
    def stiffness(self) -> np.ndarray:
        """(E,) float64, the arms' contribution c_1 + c_2 to the axial tangent [N/m]."""
        return self.c.sum(axis=1)


@dataclass
class Equilibrium:
    """A converged static state.

    Attributes:
        x: (N, 3) float64, positions [m].
        forces: (N, 3) float64, net internal (+ gravity) force on each particle [N];
            at a prescribed particle, minus the force the constraint applies.
        arm_force: (E, 2) float64, arm forces (zeros without arms) [N].
        dx: (E,) float64, connector elongations [m].
        iterations: Newton iterations used.
        volume_arm: (T, 2) float64, the volume arms' pressures [Pa] (zeros without an arm
            step), or None: the volume term has no arms.
        volume_strain: (T,) float64, the tets' volume strains [1] with ``volume_arm``.
        tension: (E,) float64, the connectors' tensions [N] (arm forces included) as the
            solver's last force evaluation left them (what the tangent at ``x`` is assembled
            from), or None (not computed: :meth:`at_rest`).
    """
    x: np.ndarray
    forces: np.ndarray
    arm_force: np.ndarray
    dx: np.ndarray
    iterations: int
    volume_arm: np.ndarray | None = None
    volume_strain: np.ndarray | None = None
    tension: np.ndarray | None = None

    @classmethod
    def at_rest(cls, model: Model) -> "Equilibrium":
        """The undeformed, unloaded state (arms unloaded, the volume arms' too)."""
        arms, rows = model.params.has_volume_arms, model.n_volume_elements
        return cls(model.rest_positions.copy(), np.zeros((model.n_particles, 3)),
                   np.zeros((model.n_connectors, 2)), np.zeros(model.n_connectors), 0,
                   np.zeros((rows, 2)) if arms else None,
                   np.zeros(rows) if arms else None)

    def reaction(self, nodes: int | np.ndarray) -> np.ndarray:
        """Force [N] the constraint applies to prescribed particle(s) ``nodes``: (3,) or (k, 3)."""
        return -self.forces[nodes]


class EquilibriumSolver:
    """Newton solver for one set of prescribed particles; keeps its LU between solves.

    Args:
        model: topology, masses and fixed particles (parameters come with each solve).
        prescribed: (k,) ids of particles whose positions are given.
        pattern: tangent pattern of ``model`` (shared between solvers of one model).
        rtol: converged when ``|residual|_2 <= rtol x`` the force scale (the largest
            of the constraint reaction, the total weight and the force of 0.1 %
            strain on an average connector).
        max_iter: Newton iterations per solve.
        refactor_ratio: refactorise when an iteration reduces the residual by less.
    """

    def __init__(self, model: Model, prescribed: np.ndarray, pattern: TangentPattern, *,
                 rtol: float = 1e-8, max_iter: int = 40, refactor_ratio: float = 0.25) -> None:
        self.model = model
        self.prescribed = model.check_nodes(prescribed, "prescribed particles")
        self.pattern = pattern
        self.rtol, self.max_iter, self.refactor_ratio = rtol, max_iter, refactor_ratio
        active = np.setdiff1d(model.free_nodes, self.prescribed)
        self._flat = flat_dofs(active)
        self._held_flat = flat_dofs(self.prescribed)
        self._mat = pattern.dofs(active)
        self._dofs = (self._flat, self._held_flat, self._mat)  # the compiled loop's
        self._zero_slots, self._diag_slots = pattern.constraint_slots(self.prescribed)
        tet_slots = (np.zeros((0, 4, 4, 3, 3), np.int64) if pattern.tet_slots is None
                     else pattern.tet_slots)
        self._tangent = (len(pattern.indices), pattern.slots, tet_slots, self._zero_slots,
                         self._diag_slots)
        self._no_volume_limit = (np.zeros(model.n_tets), np.full(model.n_tets, np.inf))
        rows = model.n_volume_elements  # the volume arms': per tet, or per particle (nodal)
        self._no_volume_arms = (np.zeros((rows, 2)), np.zeros(rows))
        # the nodal term's pattern and scratch (flag, pattern arrays, particles' volumes and
        # pressures), empty arrays of the same types for a per-tet model: one compiled loop
        nodal = pattern.nodal
        self._nodal = ((False, *_NO_NODAL_PATTERN, np.zeros(0), np.zeros(0)) if nodal is None
                       else (True, *nodal.arrays, np.empty(model.n_particles),
                             np.empty(model.n_particles)))
        self._volumes = np.empty(model.n_tets)
        self._read_only_inputs()
        self._mean_length = np.mean(model.rest_lengths)
        self._floor_of: tuple[ConnectorParams | None, float] = (None, 0.0)  # force scale floor
        self._coefficients_of: tuple = (None,)  # (parameters, their volume coefficients)
        self._lu = None
        self._stale = True  # refactorise before the next step
        self.factorizations = 0
        # the lumped masses on the tangent's dofs (the damping of settle's overdamped motion)
        self._mass_diagonal = np.zeros(pattern.n_dofs)
        self._mass_diagonal[self._mat] = np.repeat(model.masses[active], 3)

    def _read_only_inputs(self) -> None:
        """The compiled loop's read-only inputs that are not the model's or the parameters'
        arrays, typed as those are (read-only, so numba compiles one specialisation for
        every solver)."""
        # what the compiled loop gets (unread) without kv, typed as the parameters' kv
        self._no_kv = np.zeros(self.model.n_tets)
        self._no_kv.flags.writeable = False
        # the force pass typed as the explicit runs call it (statics_kernels.evaluate)
        self._force_tets = kernels.index_view(self.model.tets)

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_lu"], state["_stale"] = None, True  # factorisations are not shipped
        state["_floor_of"] = (None, 0.0)
        state["_coefficients_of"] = (None,)  # read-only arrays pickle would ship writable
        del state["_no_kv"], state["_force_tets"]  # pickle would ship them writable
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._read_only_inputs()  # a view of the unpickled (read-only again) model's tets

    @property
    def factorization(self):
        """The factorisation the next step will use (a :class:`particle.sparse_ldl.Factor`, or
        None); callers solving a sequence of similar problems hand back the one that
        served a similar problem before (see the evaluators)."""
        return self._lu

    @factorization.setter
    def factorization(self, lu) -> None:
        self._lu = lu
        self._stale = lu is None

    def _evaluate(self, x: np.ndarray, p: ConnectorParams, nonlinear: bool,
                  arms: ArmStep | None, gravity: np.ndarray | None) -> _Iterate:
        forces, tension, arm_out, dx, volume = net_forces(self.model, x, p, nonlinear, arms,
                                                          gravity, self._no_volume_limit)
        return _Iterate(x, forces, tension, arm_out, dx, forces.ravel()[self._flat], volume)

    def _factorize(self, x: np.ndarray, tension: np.ndarray, volume_arm: np.ndarray | None,
                   p: ConnectorParams, nonlinear: bool, arms: ArmStep | None) -> None:
        """Factorise the constrained tangent at positions ``x`` (tension (E,), the volume
        arms' pressures (T, 2) with a volume arm step) and keep it."""
        data = tangent_data(self.model, self.pattern, x, tension, p, nonlinear, arms,
                            volume_arm)
        data[self._zero_slots] = 0.0
        data[self._diag_slots] = 1.0
        self.factorization = factorize(self.pattern, data, self.prescribed)
        self.factorizations += 1

    def _moved(self, it: _Iterate, step: np.ndarray, *args) -> _Iterate:
        return self._evaluate(displaced(it.x, self._flat, step), *args)

    def solve(self, x: np.ndarray, params: ConnectorParams, *, arms: ArmStep | None = None,
              gravity: np.ndarray | None = None) -> Equilibrium:
        """Equilibrium from the guess ``x`` (N, 3) (prescribed particles already at their targets).

        Modified Newton: steps ``LU^{-1} residual`` with the kept factorisation;
        a step that does not lower the residual triggers a refactorisation at
        the current iterate, a fresh factorisation's step is backtracked (line
        search). Raises :class:`ConvergenceError` if the residual cannot be
        brought below the tolerance in ``max_iter`` iterations.
        """
        nonlinear = not params.is_linear
        floor = self._force_floor(params, gravity)
        buffers, springs, volume, loads = self._workspace(x, params, nonlinear, arms, gravity)
        settings = (float(self.rtol), floor, int(self.max_iter), float(self.refactor_ratio))
        symbolic = self.pattern.ldl
        kept = self._lu
        if kept is not None and (kept.symbolic is not symbolic and not (
                np.array_equal(kept.symbolic.perm, symbolic.perm)
                and np.array_equal(kept.symbolic.x_ptr, symbolic.x_ptr))):
            # a factorisation handed over from another pattern: the compiled loop solves
            # with this pattern's analysis, so factorise afresh here
            self.factorization = None
        state = (0, 0, False, self._stale, True, False, 0.0)
        while True:
            lu = (_NO_FACTOR, _NO_FACTOR) if self._lu is None else (self._lu.x, self._lu.d)
            status, cur, it, _, stale, norm, lx, ld, factorisations = newton_iterations(
                *state, *buffers, *springs, *volume, *loads, *self._dofs, *self._tangent,
                *self._nodal,
                *self._symbolic(symbolic), *lu, *settings)
            if factorisations:
                self.factorization = sparse_ldl.Factor(symbolic, lx, ld)
                self.factorizations += factorisations
            self._stale = stale
            if status != FACTORISE:
                break
            # a zero pivot: factorise here, with the singular fallback, and go on
            self._factorize(buffers[0][cur], buffers[2][cur],
                            buffers[5][cur] if volume[1] else None, params, nonlinear, arms)
            state = (cur, it, True, False, False, True, norm)
        if status == CONVERGED:
            xs, forces, tension, arm_force, dx, vol_p, vol_s, _ = buffers
            return Equilibrium(xs[cur].copy(), forces[cur].copy(), arm_force[cur].copy(),
                               dx[cur].copy(), it,
                               *volume_state(self.model, xs[cur], (vol_p[cur].copy(),
                                                                   vol_s[cur].copy())
                                             if volume[1] else None), tension[cur].copy())
        raise ConvergenceError(f"Newton did not converge for prescribed particles "
                               f"{self.prescribed.tolist()}: residual {norm:.3g} N after {it} "
                               f"iterations (tolerance {self.rtol:g} x force scale)")

    @staticmethod
    def _symbolic(s: sparse_ldl.Symbolic) -> tuple:
        """The arrays of the pattern's symbolic analysis the compiled loop factorises with."""
        return (s.sup_ptr, s.row_ptr, s.rows, s.x_ptr, s.upd_ptr, s.upd_sup, s.upd_q1,
                s.upd_q2, s.a_src, s.a_dst, s.perm)

    def _workspace(self, x: np.ndarray, p: ConnectorParams, nonlinear: bool,
                   arms: ArmStep | None, gravity: np.ndarray | None) -> tuple:
        """``(buffers, springs, volume, loads)`` of :func:`particle.statics_kernels.evaluate`
        for a solve from ``x`` (N, 3): two iterates' buffers, the first at ``x``; every
        optional term an array (zeros where it is off), so that one specialisation of the
        compiled loop serves every combination."""
        model = self.model
        n, e, t = model.n_particles, model.n_connectors, model.n_volume_elements
        xs = np.empty((2, n, 3))
        xs[0] = x
        buffers = (xs, np.empty((2, n, 3)), np.empty((2, e)), np.empty((2, e, 2)),
                   np.empty((2, e)), np.empty((2, t, 2)), np.empty((2, t)),
                   np.empty((2, len(self._flat))))
        springs = (model.edges, model.rest_lengths, p.K0) + kernel_terms(p, nonlinear, arms)
        step = volume_step(model, p, arms)
        pressures, strains = self._no_volume_arms
        r = c = pressures
        if step is not None:
            r, c, pressures, strains = step.r, step.c, step.pressure_prev, step.strain_prev
        rest, kv = self._volume_coefficients(p)
        volume = (p.kv is not None, step is not None, model.tets, rest, kv,
                  *self._no_volume_limit, r, c, pressures, strains, self._force_tets,
                  self._volumes)
        loads = ((True, model.masses, np.array(gravity, dtype=np.float64))
                 if gravity is not None else (False, model.masses, _NO_GRAVITY))
        return buffers, springs, volume, loads

    def settle(self, x: np.ndarray, params: ConnectorParams, *, arms: ArmStep | None = None,
               gravity: np.ndarray | None = None) -> Equilibrium:
        """The stable equilibrium an overdamped motion from ``x`` (N, 3) comes to rest in
        (prescribed particles already at their targets); arguments as :meth:`solve`.

        What a physical load step does where the equilibrium :meth:`solve` follows has ended
        (module docstring): implicit Euler steps of the overdamped motion ``c M dx/dt =
        f(x)`` (lumped masses ``M``, damping proportional to them, as ``particle.damping``), a
        step of ``h`` being ``(K + mu M) dx = f`` with ``mu = c / h``: with ``mu`` large a
        short step downhill, with ``mu = 0`` Newton's. ``mu`` starts at the median ``K_ii /
        m_i`` of the free dofs (the
        squared natural frequency of a typical particle), is multiplied by 4 while ``K + mu
        M`` is not positive definite (a pivot of its ``L D L^T`` <= 0: the step would not go
        downhill), a step moves some particle by more than a quarter of the mean connector
        length (the tangent would not describe it) or reaches a state of non-finite forces
        (an inverted tet), and divided by 4 after every accepted step, so the iteration ends
        as Newton's at a minimum. Converged as :meth:`solve`; :class:`ConvergenceError`
        after ``SETTLE_ITERATIONS`` steps.
        """
        args = (params, not params.is_linear, arms, gravity)
        floor = self._force_floor(params, gravity)
        cur = self._evaluate(np.array(x, dtype=np.float64, order="C"), *args)
        step_cap = 0.25 * self._mean_length
        mu = None
        for it in range(SETTLE_ITERATIONS + 1):
            if self._converged(cur, floor):
                self.factorization = None  # the next solve factorises where it starts
                log.debug("prescribed particles %s: settled in %d steps", self.prescribed.tolist(),
                          it)
                return self._equilibrium(cur, it)
            if it == SETTLE_ITERATIONS:
                break
            data = tangent_data(self.model, self.pattern, cur.x, cur.tension, *args[:3],
                                cur.volume_arm)
            data[self._zero_slots] = 0.0
            data[self._diag_slots] = 1.0
            if mu is None:
                free = self._mass_diagonal > 0.0
                mu = float(np.median(data[self.pattern.diagonal][free]
                                     / self._mass_diagonal[free]))
            for _ in range(SETTLE_SHIFTS):
                shifted = data.copy()
                shifted[self.pattern.diagonal] += mu * self._mass_diagonal
                try:
                    lu = ldl_factor(self.pattern, shifted)
                    downhill = bool(np.all(lu.d > 0.0))
                except RuntimeError:  # a zero pivot: not positive definite either
                    downhill = False
                self.factorizations += 1
                if downhill:
                    step = lu.solve_restricted(self._mat, cur.res)
                    moves = np.sqrt(np.sum(step.reshape(-1, 3) ** 2, axis=1))
                    if moves.max() <= step_cap:
                        trial = self._moved(cur, step, *args)
                        if math.isfinite(trial.norm):
                            break
                mu *= 4.0
            else:
                break
            cur, mu = trial, 0.25 * mu
        raise ConvergenceError(f"no equilibrium reached by settling from the last one for "
                               f"prescribed particles {self.prescribed.tolist()}: residual "
                               f"{cur.norm:.3g} N after {it} damped steps (tolerance "
                               f"{self.rtol:g} x force scale)")

    def _volume_coefficients(self, p: ConnectorParams) -> tuple[np.ndarray, np.ndarray]:
        """(rest volumes, kv) of the volume elements with parameters ``p``
        (:func:`~particle.nodal_volume.element_coefficients`; placeholders without kv), kept
        for the last ``p``: the same parameters serve a whole curve, and the nodal term's
        averages cost passes over the tets."""
        if p.kv is None:
            return self.model.rest_volumes, self._no_kv
        if self._coefficients_of[0] is not p:
            self._coefficients_of = (p, *element_coefficients(self.model, p))
        return self._coefficients_of[1], self._coefficients_of[2]

    def _force_floor(self, params: ConnectorParams, gravity: np.ndarray | None) -> float:
        """The smallest force scale [N] a residual is measured against: the force of 0.1 %
        strain on a mean connector, or the total weight."""
        if self._floor_of[0] is not params:  # the same parameters for a whole curve
            self._floor_of = (params, 1e-3 * float(np.mean(params.K0) * self._mean_length))
        if gravity is None:
            return self._floor_of[1]
        return max(self._floor_of[1], float(np.linalg.norm(gravity) * self.model.masses.sum()))

    def _converged(self, cur: "_Iterate", floor: float) -> bool:
        """The residual within ``rtol`` x the force scale (the constraint reaction, at least
        ``floor``): the compiled loop's test (:func:`particle.statics_kernels.converged`)."""
        return converged(cur.forces, self._held_flat, np.empty(len(self._held_flat)), cur.norm,
                         self.rtol, floor)

    def _equilibrium(self, cur: "_Iterate", iterations: int) -> Equilibrium:
        return Equilibrium(cur.x, cur.forces, cur.arm_force, cur.dx, iterations,
                           *cur.volume_state(self.model), cur.tension)


def flat_dofs(nodes: np.ndarray) -> np.ndarray:
    """(3k,) int64 indices of particles ``nodes``' (k,) components in a raveled (N, 3) array."""
    return (3 * np.asarray(nodes, dtype=np.int64)[:, None] + np.arange(3)).ravel()


@njit(**JIT)
def displaced(x, flat, step):
    """A copy of positions ``x`` (N, 3) [m] with ``step`` (k,) [m] added to its raveled
    components ``flat`` (k,) (distinct): a Newton trial point in one compiled call."""
    out = x.copy()
    moved = out.reshape(-1)
    for t in range(len(flat)):
        moved[flat[t]] += step[t]
    return out


def kernel_terms(p: ConnectorParams, nonlinear: bool, arms: ArmStep | None
                 ) -> tuple[np.ndarray, ...]:
    """``(a, b, arm_r, arm_c, arm_prev, dx_prev)`` for the force and tangent kernels, every
    one an array: zeros for linear springs (``nonlinear`` False) and without an arm step.

    Why arrays where the explicit loop passes None: numba compiles one specialisation
    per None/array combination, and the Newton path meets four (linear or not, arms or
    not), each compiled in every fresh process of a calibration (1.5 s of compilation
    in each worker); a zero term adds exactly 0.0 to a tension or tangent, and its few
    flops per connector are lost next to the sparse factorisation.
    """
    a, b = spring_terms(p, nonlinear)
    if arms is None:
        e = len(p.K0)
        zero = np.zeros((e, 2))
        return a, b, zero, zero, zero, np.zeros(e)
    return a, b, arms.r, arms.c, arms.force_prev, arms.dx_prev


def spring_terms(p: ConnectorParams, nonlinear: bool) -> tuple[np.ndarray, np.ndarray]:
    """``(a, b)`` of :func:`kernel_terms`: the springs' coefficients, or read-only zeros."""
    if nonlinear:
        return p.a, p.b
    zero = np.zeros(len(p.K0))
    zero.flags.writeable = False  # typed as the parameters' read-only arrays are
    return zero, zero


def net_forces(model: Model, x: np.ndarray, p: ConnectorParams, nonlinear: bool,
               arms: ArmStep | None, gravity: np.ndarray | None,
               volume_limits: tuple[np.ndarray, np.ndarray]) -> tuple:
    """(forces (N, 3) [N], tension (E,) [N], arm forces (E, 2) [N], elongations (E,) [m],
    volume arms) at positions ``x``: connectors (an arm step if ``arms``), the volume term
    with ``p.kv`` (no volume outside ``volume_limits`` (lo (T,), hi (T,)) [m^3]; its arms
    stepped by ``arms.volume``, else relaxed) and gravity ``m g``. The volume arms are
    (pressures (T, 2) [Pa], volume strains (T,)) after the step, or None without one."""
    n, e = model.n_particles, model.n_connectors
    forces, tension, arm_out, dx = (np.empty((n, 3)), np.empty(e), np.zeros((e, 2)),
                                    np.empty(e))
    kernels.internal_forces(x, model.edges, model.rest_lengths, p.K0,
                            *kernel_terms(p, nonlinear, arms), forces, tension, arm_out, dx)
    volume = None
    if p.kv is not None:
        step = volume_step(model, p, arms)
        kernel_arms = None
        if step is not None:
            rows = model.n_volume_elements
            volume = (np.zeros((rows, 2)), np.empty(rows))
            kernel_arms = (step.r, step.c, step.pressure_prev, step.strain_prev)
        # typed as the explicit runs call the force pass (unsigned tets, volumes stored):
        # one compiled pass for both (another typing costs ~4 s of compilation)
        if model.volume_element == "nodal":
            rest, kv = element_coefficients(model, p)
            bad, _ = add_nodal_volume_forces(
                x, kernels.index_view(model.tets), rest, kv, volume_limits[0],
                volume_limits[1], forces, None if step is None else kernel_arms + volume,
                np.empty(model.n_tets), (np.empty(model.n_particles),
                                         np.empty(model.n_particles)))
        else:
            bad, _ = add_volume_forces_grouped(
                x, kernels.index_view(model.tets), model.rest_volumes, p.kv, volume_limits[0],
                volume_limits[1], forces, kernel_arms, volume, np.empty(model.n_tets))
        if bad >= 0:
            # an inverted tet is no admissible iterate: an infinite residual makes the
            # line search shorten the step (and a converged state is never inverted)
            forces[:] = np.inf
    if gravity is not None:
        forces += model.masses[:, None] * gravity
    return forces, tension, arm_out, dx, volume


def volume_step(model: Model, p: ConnectorParams, arms: ArmStep | None) -> VolumeArmStep | None:
    """The volume arms' step of ``arms`` (None without the volume term, an arm step or
    volume arms); :class:`ParameterError` if a model with volume arms gets an arm step
    without theirs, or theirs does not have one row per tet."""
    if p.kv is None or arms is None:
        return None
    step = arms.volume
    if step is None:
        if p.has_volume_arms:
            raise ParameterError("an arm step of a model whose volume term has arms needs "
                                 "their step too (ArmStep.volume)")
        return None
    rows = model.n_volume_elements
    if not (step.r.shape == step.c.shape == step.pressure_prev.shape
            == (rows, 2) and step.strain_prev.shape == (rows,)):
        what = "particles (the nodal term" if model.volume_element == "nodal" else "tets ("
        raise ParameterError(f"volume arm step of shapes r {step.r.shape}, c "
                             f"{step.c.shape}, pressures {step.pressure_prev.shape}, "
                             f"strains {step.strain_prev.shape}: the model has "
                             f"{rows} {what}: one row each)")
    return step


def tangent_data(model: Model, pat: TangentPattern, x: np.ndarray, tension: np.ndarray,
                 p: ConnectorParams, nonlinear: bool, arms: ArmStep | None,
                 volume_arm: np.ndarray | None = None) -> np.ndarray:
    """CSC data (nnz,) of the tangent stiffness [N/m] at ``x`` in ``pat``'s storage
    (constraint rows and columns not yet applied); ``volume_arm`` (T, 2) [Pa]: the volume
    arms' pressures at ``x`` after the step ``arms.volume`` (needed with that step)."""
    data = np.empty(len(pat.indices))
    a, b = spring_terms(p, nonlinear)
    arm_stiffness = np.zeros(len(p.K0)) if arms is None else arms.stiffness
    kernels.assemble_tangent(x, model.edges, model.rest_lengths, p.K0, a, b, arm_stiffness,
                             tension, pat.slots, data)
    if p.kv is not None:
        step = None if arms is None else arms.volume
        volume_arms = None if step is None else (step.stiffness, volume_arm.sum(axis=1))
        if model.volume_element == "nodal":
            add_nodal_volume_tangent(x, model.tets, *element_coefficients(model, p),
                                     pat.nodal.arrays, pat.tet_slots, data, volume_arms,
                                     (np.empty(model.n_particles), np.empty(model.n_particles)))
        else:
            add_volume_tangent(x, model.tets, model.rest_volumes, p.kv, pat.tet_slots, data,
                               volume_arms)
    return data


def factorize(pat: TangentPattern, data: np.ndarray, prescribed: np.ndarray):
    """Factorisation (:func:`ldl_factor`) of the tangent ``data`` in ``pat``'s storage (modified
    in place if it has to be shifted); :class:`ConvergenceError` if it is singular."""
    try:
        return ldl_factor(pat, data)
    except RuntimeError:
        # exactly singular, e.g. a hanging string at rest has no transverse stiffness yet:
        # a tiny diagonal shift only changes the iteration matrix, not the equilibrium
        shift = 1e-6 * np.abs(data[pat.diagonal]).max()
        log.debug("prescribed particles %s: tangent stiffness exactly singular; factorising "
                  "it with its diagonal shifted by %.3g N/m (changes the Newton iteration, "
                  "not the equilibrium it converges to)", prescribed.tolist(), shift)
        data[pat.diagonal] += shift
        try:
            return ldl_factor(pat, data)
        except RuntimeError as exc:
            raise ConvergenceError(f"tangent stiffness is singular ({exc}); is the model "
                                   "held by fixed or prescribed particles?") from exc


def ldl_factor(pat: TangentPattern, data: np.ndarray) -> sparse_ldl.Factor:
    """``L D L^T`` factorisation of the symmetric matrix ``data`` in ``pat``'s CSC storage.

    The same algorithm as :func:`superlu` (symmetric minimum-degree ordering, no
    pivoting), with the ordering and the symbolic analysis done once per
    pattern; ``.solve`` takes (n,) or (n, r) right-hand sides like SuperLU's.
    :class:`RuntimeError` on a zero pivot (an exactly singular matrix).
    """
    return sparse_ldl.factorize(pat.ldl, data)


def superlu(pat: TangentPattern, data: np.ndarray):
    """SuperLU factorisation of the symmetric matrix ``data`` in ``pat``'s CSC storage (the
    reference for :func:`ldl_factor`, :func:`particle.sparse_ldl.superlu`)."""
    return sparse_ldl.superlu(pat.indptr, pat.indices, data)


class _Iterate:
    """One Newton iterate: positions and everything the force kernel returned for them."""
    __slots__ = ("x", "forces", "tension", "arm_force", "dx", "res", "norm", "volume_arm",
                 "volume_strain")

    def __init__(self, x, forces, tension, arm_force, dx, res, volume=None):
        self.x, self.forces, self.tension = x, forces, tension
        self.arm_force, self.dx, self.res = arm_force, dx, res
        self.volume_arm, self.volume_strain = (None, None) if volume is None else volume
        self.norm = math.sqrt(res @ res)

    def volume_state(self, model: Model) -> tuple[np.ndarray | None, np.ndarray | None]:
        """:func:`volume_state` of this iterate."""
        return volume_state(model, self.x, None if self.volume_arm is None
                            else (self.volume_arm, self.volume_strain))


def volume_state(model: Model, x: np.ndarray, volume: tuple[np.ndarray, np.ndarray] | None
                 ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(volume arm pressures (T, 2), volume strains (T,)) of an :class:`Equilibrium` at ``x``
    (N, 3): the arm step's ``volume``, zeros when the arms are relaxed (no arm step), None
    without arms."""
    if volume is not None:
        return volume
    if not model.params.has_volume_arms:
        return None, None
    return np.zeros((model.n_volume_elements, 2)), element_strains(model, x)


@contextlib.contextmanager
def reaching(last: Callable[[], float]) -> Iterator[None]:
    """Inside the block, an error of the model (Newton, a spring's stiffness, an inverted
    tet) that does not say how far it got records ``last()`` in ``reached``: the load
    parameter of the last state reached (depth [m], time [s] or load fraction [1])."""
    try:
        yield
    except (ConvergenceError, ParameterError, StabilityError) as exc:
        if exc.reached is None:
            exc.reached = float(last())
        raise


def continuation(step: Callable[[T, float, float], T], start: T, s0: float, s1: float, *,
                 max_cuts: int = 6, what: str = "load step",
                 settle: Callable[[T, float, float], T] | None = None) -> T:
    """Advance ``start`` from load parameter ``s0`` to ``s1`` with ``step(state, s_from, s_to)``.

    If a step raises :class:`ConvergenceError` it is split in two halves,
    recursively, at most ``max_cuts`` times deep. Where the shortest step still fails,
    ``settle(state, s_from, s_to)`` (if given; :meth:`EquilibriumSolver.settle`) takes it:
    the path has reached a fold and the model moves on to the state it snaps to. The error
    of a step that still fails records in ``reached`` the load parameter it started from: the
    furthest one reached.
    """
    try:
        return step(start, s0, s1)
    except ConvergenceError as exc:
        if max_cuts <= 0:
            if settle is not None:
                try:
                    state = settle(start, s0, s1)
                    log.debug("%s %g -> %g: no nearby equilibrium (a fold); settled on the "
                              "one the model snaps to", what, s0, s1)
                    return state
                except ConvergenceError as unsettled:
                    exc = unsettled
            error = ConvergenceError(f"{what} {s0:g} -> {s1:g} failed after repeated halving"
                                     f"{' and settling' if settle is not None else ''}: {exc}")
            error.reached = s0
            raise error from None
    mid = 0.5 * (s0 + s1)
    log.debug("%s %g -> %g cut at %g", what, s0, s1, mid)
    half = continuation(step, start, s0, mid, max_cuts=max_cuts - 1, what=what, settle=settle)
    return continuation(step, half, mid, s1, max_cuts=max_cuts - 1, what=what, settle=settle)


def gravity_static(model: Model, gravity: np.ndarray, *, load_steps: int = 4,
                   rtol: float = 1e-10,
                   strain_range: tuple[float, float] = (-0.5, 0.5)) -> np.ndarray:
    """(N, 3) static sag under gravity [m] (long-term springs only, arms relaxed).

    Newton equilibrium with ``gravity`` [m/s^2] applied in ``load_steps`` equal
    increments (each halved on failure, :func:`weight_equilibrium`). The parameters are
    validated on ``strain_range`` and the springs' K(eps) checked at the strains reached. An
    error of the model (parameters, Newton, the final check) records in ``reached`` the
    fraction of the load it had carried.
    """
    x = weight_equilibrium(model, gravity, load_steps, rtol=rtol, strain_range=strain_range)
    with reaching(lambda: 1.0):
        d = x[model.edges[:, 1]] - x[model.edges[:, 0]]
        check_stiffness(model, np.linalg.norm(d, axis=1) / model.rest_lengths - 1.0,
                        "gravity_static")
        if model.has_volume:
            check_volumes(model, x, "gravity_static")
    return x - model.rest_positions


def weight_equilibrium(model: Model, gravity: np.ndarray, load_steps: int, *,
                       rtol: float = 1e-10,
                       strain_range: tuple[float, float] | None = None) -> np.ndarray:
    """(N, 3) positions [m] of the static equilibrium under the weight ``m gravity``
    [m/s^2] (long-term model, arms relaxed), the load applied in ``load_steps`` equal
    increments, each halved on failure (:func:`continuation`). With ``strain_range`` the
    parameters are validated on it first. An error of the model records in ``reached`` the
    fraction of the load it had carried.

    Raises:
        ParameterError: no gravity vector, no load step or no fixed particle.
        ConvergenceError: no equilibrium is found (the model does not carry the load).
    """
    g = check_gravity(gravity)
    if g is None:
        raise ParameterError("a static weight needs a gravity vector (3 components in m/s^2)")
    if load_steps < 1:
        raise ParameterError(f"load_steps = {load_steps} must be >= 1")
    if not len(model.free_nodes) < model.n_particles:
        raise ParameterError("a static weight needs fixed particles: a free body under "
                             "gravity has no static equilibrium")
    carried = 0.0
    with reaching(lambda: carried):
        if strain_range is not None:
            model.params.validate(strain_range, model.edges, model.tets)
        solver = EquilibriumSolver(model, np.zeros(0, np.int64), TangentPattern.of(model),
                                   rtol=rtol, refactor_ratio=0.1)

        def step(x: np.ndarray, _: float, s1: float) -> np.ndarray:
            return solver.solve(x, model.params, gravity=s1 * g).x

        x = model.rest_positions.copy()
        for k in range(load_steps):
            x = continuation(step, x, k / load_steps, (k + 1) / load_steps, what="gravity load")
            carried = (k + 1) / load_steps
    return x


def check_stiffness(model: Model, strain: np.ndarray, what: str) -> None:
    """Raise :class:`ParameterError` if a spring's K(eps) <= 0 at the connector strains (E,)."""
    bad = np.nonzero(model.params.stiffness(strain) <= 0.0)[0]
    if len(bad):
        e = int(bad[0])
        raise ParameterError(f"{what}: {connector_name(e, model.edges)} reaches strain "
                             f"{strain[e]:.3g} where its stiffness K(eps) <= 0")


def check_volumes(model: Model, x: np.ndarray, what: str) -> None:
    """Raise :class:`~forcecal.errors.StabilityError` naming the first tet inverted (V <= 0) at ``x``."""
    bad = np.nonzero(~(signed_volumes(x, model.tets) > 0.0))[0]
    if len(bad):
        t = int(bad[0])
        raise StabilityError(f"{what}: {tet_name(t, model.tets)} is inverted (volume <= 0)")
