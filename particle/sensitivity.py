"""Exact sensitivities of the calibration curves to every per-connector parameter (adjoint method).

:class:`IndentationSensitivity` and :class:`RelaxationSensitivity` are the
evaluators of :mod:`particle.evaluators` (same curves, same caches, same
refusals) with one more method, :meth:`~_Adjoint.jacobian`: the curves of some
test points together with their derivatives with respect to every connector's
``K0, a, b, k1, b1, k2, b2`` (:data:`~particle.params.PARAM_NAMES`), through the
equilibria the curves are made of.

Method (reverse mode through the quasi-static path; all equilibria are the
ones the evaluator just solved, nothing is re-solved):

* each (sub)step s of a curve is an equilibrium ``f_a(x^s, T^s) = 0`` of the
  active particles, with connector tensions ``T^s = K(eps) dx + sum_i A_i^s``
  and the arm forces ``A_i^s = r_i A_i^(s-1) + c_i (dx^s - dx^(s-1))``
  (:meth:`ConnectorParams.arm_recursion`, exact form); the output of a sample is
  ``F = -n . sum_h f_h`` over the particles the indenter holds (the normal indenter
  force: the test particle alone, or a flat punch's footprint), or with ``directions``
  the force's component along each of them (``n`` replaced by each direction ``d``: D
  outputs per sample, direction-major);
* one adjoint solve per step with the exact tangent ``K = -df/dx`` at the
  equilibrium (refactorised there; one right-hand side per output sample that
  depends on the step: the one ending there and, through the arms' history,
  those ending later; the others' adjoints are zero):
  ``K_aa lam = w K_aP n - sum_e beta_e g_e`` with ``g_e`` the force pattern of a
  unit tension of connector e (``+u_e`` on i, ``-u_e`` on j) and ``beta_e`` the
  adjoint of its elongation carried back from later steps; the virtual field
  ``omega`` (``lam`` on the active dofs, ``-w n`` on each held particle)
  gives the adjoint of each tension ``tau_e = omega . g_e``;
* then ``dF/dp_e += tau_e dT_e/dp_e`` for the spring (``dx, eps dx, eps^2 dx``),
  ``mu_i = abar_i + tau_e`` times ``dA_i/dk_i, dA_i/db_i`` for the arms, and the
  history adjoints step back: ``abar_i <- r_i mu_i``,
  ``dbar <- -sum_i c_i mu_i``.

An indentation sample is elastic (no history): one step per sample. Relaxation
sub-steps are the path the evaluator actually took, halved intervals
included (recorded by :class:`_RecordingSolver`), so the derivatives are those
of the curves returned, to round-off (tests compare with finite differences).

The volume term's ``kv`` (:mod:`particle.volume`) enters the same way: its
tangent is in ``K``, and ``dF/dkv_t = omega . df/dkv_t`` with ``df/dkv_t =
-(V/V0 - 1) dV/dx`` at fixed positions. A tet is a connector whose "tension" is its
pressure ``P_t`` and whose "elongation" its volume change: the force pattern of a unit
pressure is ``h_t = -dV/dx``, so ``pi_t = omega . h_t`` is the adjoint of the pressure
(``dF/dkv_t = pi_t j_t``, ``j = V/V0 - 1``). Its Maxwell arms (a viscoelastic volume
term) carry history exactly as the connectors' arms do, in the volume strain: ``mu_i =
pbar_i + pi_t`` times ``dP_i/dkv_i, dP_i/dbv_i``, then ``pbar_i <- r_i mu_i``, ``jbar <-
-sum_i c_i mu_i``, and the history enters the next (earlier) step's right-hand side as
the forces of the pressures ``gamma/V0``, ``gamma = jbar + sum_i c_i pbar_i``
(:class:`_VolumeAdjoint`). The nodal term (:mod:`particle.nodal_volume`) is this with the
particles as the volume elements: a particle's pressure pushes each of its tets with a
quarter, its coefficients are linear means of the per-tet ones, and the derivatives are
mapped back to those (:class:`NodalElements`). Another term plugs in likewise: its tangent
in the assembly, its force derivative contracted with ``omega`` (a kernel here, its twin in
numpy).

The pass runs on the compiled kernels of :mod:`particle.sensitivity_kernels`
(``G beta`` and ``G^T omega`` straight from the connectors' unit vectors and end
dofs, the partials and the history update in one sweep); its plain numpy/scipy
twin (:func:`point_jacobian_numpy`, every sample at every step, ``G`` a
scipy matrix) is the reference the tests compare it with (round-off).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.sparse as sp

from forcecal.errors import ParameterError
from particle import sensitivity_kernels as kern
from particle.evaluators import (IndentationEvaluator, RelaxationEvaluator, force_components,
                                 normal_force)
from particle.model import Model
from particle.params import PARAM_NAMES, ConnectorParams, same_values
from particle.statics import (ArmStep, Equilibrium, EquilibriumSolver, VolumeArmStep,
                              ldl_factor, tangent_data)
from particle.nodal_volume import element_strains, is_nodal, node_average
from particle.volume import signed_volumes, volume_gradients_numpy

log = logging.getLogger(__name__)

N_PARAMS = len(PARAM_NAMES)


@dataclass(frozen=True, eq=False)
class Sensitivities:
    """Curves of some test points and their exact derivatives.

    Attributes:
        forces: (P', S) normal forces [N], exactly what the evaluator's ``__call__`` returns.
        connectors: (P', S, 7, E) derivatives [N per unit of each parameter] with respect to
            ``K0, a, b, k1, b1, k2, b2`` of every connector (PARAM_NAMES order).
        kv: (P', S, T) derivatives [N/Pa] with respect to each tet's ``kv``, or None when
            the volume term is off.
        volume_arms: (P', S, 4, T) derivatives [N/Pa, N/(Pa s)] with respect to each tet's
            volume arm ``kv1, bv1, kv2, bv2`` (:data:`~particle.params.VOLUME_ARM_NAMES`), or
            None when the volume term has no arms.
    """
    forces: np.ndarray
    connectors: np.ndarray
    kv: np.ndarray | None
    volume_arms: np.ndarray | None = None


class _RecordingSolver(EquilibriumSolver):
    """An :class:`EquilibriumSolver` that remembers every successful solve (its arms and result)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.path: list[tuple[ArmStep | None, Equilibrium]] = []

    def __getstate__(self) -> dict:
        state = super().__getstate__()
        state["path"] = []
        return state

    def solve(self, x, params, *, arms=None, gravity=None):
        eq = super().solve(x, params, arms=arms, gravity=gravity)
        self.path.append((arms, eq))
        return eq

    def settle(self, x, params, *, arms=None, gravity=None):
        eq = super().settle(x, params, arms=arms, gravity=gravity)
        self.path.append((arms, eq))
        return eq


def volume_partials_numpy(model: Model, x: np.ndarray, pat, omega: np.ndarray) -> np.ndarray:
    """(S, T): ``omega . df/dkv_t`` with ``df/dkv_t = -(V/V0 - 1) dV/dx`` at fixed x
    (``omega`` (n_dofs, S) adjoints in the tangent pattern ``pat``'s dofs); the numpy twin
    of :func:`particle.sensitivity_kernels.add_volume_partials`."""
    strain = signed_volumes(x, model.tets) / model.rest_volumes - 1.0
    grad = volume_gradients_numpy(x, model.tets)  # (T, 4, 3)
    virtual = np.zeros((model.n_particles, 3, omega.shape[1]))
    moving = pat.node_dof >= 0
    virtual[moving] = omega[pat.node_dof[moving][:, None] + np.arange(3)]
    return -np.einsum("t,tac,tacs->st", strain, grad, virtual[model.tets])


class NodalElements:
    """The nodal volume term's particles as the adjoint pass's volume elements
    (:mod:`particle.nodal_volume`). A particle's pressure pushes its tets with a quarter each
    (``dV_n/dx = sum_{t ∋ n} dV_t/dx / 4``), so the adjoint of its pressure is ``pi_n = sum_{t
    ∋ n} pi_t / 4`` (:attr:`quarter` applied to the tets' ``pi_t``), and the forces of
    pressures ``gamma_n / V0_n`` on the particles are those of ``sum_{n ∈ t} gamma_n / (4
    V0_n)`` on each tet. Its coefficients are linear in the per-tet ones (``kv_n = sum_{t ∋
    n} kv_t V0_t / 4 / V0_n``, likewise ``kv_i``, ``bv_i``: :attr:`average`), so a
    derivative with respect to the per-tet parameters is the particles' times
    :attr:`average` (:meth:`to_tets`)."""

    def __init__(self, model: Model):
        tets, n, t = model.tets, model.n_particles, model.n_tets
        rows, cols = tets.ravel(), np.repeat(np.arange(t), 4)
        self.model = model
        #: (N, T) 1/4 where particle n is a vertex of tet t
        self.quarter = sp.csr_matrix((np.full(4 * t, 0.25), (rows, cols)), shape=(n, t))
        #: (N, T) d(a particle's coefficient)/d(a tet's): V0_t / 4 / V0_n on its tets
        self.average = sp.csr_matrix((np.repeat(model.rest_volumes / 4.0, 4)
                                      / model.node_volumes[rows], (rows, cols)), shape=(n, t))

    @classmethod
    def of(cls, model: Model) -> "NodalElements | None":
        """The nodal elements of ``model``, None when its volume term is per tet (or off)."""
        return cls(model) if is_nodal(model) else None

    def means(self, per_tet: np.ndarray) -> np.ndarray:
        """(N, k) the particles' volume-weighted means of per-tet values (T, k)
        (:func:`particle.nodal_volume.node_average`, the forward pass's coefficients)."""
        m = self.model
        return node_average(m.tets, m.rest_volumes, m.node_volumes, per_tet)

    def pressure_adjoints(self, per_tet: np.ndarray) -> np.ndarray:
        """(S', N) the particles' pressure adjoints from the tets' (S', T), C-ordered."""
        return np.ascontiguousarray((self.quarter @ per_tet.T).T)

    def tet_strain_adjoints(self, gamma: np.ndarray) -> np.ndarray:
        """(S', T) per-tet strain adjoints whose pressures ``gamma_t / V0_t`` push the tets as
        the particles' strain adjoints ``gamma`` (S', N) push them through ``gamma_n / V0_n``
        (:func:`particle.sensitivity_kernels.add_volume_pattern_product`'s input)."""
        m = self.model
        return np.ascontiguousarray(
            (self.quarter.T @ (gamma / m.node_volumes).T).T * m.rest_volumes)

    def to_tets(self, jac: np.ndarray | None) -> np.ndarray | None:
        """(..., T) derivatives with respect to the per-tet parameters from those (..., N)
        with respect to the particles' coefficients (None stays None)."""
        if jac is None:
            return None
        flat = jac.reshape(-1, jac.shape[-1])
        return np.asarray(flat @ self.average).reshape(*jac.shape[:-1], self.average.shape[1])


class _VolumeAdjoint:
    """The volume arms' part of one point's adjoint pass (module docstring): their history
    adjoints, output-major like the connectors' (``pbar`` (S, 2, M) of the arm pressures,
    ``jbar`` (S, M) of the volume strains), and the derivatives ``jac`` (S, 4, M) with
    respect to each volume element's ``kv1, bv1, kv2, bv2`` (M: the tets, or the particles of
    a nodal term, ``nodal``: :class:`NodalElements`)."""

    def __init__(self, model: Model, n_out: int, nodal: "NodalElements | None" = None):
        p = model.params
        self.model, self.nodal = model, nodal
        stiffness, viscosity = p.volume_arm_stiffness, np.column_stack([p.bv1, p.bv2])
        if nodal is not None:
            stiffness, viscosity = nodal.means(stiffness), nodal.means(viscosity)
        self.stiffness, self.viscosity = stiffness, viscosity
        t = model.n_volume_elements
        self.jac = np.zeros((n_out, 4, t))
        self.pbar, self.jbar = np.zeros((n_out, 2, t)), np.zeros((n_out, t))
        self.dP_dk, self.dP_db = np.empty((t, 2)), np.empty((t, 2))

    def add_history(self, x: np.ndarray, tet_dofs: np.ndarray, cols: np.ndarray,
                    step: VolumeArmStep, out: np.ndarray) -> None:
        """``out`` (S', n) += the forces of the pressures ``gamma / V0`` carried back from
        later steps (``gamma = jbar + sum_i c_i pbar_i``, the adjoint of each tet's volume
        strain), as :func:`~particle.sensitivity_kernels.pattern_product` adds the
        connectors' ``G beta``."""
        m = self.model
        gamma = np.empty((len(cols), m.n_volume_elements))
        kern.elongation_adjoint(cols, self.jbar, self.pbar, step.c, True, gamma)
        if self.nodal is not None:
            gamma = self.nodal.tet_strain_adjoints(gamma)
        kern.add_volume_pattern_product(x, m.tets, tet_dofs, m.rest_volumes, gamma, out)

    def add_partials(self, cols: np.ndarray, step: VolumeArmStep, pressure: np.ndarray,
                     strain: np.ndarray) -> None:
        """This step's derivatives with respect to the volume arms, and their history
        adjoints stepped back; ``pressure`` (S', M) the adjoints of the volume elements'
        pressures, ``strain`` (M,) their volume strains at the step."""
        kern.arm_derivatives(step.r, step.c, self.stiffness, self.viscosity,
                             step.pressure_prev, strain, step.strain_prev, self.dP_dk,
                             self.dP_db)
        kern.add_volume_arm_partials(cols, pressure, self.jac, step.r, step.c, self.dP_dk,
                                     self.dP_db, self.pbar, self.jbar)


class _Recorded:
    """Mixin: an evaluator that records its forward pass, what the adjoint pass walks back.

    Each point's path (every (sub)step solved, :class:`_RecordingSolver`), where each
    sample ends in it, and its last force vectors with the parameters they were computed at
    (:meth:`forward`: a Jacobian at equal parameters starts from it).
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._forward: dict[int, tuple[ConnectorParams, np.ndarray]] = {}  # point -> (S, 3)
        self._ends: dict[int, list[int]] = {}  # point -> the path step where each sample ends

    def _solver(self, k: int) -> EquilibriumSolver:
        if k not in self._solvers:
            self._solvers[k] = _RecordingSolver(self.model, self.footprints[k], self._pattern,
                                                rtol=self.rtol)
        return self._solvers[k]

    def _samples(self, k: int, solver: EquilibriumSolver, n: int):
        # the path of this call only, and where each sample ends in it
        solver.path.clear()
        ends = []
        for s in super()._samples(k, solver, n):
            yield s
            ends.append(len(solver.path) - 1)
        self._ends[k] = ends

    def force_vectors(self, params: ConnectorParams, points: Sequence[int] | None = None
                      ) -> np.ndarray:
        idx = self._indices(points)
        for k in idx:  # their paths are about to be overwritten (even if a solve fails)
            self._forward.pop(int(k), None)
        vectors = super().force_vectors(params, idx)
        # each point's path now belongs to these parameters: a Jacobian at equal
        # parameters (the fit's linearisation after an accepted trial) starts from it
        for k, row in zip(idx, vectors):
            self._forward[int(k)] = (params, row)
        return vectors

    def forget(self) -> None:
        super().forget()
        self._forward = {}

    def __getstate__(self) -> dict:
        state = super().__getstate__()
        state["_forward"] = {}
        return state

    def forward(self, params: ConnectorParams, idx: np.ndarray) -> np.ndarray:
        """(P', S, 3) indenter force vectors [N] of points ``idx`` at ``params``, their paths
        recorded: solved only for points whose last curve was computed at other parameters."""
        stale = [int(k) for k in idx if int(k) not in self._forward
                 or not same_values(self._forward[int(k)][0], params)]
        if stale:
            self.force_vectors(params, stale)
        return np.stack([self._forward[int(k)][1] for k in idx])


class _Adjoint(_Recorded):
    """Mixin: the adjoint pass shared by the two evaluators (module docstring).

    :meth:`_point_jacobian` runs it with the compiled kernels of
    :mod:`particle.sensitivity_kernels`; :func:`point_jacobian_numpy` is the plain
    numpy/scipy twin it is tested against (``numpy_twin = True`` makes :meth:`jacobian`
    use it).
    """

    numpy_twin = False

    def jacobian(self, params: ConnectorParams, points: Sequence[int] | None = None,
                 directions: np.ndarray | None = None) -> Sensitivities:
        """Curves and their derivatives at the selected points (all if None).

        ``directions``: (D, 3) unit vectors; the outputs are then the components of the
        indenter force along each (``force_vectors . d``), direction-major: output
        ``d S + j`` is direction d at sample j (D S outputs per point). None: the normal
        force curves of :meth:`__call__` (each point's own normal, S outputs).

        A point whose last curve was computed at equal parameters is not solved again:
        its recorded path and force vectors are used (what :meth:`force_vectors`, hence
        :meth:`__call__`, returned then).
        """
        idx = self._indices(points)
        vectors = self.forward(params, idx)
        if directions is None:
            forces = normal_force(vectors, self.normals[idx])
        else:
            directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
            if not np.allclose(np.linalg.norm(directions, axis=1), 1.0, atol=1e-9):
                raise ParameterError(f"output directions must be unit vectors, got "
                                     f"{directions.tolist()}")
            forces = force_components(vectors, directions)
        model = self.model.with_params(params)
        parts = [point_jacobian_numpy(self, model, int(k), directions) if self.numpy_twin
                 else self._point_jacobian(model, int(k), directions) for k in idx]
        return Sensitivities(forces, np.stack([c for c, _, _ in parts]),
                             None if params.kv is None else np.stack([v for _, v, _ in parts]),
                             None if not params.has_volume_arms
                             else np.stack([a for _, _, a in parts]))

    def _steps(self, k: int) -> tuple[list[tuple[ArmStep | None, Equilibrium]], list[int]]:
        """The (sub)steps whose equilibria make point k's curve, and the step of each sample."""
        raise NotImplementedError

    def _push(self, k: int, pat, directions: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
        """(D, n_dofs) each output direction on the dofs of the particles the indenter holds
        (0 elsewhere; ``directions`` (D, 3), None: the point's normal, D = 1) and (3h,) those
        dofs."""
        prescribed = self._solvers[k].prescribed
        pdofs = pat.dofs(prescribed)
        directions = self.normals[k][None] if directions is None else directions
        push = np.zeros((len(directions), pat.n_dofs))
        push[:, pdofs] = np.tile(directions, (1, len(prescribed)))
        return push, pdofs

    @staticmethod
    def _tangent(solver: EquilibriumSolver, model: Model, pat, eq: Equilibrium,
                 arms: ArmStep | None) -> np.ndarray:
        """CSC data (nnz,) of the exact tangent ``K`` at the equilibrium (no constraints yet):
        from the tensions (and the volume arms' pressures) the solve left (bitwise those a
        force evaluation at ``eq.x`` gives: the same kernel at the same point with the same
        arm step), else from an evaluation."""
        if eq.tension is not None:
            return tangent_data(model, pat, eq.x, eq.tension, model.params, True, arms,
                                eq.volume_arm)
        it = solver._evaluate(eq.x, model.params, not model.params.is_linear, arms, None)
        return tangent_data(model, pat, eq.x, it.tension, model.params, True, arms,
                            it.volume_arm)

    @staticmethod
    def _constrained_factor(solver: EquilibriumSolver, pat, data: np.ndarray):
        """Factorisation of ``K_aa`` (identity on the prescribed dofs); overwrites ``data``."""
        data[solver._zero_slots] = 0.0
        data[solver._diag_slots] = 1.0
        return ldl_factor(pat, data)

    def _point_jacobian(self, model: Model, k: int, directions: np.ndarray | None = None
                        ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(D S, 7, E) connector derivatives, (D S, T) kv derivatives (None without kv) and
        (D S, 4, T) volume arm derivatives (None without them) of the outputs along
        ``directions`` (D, 3) (:meth:`jacobian`; None: the normal, D = 1).

        The adjoints are kept output-major (:mod:`particle.sensitivity_kernels`), and a
        step solves only for the outputs it carries: those whose sample ends there, and
        those ending later when the arms carry their history back (the others' adjoints
        are 0).
        """
        solver = self._solvers[k]
        steps, ends = self._steps(k)
        n_samples, e = len(self.depths), model.n_connectors
        pat = self.pattern_for(solver)
        push, pdofs = self._push(k, pat, directions)
        n_dirs = len(push)
        n_out = n_dirs * n_samples
        direction_of = np.repeat(np.arange(n_dirs), n_samples)  # output -> its direction
        push_cols = np.unique(pdofs)
        p = model.params
        end_dofs = pat.node_dof[model.edges]  # (E, 2) first dof of each end, -1 fixed
        tet_dofs = None if p.kv is None else pat.node_dof[model.tets]
        arm_k, arm_b = p.arm_stiffness, np.column_stack([p.b1, p.b2])
        jac = np.zeros((n_out, N_PARAMS, e))
        nodal = NodalElements.of(model)
        jac_kv = None if p.kv is None else np.zeros((n_out, model.n_volume_elements))
        volume = None if not p.has_volume_arms else _VolumeAdjoint(model, n_out, nodal)
        abar = np.zeros((n_out, 2, e))  # adjoint of the arm forces passed to the next step
        dbar = np.zeros((n_out, e))  # adjoint of the elongation passed to the next step
        carried = np.zeros(n_out, dtype=bool)  # outputs whose abar, dbar may be nonzero
        unit, dx = np.empty((e, 3)), np.empty(e)
        dA_dk, dA_db = np.empty((e, 2)), np.empty((e, 2))
        no_arms = np.zeros((e, 2))  # what the kernels get (unread) for an elastic step
        k_push = np.empty((n_dirs, pat.n_dofs))
        end_of = {s: j for j, s in enumerate(ends)}
        for s in range(len(steps) - 1, -1, -1):
            arms, eq = steps[s]
            live = carried.copy()
            ending = (np.arange(n_dirs) * n_samples + end_of[s] if s in end_of
                      else np.empty(0, dtype=np.int64))  # the outputs whose sample ends here
            live[ending] = True
            cols = np.flatnonzero(live)
            if not len(cols):
                continue
            w = np.zeros(n_out)
            w[ending] = 1.0
            w = w[cols]  # (S',) output weights: 1 for the outputs ending here
            data = self._tangent(solver, model, pat, eq, arms)
            for d in range(n_dirs):
                kern.csc_columns_product(pat.indptr, pat.indices, data, push_cols,
                                         push[d, push_cols], k_push[d])
            kern.connector_geometry(eq.x, model.edges, model.rest_lengths, unit, dx)
            beta = np.empty((len(cols), e))
            kern.elongation_adjoint(cols, dbar, abar, no_arms if arms is None else arms.c,
                                    arms is not None, beta)
            rhs = np.empty((len(cols), pat.n_dofs))
            kern.pattern_product(end_dofs, unit, beta, rhs)
            step = None if arms is None else arms.volume
            if volume is not None and step is not None:
                volume.add_history(eq.x, tet_dofs, cols, step, rhs)
            rhs = k_push[direction_of[cols]] * w[:, None] - rhs
            rhs[:, pdofs] = 0.0
            lam = self._constrained_factor(solver, pat, data).solve(rhs.T).T  # (S', n) C-order
            lam[:, pdofs] = -push[direction_of[cols]][:, pdofs] * w[:, None]
            tau = np.empty((len(cols), e))  # adjoint of each connector's tension
            kern.pattern_transpose_product(end_dofs, unit, lam, tau)
            if arms is not None:
                kern.arm_derivatives(arms.r, arms.c, arm_k, arm_b, arms.force_prev, dx,
                                     arms.dx_prev, dA_dk, dA_db)
                kern.add_partials(cols, tau, dx, model.rest_lengths, jac, True, arms.r, arms.c,
                                  dA_dk, dA_db, abar, dbar)
                carried = live
            else:
                kern.add_partials(cols, tau, dx, model.rest_lengths, jac, False, no_arms,
                                  no_arms, dA_dk, dA_db, abar, dbar)
            if jac_kv is not None:
                pressure = np.empty((len(cols), model.n_tets))  # adjoint of each tet's pressure
                strain = np.empty(model.n_tets)
                if nodal is None:
                    kern.add_volume_partials(eq.x, model.tets, tet_dofs, model.rest_volumes,
                                             cols, lam, jac_kv, pressure, strain)
                else:  # the tets' pressure adjoints, then the particles' (the tets' kv unused)
                    kern.add_volume_partials(eq.x, model.tets, tet_dofs, model.rest_volumes,
                                             cols, lam, np.zeros((n_out, model.n_tets)),
                                             pressure, strain)
                    pressure = nodal.pressure_adjoints(pressure)
                    jac_kv[cols] += pressure * element_strains(model, eq.x)
                if volume is not None and step is not None:
                    volume.add_partials(cols, step, pressure, eq.volume_strain)
        if nodal is not None:
            return jac, nodal.to_tets(jac_kv), None if volume is None else nodal.to_tets(
                volume.jac)
        return jac, jac_kv, None if volume is None else volume.jac

    @staticmethod
    def pattern_for(solver: EquilibriumSolver):
        return solver.pattern

def point_jacobian_numpy(ev: "_Adjoint", model: Model, k: int,
                         directions: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """:meth:`_Adjoint._point_jacobian` of evaluator ``ev`` in plain numpy/scipy (every output
    at every step): its twin."""
    solver = ev._solvers[k]
    steps, ends = ev._steps(k)
    n_samples, e = len(ev.depths), model.n_connectors
    pat = ev.pattern_for(solver)
    push, pdofs = ev._push(k, pat, directions)  # (D, n_dofs)
    n_out = len(push) * n_samples
    push = np.repeat(push, n_samples, axis=0).T  # (n_dofs, D S): each output's direction
    jac = np.zeros((n_out, N_PARAMS, e))
    p = model.params
    nodal = NodalElements.of(model)
    m = model.n_volume_elements  # the tets, or the particles of the nodal term
    rest = model.rest_volumes if nodal is None else model.node_volumes
    arm_k = arm_b = None
    if p.has_volume_arms:
        arm_k, arm_b = p.volume_arm_stiffness, np.column_stack([p.bv1, p.bv2])
        if nodal is not None:
            arm_k, arm_b = nodal.means(arm_k), nodal.means(arm_b)
    jac_kv = None if p.kv is None else np.zeros((n_out, m))
    jac_arms = np.zeros((n_out, 4, m)) if p.has_volume_arms else None
    abar = np.zeros((e, 2, n_out))  # adjoint of the arm forces passed to the next step
    dbar = np.zeros((e, n_out))  # adjoint of the elongation passed to the next step
    pbar = np.zeros((m, 2, n_out))  # adjoint of the volume arms' pressures
    jbar = np.zeros((m, n_out))  # adjoint of the volume strains
    end_of = {s: j for j, s in enumerate(ends)}
    for s in range(len(steps) - 1, -1, -1):
        arms, eq = steps[s]
        volume = None if arms is None else arms.volume
        w = np.zeros(n_out)
        if s in end_of:
            w[end_of[s]::n_samples] = 1.0
        if not w.any() and not abar.any() and not dbar.any():
            continue
        geo = _Geometry(model, eq.x)
        data = ev._tangent(solver, model, pat, eq, arms)
        full = sp.csc_matrix((data, pat.indices, pat.indptr), shape=(pat.n_dofs, pat.n_dofs))
        G = geo.pattern_matrix(pat)  # (n_dofs, E): force of a unit tension
        beta = dbar.copy()
        if arms is not None:
            beta += np.einsum("ei,eis->es", arms.c, abar)
        rhs = (full @ push) * w[None, :] - G @ beta
        if p.kv is not None:
            H = volume_pattern_matrix(model, eq.x, pat)  # (n_dofs, T): force of a unit pressure
            if nodal is not None:  # (n_dofs, N): a particle's pressure, a quarter on each tet
                H = (H @ nodal.quarter.T).tocsr()
        if volume is not None:
            gamma = jbar + np.einsum("ti,tis->ts", volume.c, pbar)
            rhs -= H @ (gamma / rest[:, None])
        rhs[pdofs] = 0.0
        lam = ev._constrained_factor(solver, pat, data).solve(rhs)
        lam[pdofs] = -push[pdofs] * w[None, :]
        tau = G.T @ lam  # (E, S) adjoint of each connector's tension
        jac += partials_numpy(model, geo, arms, tau, abar)
        if p.kv is not None and nodal is None:
            jac_kv += volume_partials_numpy(model, eq.x, pat, lam)
        elif p.kv is not None:
            jac_kv += ((H.T @ lam) * element_strains(model, eq.x)[:, None]).T
        if arms is not None:
            mu = abar + tau[:, None, :]
            abar = arms.r[:, :, None] * mu
            dbar = -np.einsum("ei,eis->es", arms.c, mu)
        if volume is not None:
            mu = pbar + (H.T @ lam)[:, None, :]  # (T, 2, S)
            jac_arms += maxwell_partials_numpy(
                volume.r, volume.c, arm_k, arm_b, volume.pressure_prev,
                eq.volume_strain - volume.strain_prev, mu)
            pbar = volume.r[:, :, None] * mu
            jbar = -np.einsum("ti,tis->ts", volume.c, mu)
    if nodal is not None:
        return jac, nodal.to_tets(jac_kv), nodal.to_tets(jac_arms)
    return jac, jac_kv, jac_arms


def volume_pattern_matrix(model: Model, x: np.ndarray, pat) -> sp.csr_matrix:
    """(n_dofs, T) forces on the matrix dofs of a unit pressure in each tet: ``-dV/dx``."""
    grad = volume_gradients_numpy(x, model.tets)  # (T, 4, 3)
    dof = pat.node_dof[model.tets]  # (T, 4)
    rows = dof[:, :, None] + np.arange(3)
    cols = np.broadcast_to(np.arange(model.n_tets)[:, None, None], rows.shape)
    keep = np.broadcast_to((dof >= 0)[:, :, None], rows.shape)
    return sp.csr_matrix((-grad[keep], (rows[keep], cols[keep])),
                         shape=(pat.n_dofs, model.n_tets))


def maxwell_partials_numpy(r: np.ndarray, c: np.ndarray, k: np.ndarray, b: np.ndarray,
                           force_prev: np.ndarray, step: np.ndarray, mu: np.ndarray
                           ) -> np.ndarray:
    """(S, 4, M): ``mu_i dA_i/dk_i, mu_i dA_i/db_i`` (i = 1, 2) of M elements' arms after one
    exact step ``A_i = r_i A_i^prev + c_i step`` (``r``, ``c``, ``k``, ``b``, ``force_prev``
    (M, 2); ``step`` (M,) the change of the elongation or volume strain; ``mu`` (M, 2, S)
    the arm forces' adjoints): the twin of :func:`particle.sensitivity_kernels.arm_derivatives`
    with the arms' part of :func:`~particle.sensitivity_kernels.add_partials`."""
    log_r = np.log(r)
    dA_dk = (log_r * r / k) * force_prev + r * step[:, None]
    dA_db = (-log_r * r / b) * force_prev + ((c - r * k) / b) * step[:, None]
    out = np.empty((mu.shape[2], 4, len(r)))
    for i in range(2):
        out[:, 2 * i] = (mu[:, i, :] * dA_dk[:, i, None]).T
        out[:, 2 * i + 1] = (mu[:, i, :] * dA_db[:, i, None]).T
    return out


def partials_numpy(model: Model, geo: "_Geometry", arms: ArmStep | None, tau: np.ndarray,
                   abar: np.ndarray) -> np.ndarray:
    """(S, 7, E): this step's explicit parameter derivatives contracted with the adjoints
    (the twin of :func:`particle.sensitivity_kernels.add_partials`).

    ``tau`` (E, S) adjoint of the tensions, ``abar`` (E, 2, S) of the new arm forces
    (from later steps).
    """
    p = model.params
    out = np.zeros((tau.shape[1], N_PARAMS, model.n_connectors))
    dx, eps = geo.dx, geo.dx / model.rest_lengths
    out[:, 0] = (tau * dx[:, None]).T
    out[:, 1] = (tau * (eps * dx)[:, None]).T
    out[:, 2] = (tau * (eps * eps * dx)[:, None]).T
    if arms is not None:
        mu = abar + tau[:, None, :]  # (E, 2, S)
        out[:, 3:] = maxwell_partials_numpy(arms.r, arms.c, p.arm_stiffness,
                                            np.column_stack([p.b1, p.b2]), arms.force_prev,
                                            geo.dx - arms.dx_prev, mu)
    return out


class _Geometry:
    """Connector directions and elongations at positions x (N, 3)."""

    def __init__(self, model: Model, x: np.ndarray):
        i, j = model.edges[:, 0], model.edges[:, 1]
        d = x[j] - x[i]
        length = np.linalg.norm(d, axis=1)
        self.model = model
        self.unit = d / length[:, None]
        self.dx = length - model.rest_lengths

    def pattern_matrix(self, pat) -> sp.csr_matrix:
        """(n_dofs, E) forces on the matrix dofs of a unit tension in each connector."""
        e = np.arange(self.model.n_connectors)
        rows, cols, vals = [], [], []
        for end, sign in ((0, 1.0), (1, -1.0)):
            dof0 = pat.node_dof[self.model.edges[:, end]]
            keep = dof0 >= 0
            for c in range(3):
                rows.append(dof0[keep] + c)
                cols.append(e[keep])
                vals.append(sign * self.unit[keep, c])
        return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(pat.n_dofs, self.model.n_connectors))


class IndentationSensitivity(_Adjoint, IndentationEvaluator):
    """:class:`IndentationEvaluator` with :meth:`jacobian` (module docstring)."""

    def _steps(self, k):
        solver = self._solvers[k]
        steps = [solver.path[s] for s in self._ends[k]]  # elastic: each sample on its own
        return steps, list(range(len(steps)))


class RelaxationSensitivity(_Adjoint, RelaxationEvaluator):
    """:class:`RelaxationEvaluator` with :meth:`jacobian` (module docstring)."""

    def _steps(self, k):
        solver = self._solvers[k]
        path = list(solver.path)
        if any(arms is None for arms, _ in path):
            raise ParameterError("relaxation path without arm steps; cannot differentiate it")
        return path, list(self._ends[k])


def sensitivity_evaluators(model: Model, nodes: np.ndarray, normals: np.ndarray,
                           depths: np.ndarray, times: np.ndarray, relaxation_depths: np.ndarray,
                           strain_range: tuple[float, float] | None = None, *,
                           footprints: Sequence[np.ndarray] | None = None
                           ) -> dict[str, _Adjoint]:
    """Both experiments' evaluators with :meth:`~_Adjoint.jacobian`, keyed like the pool's
    (``footprints``: the particles each indenter holds, as in :mod:`particle.evaluators`)."""
    kw = dict(strain_range=strain_range, footprints=footprints)
    return {"indentation": IndentationSensitivity(model, nodes, normals, depths, **kw),
            "relaxation": RelaxationSensitivity(model, nodes, normals, times, relaxation_depths,
                                                **kw)}
