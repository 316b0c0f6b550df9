"""Whole-body responses of the particle model and their exact parameter derivatives.

The FE reference's experiment ``body`` (:class:`forcecal.h5io.BodyResult`) holds whole-body
data (modes with the support and without, static loads, modes about the loads); this module
computes the particle model's counterparts, their residuals against the FE's and the
Jacobians of those residuals with respect to every parameter:

* **natural modes** about the rest state (the fixed particles held), at the instantaneous
  stiffness (springs ``K0 + k1 + k2``, volume term ``kv + kv1 + kv2`` when it relaxes) and
  at the long-term one (``K0``, ``kv``), with the model's lumped masses ``M``. At rest a
  connector has no tension, so the tangent is linear in the stiffnesses::

      K = G diag(k) G^T + H diag(kv / V0) H^T

  (``G`` (n, E) the force pattern of unit connector tensions, ``H`` (n, T) that of unit tet
  pressures ``-dV/dx``, on the free dofs). For a mode ``K phi = lambda M phi`` with
  ``phi^T M phi = 1``, ``dlambda/dp = phi^T D(phi)_p`` with ``D(phi) = d(K phi)/dp`` (a
  sparse (n, P) matrix: column ``G_e (G_e . phi)`` for a connector's stiffness, ``H_t
  (H_t . phi)/V0_t`` for a tet's), and the mode's derivative ``dphi/dp = -S D(phi)_p``
  with ``S = sum_{j != m} phi_j phi_j^T / (lambda_j - lambda_m)`` (the masses do not
  depend on the parameters). ``S b`` is one solve of the bordered system ``[[K - lambda
  M, M phi], [phi^T M, 0]]`` (exact, no modal truncation).
* **natural modes of the unsupported body** (no particle held; :func:`unsupported_model`):
  the same, with its six rigid modes left out (:func:`forcecal.eigen.free_modes`). A rigid
  mode's force pattern ``G^T psi`` is zero, so it adds nothing to ``dlambda/dp`` and the
  bordered solve stays regular;
* **static body loads**: the weight along a direction, long-term model, nonlinear, load
  stepped (:func:`particle.statics.weight_equilibrium`); at the equilibrium ``f(x, p) =
  0`` with tangent ``K_t = -df/dx``, ``du/dp = K_t^{-1} E`` with ``E = df/dp`` at fixed
  positions (``G_e dx_e``, ``G_e eps dx``, ``G_e eps^2 dx`` for ``K0, a, b``, ``H_t j_t``
  for ``kv``; arms relaxed).

Every Jacobian is returned as ``L @ D`` (:class:`Rows`): dense *virtual fields* ``L``
(rows, n) times a sparse parameter-force matrix ``D`` (n, P) in the parameter layout of
:func:`parameter_layout` (``K0, a, b, k1, b1, k2, b2`` per connector, then ``kv`` and
``kv1, bv1, kv2, bv2`` per tet), so that a caller can chain it to its own coordinates as
a sparse product and never form a dense (rows, P) block it does not need.

Residuals (each a relative error, so a whole-body item weighs like a calibration point):

* a load: ``(u - u_FE) / (max |u_FE| sqrt(N_free))`` on every free particle's three
  components: its squared norm is the squared RMS displacement error relative to the
  largest FE displacement;
* a mode (FE mode ``k`` at one modulus, paired with the model mode of largest MAC by an
  optimal assignment): the frequency error ``f_m / f_k - 1`` and the shape error
  ``Q^T M (phi_m - psi_k)`` in an ``M``-orthonormal basis ``Q`` of the FE modes' span at
  that modulus (``psi``: the FE shapes at the particles, ``M``-normalised; ``phi_m``
  signed to agree with ``psi_k``): its norm is the shape's relative error within the span
  of the FE modes computed.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from scipy.optimize import linear_sum_assignment

from forcecal.eigen import RIGID_MODES, free_modes, nearest_modes
from forcecal.errors import ConvergenceError, ParameterError
from forcecal.h5io import BODY_MODULI, BodyResult
from forcecal.scene import BODY_KINDS
from particle import body_kernels
from particle.model import Model
from particle.params import PARAM_NAMES, VOLUME_ARM_NAMES, ConnectorParams
from particle.sensitivity import _Geometry, volume_pattern_matrix
from particle.statics import (ArmStep, TangentPattern, VolumeArmStep, ldl_factor, net_forces,
                              tangent_data, weight_equilibrium)
from particle.nodal_volume import refuse_nodal
from particle.volume import volume_strains

log = logging.getLogger(__name__)

#: model modes computed beyond the FE's, so that each FE mode finds its partner by MAC
EXTRA_MODES = 4


def parameter_layout(n_connectors: int, n_tets: int, arms: bool) -> dict[str, slice]:
    """Columns of each parameter block in a parameter-force matrix: ``K0, a, b, k1, b1, k2,
    b2`` (E each), then ``kv`` and, with volume arms, ``kv1, bv1, kv2, bv2`` (T each)."""
    names = list(PARAM_NAMES) + (["kv"] if n_tets else []) + (
        list(VOLUME_ARM_NAMES) if arms else [])
    out, start = {}, 0
    for name in names:
        size = n_connectors if name in PARAM_NAMES else n_tets
        out[name] = slice(start, start + size)
        start += size
    return out


@dataclass(frozen=True, eq=False)
class Rows:
    """Residual rows and their Jacobian ``L @ D`` (module docstring).

    Attributes:
        residual: (R,) residuals [1].
        fields: (R, n) virtual fields ``L`` on the free dofs; None for residuals alone
            (:func:`body_response` with ``jacobian=False``).
        forces: (n, P) sparse parameter-force matrix ``D`` (:func:`parameter_layout`); None
            for residuals alone.
        explicit: (R, P) a part of the Jacobian given as it is (added to ``L D``), or None.
    """
    residual: np.ndarray
    fields: np.ndarray | None = None
    forces: sp.csr_matrix | None = None
    explicit: np.ndarray | None = None

    def jacobian(self) -> np.ndarray:
        """(R, P) the dense Jacobian (for tests and small problems)."""
        out = np.asarray((self.forces.T @ self.fields.T).T)
        return out if self.explicit is None else out + self.explicit


#: the kinds of whole-body data that come from the static body loads
LOAD_KINDS = (BODY_KINDS[0], BODY_KINDS[2])


def available_kinds(body: BodyResult) -> tuple[str, ...]:
    """The kinds (:data:`BODY_KINDS`) an FE ``body`` result holds: every one, but
    ``free_modes`` in a reference computed before them and the loads and the modes about
    them (:data:`LOAD_KINDS`) where the FE could not hold the body under the loads."""
    return tuple(k for k in BODY_KINDS
                 if (k != BODY_KINDS[3] or body.free_frequencies is not None)
                 and (k not in LOAD_KINDS or body.load_failure is None))


def _no_modes(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Empty (frequencies (2, 0), shapes (2, 0, n, 3)) at :data:`BODY_MODULI`: no modes."""
    return np.zeros((len(BODY_MODULI), 0)), np.zeros((len(BODY_MODULI), 0, n, 3))


@dataclass(frozen=True, eq=False)
class BodyTarget:
    """The FE's whole-body data in the particle model's terms.

    Attributes:
        accelerations: (L, 3) the loads [m/s^2]; (0, 3) when loads are not fitted.
        displacement: (L, N, 3) their FE displacements [m].
        frequencies: (2, M) FE natural frequencies [Hz] (:data:`~forcecal.h5io.BODY_MODULI`);
            (2, 0) when modes are not fitted.
        shapes: (2, M, N, 3) FE mode shapes at the particles (any normalisation).
        loaded_accelerations: (L', 3) the loads whose loaded states' modes are fitted
            ((0, 3): none).
        loaded_frequencies: (L', M') their FE frequencies [Hz]; loaded_shapes: (L', M', N, 3).
        free_frequencies: (2, M'') FE natural frequencies of the unsupported body [Hz]
            ((2, 0): not fitted, or a reference without them); free_shapes: (2, M'', N, 3).
    """
    accelerations: np.ndarray
    displacement: np.ndarray
    frequencies: np.ndarray
    shapes: np.ndarray
    loaded_accelerations: np.ndarray
    loaded_frequencies: np.ndarray
    loaded_shapes: np.ndarray
    free_frequencies: np.ndarray
    free_shapes: np.ndarray

    @classmethod
    def of(cls, body: BodyResult, kinds: tuple[str, ...]) -> "BodyTarget":
        """The data of ``kinds`` (some of :data:`BODY_KINDS`) of an FE ``body`` result.

        Raises:
            ParameterError: an unknown kind, or ``free_modes`` asked of a reference computed
                without them.
        """
        if BODY_KINDS[3] in kinds and body.free_frequencies is None:
            raise ParameterError("whole-body data 'free_modes': the reference's experiment "
                                 "body was computed without the unsupported body's modes; "
                                 "recompute it (make reference)")
        free = ((body.free_frequencies, body.free_shapes) if body.free_frequencies is not None
                else _no_modes(body.shapes.shape[2]))
        every = cls(body.load_accelerations, body.load_displacement, body.frequencies,
                    body.shapes, body.load_accelerations, body.loaded_frequencies,
                    body.loaded_shapes, *free)
        return every.subset(kinds)

    def subset(self, kinds: tuple[str, ...]) -> "BodyTarget":
        """The data of ``kinds`` of this target (empty arrays for the others)."""
        unknown = sorted(set(kinds) - set(BODY_KINDS))
        if unknown:
            raise ParameterError(f"whole-body data {unknown}: known kinds are {BODY_KINDS}")
        loads, modes, loaded, free = (k in kinds for k in BODY_KINDS)
        n = self.shapes.shape[2]
        no_modes = _no_modes(n)
        return BodyTarget(self.accelerations if loads else np.zeros((0, 3)),
                          self.displacement if loads else np.zeros((0, n, 3)),
                          *((self.frequencies, self.shapes) if modes else no_modes),
                          self.loaded_accelerations if loaded else np.zeros((0, 3)),
                          self.loaded_frequencies if loaded else np.zeros((0, 0)),
                          self.loaded_shapes if loaded else np.zeros((0, 0, n, 3)),
                          *((self.free_frequencies, self.free_shapes) if free else no_modes))

    @property
    def items(self) -> list[str]:
        """Names of the data items, in residual order: ``load <k>``, ``<modulus> mode <j>``
        for each modulus, ``load <k> mode <j>``, then ``free <modulus> mode <j>``."""
        return ([f"load {k}" for k in range(len(self.accelerations))]
                + [f"{modulus} mode {k}" for modulus in BODY_MODULI
                   for k in range(self.frequencies.shape[1])]
                + [f"load {k} mode {j}" for k in range(len(self.loaded_accelerations))
                   for j in range(self.loaded_frequencies.shape[1])]
                + [f"free {modulus} mode {k}" for modulus in BODY_MODULI
                   for k in range(self.free_frequencies.shape[1])])

    @property
    def item_kinds(self) -> list[str]:
        """The kind (:data:`BODY_KINDS`) of each of :attr:`items`."""
        return [BODY_KINDS[3] if name.startswith("free")
                else BODY_KINDS[2] if " mode " in name and name.startswith("load")
                else BODY_KINDS[0] if name.startswith("load") else BODY_KINDS[1]
                for name in self.items]


@dataclass(frozen=True, eq=False)
class RestOperators:
    """The model's linear operators at the rest state, on the dofs of its free particles.

    Attributes:
        unsupported: the same operators of the model with no particle fixed, or None.
        pattern: the tangent pattern (dof numbering) of the model.
        tension: (n, E) sparse ``G``: forces of unit connector tensions at rest.
        pressure: (n, T) sparse ``H``: forces of unit tet pressures at rest (used with the
            volume term only).
        mass: (n,) lumped mass of each dof [kg].
    """
    pattern: TangentPattern
    tension: sp.csr_matrix
    pressure: sp.csr_matrix
    mass: np.ndarray
    unsupported: "RestOperators | None" = None

    @classmethod
    def of(cls, model: Model, *, unsupported: bool = False) -> "RestOperators":
        """The operators of ``model``; with ``unsupported`` also those of the model with no
        particle fixed (:attr:`unsupported`: the free-free modes' dofs)."""
        refuse_nodal(model, "the whole-body operators (particle.body)")
        pat = TangentPattern.of(model)
        x = model.rest_positions
        pressure = volume_pattern_matrix(model, x, pat)  # (n, T); unused without kv
        mass = np.repeat(model.masses[model.free_nodes], 3)
        free = cls.of(unsupported_model(model)) if unsupported else None
        return cls(pat, _Geometry(model, x).pattern_matrix(pat), pressure, mass, free)

    def stiffnesses(self, p: ConnectorParams, modulus: str) -> tuple[np.ndarray, np.ndarray]:
        """((E,) connector [N/m], (T,) volume [Pa]) stiffnesses at ``modulus``."""
        if modulus not in BODY_MODULI:
            raise ParameterError(f"modulus {modulus!r}: one of {BODY_MODULI}")
        instantaneous = modulus == "instantaneous"
        springs = p.K0 + p.k1 + p.k2 if instantaneous else p.K0
        if p.kv is None:
            return springs, np.zeros(0)
        volume = p.volume_instantaneous if instantaneous else p.kv
        return springs, volume

    def stiffness(self, model: Model, modulus: str) -> sp.csc_matrix:
        """(n, n) the tangent ``K`` at rest at ``modulus`` [N/m]."""
        springs, volume = self.stiffnesses(model.params, modulus)
        G, H = self.tension, self.pressure
        K = G @ sp.diags(springs) @ G.T
        if model.params.kv is not None:
            K = K + H @ sp.diags(volume / model.rest_volumes) @ H.T
        return sp.csc_matrix(K)

    def mode_forces(self, model: Model, phi: np.ndarray, modulus: str) -> sp.csr_matrix:
        """(n, P) ``d(K phi)/dp`` at ``modulus`` (module docstring): a connector's ``K0`` (and
        ``k1, k2`` at the instantaneous modulus) ``G_e (G_e . phi)``, a tet's ``kv`` (and
        ``kv1, kv2`` when the volume term relaxes) ``H_t (H_t . phi) / V0_t``."""
        p = model.params
        layout = parameter_layout(model.n_connectors, model.n_tets if p.kv is not None else 0,
                                  p.has_volume_arms)
        instantaneous = modulus == "instantaneous"
        blocks = {"K0": self.tension @ sp.diags(self.tension.T @ phi)}
        if instantaneous:
            blocks["k1"] = blocks["k2"] = blocks["K0"]
        if p.kv is not None:
            H = self.pressure
            blocks["kv"] = H @ sp.diags((H.T @ phi) / model.rest_volumes)
            if instantaneous and p.has_volume_arms:
                blocks["kv1"] = blocks["kv2"] = blocks["kv"]
        return assemble_blocks(blocks, layout, len(phi))


def assemble_blocks(blocks: dict[str, sp.spmatrix], layout: dict[str, slice], n: int
                    ) -> sp.csr_matrix:
    """(n, P) the named (n, width) sparse blocks at their columns of ``layout``, zero
    elsewhere."""
    width = max(s.stop for s in layout.values())
    parts = []
    for name, cols in layout.items():
        block = blocks.get(name)
        parts.append(sp.csr_matrix((n, cols.stop - cols.start)) if block is None else block)
    out = sp.hstack(parts, format="csr")
    assert out.shape == (n, width)
    return out


def load_forces(model: Model, x: np.ndarray, pat: TangentPattern) -> sp.csr_matrix:
    """(n, P) ``df/dp`` at positions ``x`` at fixed positions (long-term model, arms relaxed):
    ``G_e dx_e``, ``G_e eps_e dx_e``, ``G_e eps_e^2 dx_e`` for ``K0, a, b``, ``H_t j_t`` for
    ``kv`` (``j = V/V0 - 1``)."""
    refuse_nodal(model, "the whole-body load derivatives (particle.body)")
    p = model.params
    geometry = _Geometry(model, x)
    G = geometry.pattern_matrix(pat)
    dx = geometry.dx
    eps = dx / model.rest_lengths
    blocks = {"K0": G @ sp.diags(dx), "a": G @ sp.diags(eps * dx),
              "b": G @ sp.diags(eps * eps * dx)}
    if p.kv is not None:
        strain = volume_strains(x, model.tets, model.rest_volumes)
        blocks["kv"] = volume_pattern_matrix(model, x, pat) @ sp.diags(strain)
    layout = parameter_layout(model.n_connectors, model.n_tets if p.kv is not None else 0,
                              p.has_volume_arms)
    return assemble_blocks(blocks, layout, pat.n_dofs)


def free_dofs_values(model: Model, field: np.ndarray) -> np.ndarray:
    """(n,) the free particles' components of an (N, 3) field, in the pattern's dof order."""
    return np.asarray(field)[model.free_nodes].ravel()


def load_rows(model: Model, acceleration: np.ndarray, target: np.ndarray, load_steps: int,
              pat: TangentPattern | None = None, *, jacobian: bool = True) -> Rows:
    """The residual rows of one static body load (module docstring) and their Jacobian
    (``jacobian`` False: the residuals alone, without the tangent's factorisation).

    Raises:
        ConvergenceError: the model has no static equilibrium under the load (a model that
            does not carry a load it is fitted to).
    """
    pat = TangentPattern.of(model) if pat is None else pat
    x = weight_equilibrium(model, acceleration, load_steps)
    free = model.free_nodes
    u = (x - model.rest_positions)[free].ravel()
    u_fe = np.asarray(target)[free].ravel()
    scale = float(np.linalg.norm(target, axis=1).max()) * np.sqrt(len(free))
    if not scale > 0:
        raise ParameterError("a body load whose FE displacement is zero everywhere")
    if not jacobian:
        return Rows((u - u_fe) / scale)
    forces, tension, *_ = net_forces(model, x, model.params, not model.params.is_linear, None,
                                     None, (np.zeros(model.n_tets),
                                            np.full(model.n_tets, np.inf)))
    data = tangent_data(model, pat, x, tension, model.params, True, None)
    factor = ldl_factor(pat, data)
    fields = factor.solve(np.eye(pat.n_dofs) / scale).T  # rows: K_t^{-1} e_i / scale
    return Rows((u - u_fe) / scale, np.ascontiguousarray(fields), load_forces(model, x, pat))


def unsupported_model(model: Model) -> Model:
    """``model`` with no particle fixed (its free-free modes' model)."""
    return dataclasses.replace(model, fixed=np.zeros(model.n_particles, bool))


def model_modes(model: Model, ops: RestOperators, modulus: str, count: int,
                stiffness: sp.csc_matrix | None = None, *, free_free: bool = False
                ) -> tuple[np.ndarray, np.ndarray, sp.csc_matrix]:
    """The ``count`` lowest modes of ``model`` at ``modulus`` (or of the given ``stiffness``
    on the free dofs, ``modulus`` then only names it): (eigenvalues (count,) [1/s^2],
    mass-normalised shapes (n, count) on the free dofs, the stiffness ``K``). With
    ``free_free``, ``model`` has no fixed particle and its six rigid modes are left out
    (:func:`forcecal.eigen.free_modes`)."""
    K = ops.stiffness(model, modulus) if stiffness is None else stiffness
    if free_free:
        count = min(count, K.shape[0] - RIGID_MODES - 1)
        values, vectors = free_modes(K, sp.diags(ops.mass), count, f"particle modes of the "
                                     f"unsupported body at the {modulus} stiffness")
        return values, vectors, sp.csc_matrix(K)
    count = min(count, K.shape[0] - 1)
    what = f"particle modes at the {modulus} stiffness"
    values, vectors = nearest_modes(K, sp.diags(ops.mass), count, 0.0, what)
    if not values[0] > 0:
        raise ConvergenceError(f"{what}: eigenvalue {values[0]:.3g} <= 0 (the model is not "
                               "held)")
    return values, vectors, K


def mass_orthonormal(shapes: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """(n, k) an ``M``-orthonormal basis of the span of ``shapes`` (n, k) (``M = diag(mass)``)."""
    w = np.sqrt(mass)[:, None]
    q, _ = np.linalg.qr(w * shapes)
    return q / w


def pair_modes(fe: np.ndarray, model: np.ndarray, mass: np.ndarray) -> tuple[np.ndarray,
                                                                           np.ndarray]:
    """(partner (M,), MAC (M,)): the model mode paired with each FE mode ``fe`` (n, M) among
    ``model`` (n, K), K >= M, by the assignment of largest total MAC (``mass``-weighted)."""
    cross = fe.T @ (mass[:, None] * model)
    norms = np.outer(np.einsum("nk,n,nk->k", fe, mass, fe),
                     np.einsum("nk,n,nk->k", model, mass, model))
    mac = cross ** 2 / norms
    rows, cols = linear_sum_assignment(-mac)
    partner = cols[np.argsort(rows)]
    return partner, mac[np.arange(fe.shape[1]), partner]


@dataclass(frozen=True, eq=False)
class ModeMatch:
    """The model's modes at one modulus paired with the FE's.

    Attributes:
        frequency_errors: (M,) ``f_m / f_k - 1`` of each FE mode's partner [1].
        shape_errors: (M,) ``|Q^T M (phi_m - psi_k)|`` [1].
        mac: (M,) the pairs' MAC [1].
        partner: (M,) the model mode paired with each FE mode.
        parts: each FE mode's residual rows (its frequency error, then its shape error's M
            components) with their Jacobian.
        modes: (n,) each FE mode's partner, mass-normalised and signed like it.
    """
    frequency_errors: np.ndarray
    shape_errors: np.ndarray
    mac: np.ndarray
    partner: np.ndarray
    parts: list[Rows]
    modes: list[np.ndarray]


def mode_rows(model: Model, ops: RestOperators, modulus: str, frequencies: np.ndarray,
              shapes: np.ndarray, stiffness: sp.csc_matrix | None = None, *,
              jacobian: bool = True, free_free: bool = False) -> ModeMatch:
    """Residual rows of the FE modes ``frequencies`` (M,) [Hz], ``shapes`` (M, N, 3) at
    ``modulus`` against the model's (module docstring), with their Jacobian (``jacobian``
    False: the residuals alone, without the bordered solves); with a given ``stiffness`` (a
    loaded state's, :func:`loaded_mode_rows`) its modes, the rows' forces left for the
    caller (None). ``free_free``: ``model`` and ``ops`` are the unsupported body's, whose
    rigid modes are left out (the bordered system stays regular: ``K - lambda M`` is
    singular only along the mode itself, and a rigid mode's force pattern is zero)."""
    n_fe = len(frequencies)
    values, vectors, K = model_modes(model, ops, modulus, n_fe + EXTRA_MODES, stiffness,
                                     free_free=free_free)
    mass = ops.mass
    psi = np.stack([free_dofs_values(model, s) for s in shapes], axis=1)  # (n, M)
    psi = psi / np.sqrt(np.einsum("nk,n,nk->k", psi, mass, psi))
    basis = mass_orthonormal(psi, mass)
    partner, mac = pair_modes(psi, vectors, mass)
    parts, modes = [], []
    f_err, s_err = np.empty(n_fe), np.empty(n_fe)
    M = sp.diags(mass).tocsc()
    for k in range(n_fe):
        m = partner[k]
        lam, phi = values[m], vectors[:, m]
        phi = phi * np.sign(psi[:, k] @ (mass * phi))
        ratio = np.sqrt(lam) / (2.0 * np.pi) / frequencies[k]
        shape = basis.T @ (mass * (phi - psi[:, k]))
        f_err[k], s_err[k] = ratio - 1.0, np.linalg.norm(shape)
        modes.append(phi)
        if not jacobian:
            parts.append(Rows(np.r_[ratio - 1.0, shape]))
            continue
        # S M Q: the bordered system's solution for each basis vector (module docstring)
        mphi = mass * phi
        bordered = sp.bmat([[K - lam * M, sp.csc_matrix(mphi[:, None])],
                            [sp.csc_matrix(mphi[None, :]), None]], format="csc")
        rhs = np.vstack([mass[:, None] * basis - np.outer(mphi, mphi @ basis),
                         np.zeros((1, basis.shape[1]))])
        solved = sla.splu(bordered).solve(rhs)[:-1]  # (n, M)
        parts.append(Rows(np.r_[ratio - 1.0, shape],
                          np.vstack([ratio / (2.0 * lam) * phi, -solved.T]),
                          None if stiffness is not None
                          else ops.mode_forces(model, phi, modulus)))
    return ModeMatch(f_err, s_err, mac, partner, parts, modes)


def incremental_form(model: Model, x: np.ndarray, field: np.ndarray
                     ) -> tuple[float, np.ndarray, np.ndarray]:
    """The instantaneous incremental tangent's quadratic form about the long-term state ``x``
    (N, 3), ``q = phi^T K_t phi`` for a field ``phi`` (N, 3) (zero on fixed particles), with
    its gradient with respect to the positions and its explicit parameter derivatives.

    ``K_t`` is the tangent of small quick motions about a relaxed static state: each
    connector ``s (u . w)^2 + (T / l) (|w|^2 - (u . w)^2)`` (``w`` the field's difference
    across it, ``s = K0 + 2 a eps + 3 b eps^2 + k1 + k2`` the axial tangent with the arms'
    instantaneous stiffness, ``T`` the long-term tension: the relaxed arms carry none), each
    tet ``(kv + kv1 + kv2) / V0 (g . phi)^2 + P phi^T (d^2 V / dx^2) phi`` (``g = dV/dx``,
    ``P = kv (V/V0 - 1)`` the long-term pressure; no ``kv1, kv2`` for an elastic term).

    Returns (q [N m], (N, 3) dq/dx [N], (P,) dq/dp at fixed x in the layout of
    :func:`parameter_layout`).

    One compiled pass over the connectors and one over the tets (:mod:`particle.body_kernels`;
    the loaded modes' rows call this thousands of times per calibration), the sums over them
    numpy's; :func:`incremental_form_numpy` is its twin.
    """
    refuse_nodal(model, "the whole-body incremental tangent (particle.body)")
    p = model.params
    x = np.ascontiguousarray(x, dtype=np.float64)
    field = np.ascontiguousarray(field, dtype=np.float64)
    e = model.n_connectors
    grad = np.zeros_like(x)
    q_connectors, connector_explicit = np.empty(e), np.empty((4, e))
    body_kernels.connector_form(x, field, model.edges, model.rest_lengths, p.K0, p.a, p.b,
                                p.k1, p.k2, q_connectors, grad, connector_explicit)
    layout = parameter_layout(e, model.n_tets if p.kv is not None else 0, p.has_volume_arms)
    explicit = np.zeros(max(s_.stop for s_ in layout.values()))
    explicit[layout["K0"]], explicit[layout["a"]], explicit[layout["b"]] = connector_explicit[:3]
    explicit[layout["k1"]] = explicit[layout["k2"]] = connector_explicit[3]
    q = float(np.sum(q_connectors))
    if p.kv is None:
        return q, grad, explicit
    q_tets, tet_explicit = np.empty(model.n_tets), np.empty((2, model.n_tets))
    stiffness = p.volume_instantaneous if p.has_volume_arms else p.kv
    body_kernels.tet_form(x, field, model.tets, model.rest_volumes, p.kv, stiffness, q_tets,
                          grad, tet_explicit)
    q += float(np.sum(q_tets))
    explicit[layout["kv"]] = tet_explicit[0]
    if p.has_volume_arms:
        explicit[layout["kv1"]] = explicit[layout["kv2"]] = tet_explicit[1]
    return q, grad, explicit


def incremental_form_numpy(model: Model, x: np.ndarray, field: np.ndarray
                           ) -> tuple[float, np.ndarray, np.ndarray]:
    """:func:`incremental_form` as numpy expressions (its twin: the compiled passes do these
    operations in this order)."""
    refuse_nodal(model, "the whole-body incremental tangent (particle.body)")
    p = model.params
    i, j = model.edges[:, 0], model.edges[:, 1]
    d = x[j] - x[i]
    length = np.linalg.norm(d, axis=1)
    u = d / length[:, None]
    L0 = model.rest_lengths
    eps = length / L0 - 1.0
    dx = length - L0
    w = field[j] - field[i]
    uw = np.einsum("ec,ec->e", u, w)
    ww = np.einsum("ec,ec->e", w, w)
    transverse = ww - uw ** 2
    tension = (p.K0 + p.a * eps + p.b * eps ** 2) * dx
    s_long = p.K0 + 2.0 * p.a * eps + 3.0 * p.b * eps ** 2
    s = s_long + p.k1 + p.k2
    q = float(np.sum(s * uw ** 2 + tension / length * transverse))
    d_uw = (w - uw[:, None] * u) / length[:, None]
    grad_d = ((uw ** 2 * (2.0 * p.a + 6.0 * p.b * eps) / L0)[:, None] * u
              + (2.0 * (s - tension / length) * uw)[:, None] * d_uw
              + (transverse * (s_long / length - tension / length ** 2))[:, None] * u)
    grad = np.zeros_like(x)
    np.add.at(grad, j, grad_d)
    np.add.at(grad, i, -grad_d)
    layout = parameter_layout(model.n_connectors, model.n_tets if p.kv is not None else 0,
                              p.has_volume_arms)
    explicit = np.zeros(max(s_.stop for s_ in layout.values()))
    per_length = transverse * dx / length
    explicit[layout["K0"]] = uw ** 2 + per_length
    explicit[layout["a"]] = 2.0 * eps * uw ** 2 + eps * per_length
    explicit[layout["b"]] = 3.0 * eps ** 2 * uw ** 2 + eps ** 2 * per_length
    explicit[layout["k1"]] = explicit[layout["k2"]] = uw ** 2
    if p.kv is None:
        return q, grad, explicit
    V0 = model.rest_volumes
    t = model.tets
    e = [x[t[:, a]] - x[t[:, 0]] for a in (1, 2, 3)]
    f = [field[t[:, a]] - field[t[:, 0]] for a in (1, 2, 3)]
    cross = np.cross
    dot = lambda a, b: np.einsum("tc,tc->t", a, b)  # noqa: E731
    volume = dot(e[0], cross(e[1], e[2])) / 6.0
    strain = volume / V0 - 1.0
    pressure = p.kv * strain
    g_phi = (dot(f[0], cross(e[1], e[2])) + dot(e[0], cross(f[1], e[2]))
             + dot(e[0], cross(e[1], f[2]))) / 6.0
    h_phi = (dot(f[0], cross(f[1], e[2])) + dot(f[0], cross(e[1], f[2]))
             + dot(e[0], cross(f[1], f[2]))) / 3.0
    stiffness = p.volume_instantaneous if p.has_volume_arms else p.kv
    q += float(np.sum(stiffness / V0 * g_phi ** 2 + pressure * h_phi))
    # derivatives with respect to the edge vectors e1, e2, e3 (module docstring: V trilinear)
    d_g = [(cross(f[1], e[2]) + cross(e[1], f[2])) / 6.0,
           (cross(e[2], f[0]) + cross(f[2], e[0])) / 6.0,
           (cross(f[0], e[1]) + cross(e[0], f[1])) / 6.0]
    d_h = [cross(f[1], f[2]) / 3.0, cross(f[2], f[0]) / 3.0, cross(f[0], f[1]) / 3.0]
    d_v = [cross(e[1], e[2]) / 6.0, cross(e[2], e[0]) / 6.0, cross(e[0], e[1]) / 6.0]
    for a in range(3):
        grad_e = ((2.0 * stiffness / V0 * g_phi)[:, None] * d_g[a]
                  + (p.kv / V0 * h_phi)[:, None] * d_v[a] + pressure[:, None] * d_h[a])
        np.add.at(grad, t[:, a + 1], grad_e)
        np.add.at(grad, t[:, 0], -grad_e)
    explicit[layout["kv"]] = g_phi ** 2 / V0 + strain * h_phi
    if p.has_volume_arms:
        explicit[layout["kv1"]] = explicit[layout["kv2"]] = g_phi ** 2 / V0
    return q, grad, explicit


def incremental_tangent(model: Model, pat: TangentPattern, x: np.ndarray) -> sp.csc_matrix:
    """(n, n) the tangent ``K_t`` of :func:`incremental_form` on the free dofs [N/m]."""
    refuse_nodal(model, "the whole-body incremental tangent (particle.body)")
    p = model.params
    forces, tension, *_ = net_forces(model, x, p, not p.is_linear, None, None,
                                     (np.zeros(model.n_tets), np.full(model.n_tets, np.inf)))
    e, t = model.n_connectors, model.n_tets
    volume = None
    if p.has_volume_arms:  # relaxed arms: no pressure, their instantaneous stiffness
        volume = VolumeArmStep(np.ones((t, 2)), np.column_stack([p.kv1, p.kv2]),
                               np.zeros((t, 2)), np.zeros(t))
    arms = ArmStep(np.ones((e, 2)), np.column_stack([p.k1, p.k2]), np.zeros((e, 2)),
                   np.zeros(e), volume)
    data = tangent_data(model, pat, x, tension, p, True, arms,
                        None if volume is None else np.zeros((t, 2)))
    return sp.csc_matrix((data, pat.indices, pat.indptr), shape=(pat.n_dofs, pat.n_dofs))


def loaded_mode_rows(model: Model, ops: RestOperators, acceleration: np.ndarray,
                     load_steps: int, frequencies: np.ndarray, shapes: np.ndarray, *,
                     jacobian: bool = True) -> ModeMatch:
    """Residual rows of the FE modes ``frequencies`` (M,) [Hz], ``shapes`` (M, N, 3) about
    the equilibrium under the weight ``acceleration`` against the model's modes about its
    own (:func:`incremental_form`), as :func:`mode_rows` for the rest state, with their
    Jacobian.

    Each row's derivative has an explicit part (the tangent's parameters at fixed
    positions) and one through the equilibrium's positions: for a row ``v^T dK_t/dp phi``,
    ``z^T df/dp`` with ``K_s z = d(v^T K_t phi)/dx`` (``K_s`` the static tangent, the
    gradient by polarisation of :func:`incremental_form`): an adjoint solve per row.

    ``jacobian`` False: the residuals alone (no adjoint solves).

    Raises:
        ConvergenceError: no equilibrium under the load, or the eigen-solve failed.
    """
    pat = ops.pattern
    x = weight_equilibrium(model, acceleration, load_steps)
    if not jacobian:
        return mode_rows(model, ops, "loaded", frequencies, shapes,
                         stiffness=incremental_tangent(model, pat, x), jacobian=False)
    forces, tension, *_ = net_forces(model, x, model.params, not model.params.is_linear, None,
                                     None, (np.zeros(model.n_tets),
                                            np.full(model.n_tets, np.inf)))
    static = ldl_factor(pat, tangent_data(model, pat, x, tension, model.params, True, None))
    load = load_forces(model, x, pat)
    K = incremental_tangent(model, pat, x)
    match = mode_rows(model, ops, "loaded", frequencies, shapes, stiffness=K)
    free = model.free_nodes

    def field(v: np.ndarray) -> np.ndarray:
        out = np.zeros((model.n_particles, 3))
        out[free] = v.reshape(-1, 3)
        return out

    parts = []
    for part, phi in zip(match.parts, match.modes):
        gradients, explicit = [], []
        for v in part.fields:  # the rows' virtual fields: v^T (dK/dp) phi, v = c phi or -y
            _, g_plus, e_plus = incremental_form(model, x, field(v + phi))  # polarisation
            _, g_minus, e_minus = incremental_form(model, x, field(v - phi))
            gradients.append(0.25 * (g_plus - g_minus)[free].ravel())
            explicit.append(0.25 * (e_plus - e_minus))
        adjoint = static.solve(np.array(gradients).T).T  # (R, n): K_s z = gradient
        parts.append(Rows(part.residual, np.ascontiguousarray(adjoint), load,
                          np.array(explicit)))
    return dataclasses.replace(match, parts=parts)


@dataclass(frozen=True, eq=False)
class BodyResponse:
    """The model's whole-body residuals against a :class:`BodyTarget`.

    Attributes:
        items: name of each data item (:attr:`BodyTarget.items`).
        parts: each item's residual rows with their Jacobian, in item order.
        load_errors: (L,) RMS displacement error of each load relative to its largest FE
            displacement [1].
        modes: modulus (rest state) or ``load <k>`` (about that load's equilibrium) -> its
            :class:`ModeMatch` (only with modes).
    """
    items: list[str]
    parts: list[Rows]
    load_errors: np.ndarray
    modes: dict[str, ModeMatch]

    @property
    def residual(self) -> np.ndarray:
        """(R,) every item's residuals, in order."""
        return np.concatenate([p.residual for p in self.parts]) if self.parts else np.zeros(0)

    def item_errors(self) -> np.ndarray:
        """(items,) the norm of each item's residual [1]."""
        return np.array([float(np.linalg.norm(p.residual)) for p in self.parts])

    def summary(self) -> dict:
        """Plain numbers for ``params.h5`` and the studies."""
        out = {"items": self.items, "item_errors": self.item_errors().tolist(),
               "load_errors": self.load_errors.tolist()}
        for modulus, match in self.modes.items():
            out[modulus] = {"frequency_errors": match.frequency_errors.tolist(),
                            "shape_errors": match.shape_errors.tolist(),
                            "mac": match.mac.tolist(), "partner": match.partner.tolist()}
        return out


def body_response(model: Model, target: BodyTarget, load_steps: int,
                  ops: RestOperators | None = None, *, jacobian: bool = True) -> BodyResponse:
    """Every whole-body residual of ``model`` against ``target`` with its Jacobian
    (``jacobian`` False: the residuals alone, the same numbers at a fraction of the cost:
    what a trial step's objective and the errors' record need).

    Raises:
        ConvergenceError: a load has no static equilibrium, or an eigen-solve failed.
    """
    ops = RestOperators.of(model) if ops is None else ops
    parts, load_errors, modes = [], [], {}
    for g, u_fe in zip(target.accelerations, target.displacement):
        rows = load_rows(model, g, u_fe, load_steps, ops.pattern, jacobian=jacobian)
        parts.append(rows)
        load_errors.append(float(np.linalg.norm(rows.residual)))
    for i, modulus in enumerate(BODY_MODULI):
        if target.frequencies.shape[1]:
            modes[modulus] = mode_rows(model, ops, modulus, target.frequencies[i],
                                       target.shapes[i], jacobian=jacobian)
            parts += modes[modulus].parts
    for k, g in enumerate(target.loaded_accelerations):
        modes[f"load {k}"] = loaded_mode_rows(model, ops, g, load_steps,
                                             target.loaded_frequencies[k],
                                             target.loaded_shapes[k], jacobian=jacobian)
        parts += modes[f"load {k}"].parts
    if target.free_frequencies.shape[1]:
        free = unsupported_model(model)
        free_ops = ops.unsupported if ops.unsupported is not None else RestOperators.of(free)
        for i, modulus in enumerate(BODY_MODULI):
            modes[f"free {modulus}"] = mode_rows(free, free_ops, modulus,
                                                 target.free_frequencies[i],
                                                 target.free_shapes[i], jacobian=jacobian,
                                                 free_free=True)
            parts += modes[f"free {modulus}"].parts
    return BodyResponse(target.items, parts, np.array(load_errors), modes)
