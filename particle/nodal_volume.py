"""Nodal (one-ring averaged) volume term of the particle model, in the spirit of the FE's
average nodal pressure element (ANP, Bonet and Burton 1998).

The per-tet volume term (:mod:`particle.volume`) puts one volume constraint on every
tetrahedron, about three per particle; on coarse linear tets that locks the bending of a
nearly incompressible body (the FE shows the same: plain P1 sags 11.7 mm on the default
liver, ANP 19.9 mm, docs/fe-reference.md). The nodal term has one constraint per particle:
particle n owns a quarter of each of its tets,

    V0_n = sum_{t ∋ n} V0_t / 4,   V_n = sum_{t ∋ n} V_t / 4,   j_n = V_n / V0_n - 1,

with the energy ``E = sum_n kv_n / 2 V0_n j_n^2``. The parameters stay per tet
(``ConnectorParams.kv``, ``kv1, bv1, kv2, bv2``, (T,)), so the calibration's
parametrisation is the per-tet term's; a particle's coefficients are their volume-weighted
means over its tets, ``kv_n = sum_{t ∋ n} kv_t V0_t / 4 / V0_n`` (:func:`node_average`;
likewise the arms' ``kv_i`` and ``bv_i``). Hence:

* on a single tet, ``V0_n = V0/4``, ``j_n = j`` and ``kv_n = kv``: the per-tet term;
* under a uniform dilation every ``j_n`` equals every tet's ``j``, so ``E = sum_t kv_t/2 V0_t
  j^2``: the term adds exactly ``kv`` to the bulk modulus, as the per-tet one does
  (:func:`particle.volume.network_bulk_modulus`'s reading of kv holds for both).

**Forces.** ``dV_n/dp_a = sum_{t ∋ n} dV_t/dp_a / 4``, so ``-dE/dp_a = -sum_t Pbar_t
dV_t/dp_a`` with the tet pressure ``Pbar_t`` the mean of its four particles' pressures
``P_n = kv_n j_n (+ P_1,n + P_2,n)``: the per-tet force pass with an averaged pressure
(:func:`nodal_volume_forces_numpy`; the mean is taken as ``((P_0 + P_1) + (P_2 + P_3)) /
4``, exact for four equal pressures). **Arms.** ``P_i,n`` are Maxwell arms in the node's
volume strain ``j_n``, the per-tet arms' recursion
(:func:`particle.volume.volume_arm_pressures_numpy`) with the node's ``kv_i``, ``tau_i =
bv_i/kv_i`` (:func:`nodal_arm_recursion`); their state (``State.volume_arm`` (N, 2),
``volume_prev`` (N,)) is per particle.

**Tangent.** ``K = sum_n k_n / V0_n (dV_n/dx)(dV_n/dx)^T + sum_t Pbar_t d^2V_t/dx^2`` with
``k_n = kv_n (+ c_1,n + c_2,n)``, the arms' step coefficients: the rank-one parts couple a
particle's whole one-ring, so two particles are coupled when they share a neighbour (a
two-ring pattern, unlike the per-tet term's, which stays on the connectors'). Numpy:
:func:`nodal_volume_tangent_numpy`.

A model says which element it uses with ``Model.volume_element`` (``"tet"`` or
``"nodal"``, scene key ``particle.volume_element``); the rest volumes ``Model.node_volumes``
(N,) are computed with the model. A path that does not support the nodal term yet refuses
such a model (:func:`refuse_nodal`) instead of running the per-tet term in its place.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from forcecal.errors import ParameterError
from particle.volume import signed_volumes, volume_gradients_numpy, volume_hessian_numpy

#: the volume elements a model can use: one constraint per tet, or per particle
VOLUME_ELEMENTS = ("tet", "nodal")


def node_rest_volumes(tets: np.ndarray, rest_volumes: np.ndarray, n: int) -> np.ndarray:
    """(N,) ``V0_n = sum_{t ∋ n} V0_t / 4`` [m^3] (0 for a particle in no tet); with the tets'
    current volumes, their current ``V_n`` (:func:`node_volumes_at`)."""
    return np.bincount(np.asarray(tets).ravel(), np.repeat(np.asarray(rest_volumes) / 4.0, 4),
                       n)


def node_volumes_at(x: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(N,) ``V_n = sum_{t ∋ n} V_t / 4`` [m^3] at positions ``x`` (N, 3)."""
    return node_rest_volumes(tets, signed_volumes(x, tets), len(x))


def node_volume_strains(x: np.ndarray, tets: np.ndarray, node_volumes: np.ndarray
                        ) -> np.ndarray:
    """(N,) nodal volume strains ``j_n = V_n / V0_n - 1`` [1]."""
    return node_volumes_at(x, tets) / node_volumes - 1.0


def node_average(tets: np.ndarray, rest_volumes: np.ndarray, node_volumes: np.ndarray,
                 per_tet: np.ndarray) -> np.ndarray:
    """(N,) or (N, k): the volume-weighted mean ``sum_{t ∋ n} v_t V0_t / 4 / V0_n`` of the
    per-tet values ``per_tet`` (T,) or (T, k) over each particle's tets."""
    per_tet = np.asarray(per_tet, dtype=np.float64)
    weights = rest_volumes / 4.0
    if per_tet.ndim == 1:
        return np.bincount(tets.ravel(), np.repeat(per_tet * weights, 4),
                           len(node_volumes)) / node_volumes
    return np.column_stack([node_average(tets, rest_volumes, node_volumes, per_tet[:, k])
                            for k in range(per_tet.shape[1])])


@dataclass(frozen=True)
class NodalParams:
    """A model's per-particle volume coefficients (each :func:`node_average` of the per-tet
    ones): ``kv`` (N,) [Pa]; ``arm_stiffness`` (N, 2) [Pa] (kv1, kv2) and ``arm_tau`` (N, 2)
    [s] (bv_i/kv_i of the averaged bv_i, kv_i), None without arms."""
    kv: np.ndarray
    arm_stiffness: np.ndarray | None = None
    arm_tau: np.ndarray | None = None

    @property
    def instantaneous(self) -> np.ndarray:
        """(N,) ``kv + kv1 + kv2`` [Pa] (``kv`` without arms)."""
        return self.kv if self.arm_stiffness is None else self.kv + self.arm_stiffness.sum(1)


def nodal_params(model) -> NodalParams:
    """The :class:`NodalParams` of ``model`` (with the volume term on), read-only arrays."""
    from particle.params import frozen_copy
    p = model.params
    if p.kv is None:
        raise ParameterError("nodal volume coefficients of a model without the volume term "
                             "(ConnectorParams.kv is None)")

    def mean(values):
        return node_average(model.tets, model.rest_volumes, model.node_volumes, values)

    kv = frozen_copy(mean(p.kv), np.float64)
    if not p.has_volume_arms:
        return NodalParams(kv)
    stiffness = mean(p.volume_arm_stiffness)
    viscosity = mean(np.column_stack([p.bv1, p.bv2]))
    return NodalParams(kv, frozen_copy(stiffness, np.float64),
                       frozen_copy(viscosity / stiffness, np.float64))


def nodal_arm_recursion(nodal: NodalParams, dt: float, *, exact: bool = False
                        ) -> tuple[np.ndarray, np.ndarray]:
    """(r, c), each (N, 2), of the nodal arms' step ``P^t = r P^{t-1} + c (j^t - j^{t-1})``
    (``c`` [Pa]): the connectors' and tets' recursion
    (:func:`particle.params.maxwell_recursions`) with the particles' coefficients."""
    from particle.params import check_step, maxwell_recursions
    r, c = maxwell_recursions(nodal.arm_stiffness, nodal.arm_tau,
                              np.array([check_step(dt)]), exact=exact)
    return r[0], c[0]


def mean_tet_pressures(tets: np.ndarray, pressure: np.ndarray) -> np.ndarray:
    """(T,) each tet's mean ``((P_0 + P_1) + (P_2 + P_3)) / 4`` [Pa] of its particles'
    pressures ``pressure`` (N,) (pairwise: four equal pressures give that pressure exactly)."""
    p = pressure[tets]
    return ((p[:, 0] + p[:, 1]) + (p[:, 2] + p[:, 3])) * 0.25


def nodal_pressures(x: np.ndarray, tets: np.ndarray, node_volumes: np.ndarray,
                    kv: np.ndarray, arm_pressure: np.ndarray | None = None) -> np.ndarray:
    """(N,) ``P_n = kv_n j_n (+ arm_pressure_n)`` [Pa]; ``arm_pressure`` (N,): the nodal
    arms' summed pressures at ``x`` (None: no arms)."""
    pressure = kv * node_volume_strains(x, tets, node_volumes)
    return pressure if arm_pressure is None else pressure + arm_pressure


def nodal_volume_forces_numpy(x: np.ndarray, tets: np.ndarray, node_volumes: np.ndarray,
                              kv: np.ndarray, arm_pressure: np.ndarray | None = None
                              ) -> np.ndarray:
    """(N, 3) forces [N] of the nodal term: ``f_a = -sum_t Pbar_t dV_t/dp_a``, ``Pbar_t``
    the mean of the tet's particles' pressures (:func:`nodal_pressures`); ``kv`` (N,) [Pa],
    ``arm_pressure`` (N,) [Pa] or None."""
    from particle.volume import pressure_forces_numpy
    pressure = nodal_pressures(x, tets, node_volumes, kv, arm_pressure)
    return pressure_forces_numpy(x, tets, mean_tet_pressures(tets, pressure))


def nodal_volume_energy(x: np.ndarray, tets: np.ndarray, node_volumes: np.ndarray,
                        kv: np.ndarray) -> float:
    """The elastic energy ``sum_n kv_n / 2 V0_n j_n^2`` [J] at positions ``x`` (N, 3)."""
    j = node_volume_strains(x, tets, node_volumes)
    return float(np.sum(0.5 * kv * node_volumes * j * j))


def node_volume_gradients(x: np.ndarray, tets: np.ndarray) -> sp.csr_matrix:
    """(N, 3N) ``dV_n/dx`` [m^2] (row n, column 3a + c): ``sum_{t ∋ n, a} dV_t/dp_a / 4``."""
    g = volume_gradients_numpy(x, tets) / 4.0  # (T, 4, 3)
    n_tets = len(tets)
    rows = np.broadcast_to(tets[:, :, None, None], (n_tets, 4, 4, 3))  # node slot, vertex, c
    cols = np.broadcast_to(3 * tets[:, None, :, None] + np.arange(3), (n_tets, 4, 4, 3))
    vals = np.broadcast_to(g[:, None, :, :], (n_tets, 4, 4, 3))
    n = len(x)
    return sp.csr_matrix((vals.ravel(), (rows.ravel(), cols.ravel())), shape=(n, 3 * n))


def nodal_volume_tangent_numpy(x: np.ndarray, tets: np.ndarray, node_volumes: np.ndarray,
                               kv: np.ndarray, arms: tuple[np.ndarray, np.ndarray] | None = None
                               ) -> sp.csr_matrix:
    """(3N, 3N) ``-d(forces)/dx`` [N/m] of the nodal term over every particle's dofs (3n +
    c): ``B^T diag(k_n / V0_n) B + sum_t Pbar_t d^2V_t/dx^2`` with ``B`` =
    :func:`node_volume_gradients`, ``k_n = kv_n (+ c_1,n + c_2,n)``; ``arms`` None (elastic,
    or the arms relaxed) or (the arms' step coefficients ``c_1 + c_2`` (N,) [Pa], their
    summed pressures at ``x`` (N,) [Pa]). The curvature blocks are
    :func:`particle.volume.volume_hessian_numpy`'s (d^2V from unit displacements), of the tets
    whose mean pressure is not exactly 0 (the others' blocks are 0: at rest, none)."""
    stiffness, arm_pressure = (kv, None) if arms is None else (kv + arms[0], arms[1])
    b = node_volume_gradients(x, tets)
    rank_one = (b.T @ sp.diags(stiffness / node_volumes) @ b).tocsr()
    mean = mean_tet_pressures(tets, nodal_pressures(x, tets, node_volumes, kv, arm_pressure))
    loaded = np.flatnonzero(mean)
    blocks = np.stack([volume_hessian_numpy(x, tets[t], 1.0, 0.0, 0.0, mean[t])
                       for t in loaded]) if len(loaded) else np.zeros((0, 12, 12))
    dofs = (3 * tets[loaded, :, None] + np.arange(3)).reshape(len(loaded), 12)
    rows = np.broadcast_to(dofs[:, :, None], blocks.shape)
    cols = np.broadcast_to(dofs[:, None, :], blocks.shape)
    n = 3 * len(x)
    curvature = sp.csr_matrix((blocks.ravel(), (rows.ravel(), cols.ravel())), shape=(n, n))
    return (rank_one + curvature).tocsr()


def element_strains(model, x: np.ndarray) -> np.ndarray:
    """The volume strains [1] of ``model``'s volume elements at ``x`` (N, 3): (T,) per tet,
    (N,) per particle for the nodal term (the strains its arms follow)."""
    if model.volume_element == "nodal":
        return node_volume_strains(x, model.tets, model.node_volumes)
    from particle.volume import volume_strains
    return volume_strains(x, model.tets, model.rest_volumes)


def element_arm_recursion(model, dt: float, *, exact: bool = False
                          ) -> tuple[np.ndarray, np.ndarray]:
    """(r, c) of ``model``'s volume arms, one row per volume element (its tets, or its
    particles for the nodal term: :func:`nodal_arm_recursion`)."""
    if model.volume_element == "nodal":
        return nodal_arm_recursion(nodal_params(model), dt, exact=exact)
    return model.params.volume_arm_recursion(dt, exact=exact)


def element_arm_recursions(model, dts: np.ndarray, *, exact: bool = False
                           ) -> tuple[np.ndarray, np.ndarray]:
    """(r, c), each (S, M, 2), of ``model``'s volume arms for S time steps ``dts`` [s], one
    row per volume element (:func:`element_arm_recursion` for many steps at once)."""
    from particle.params import maxwell_recursions, volume_arm_recursions
    if model.volume_element == "nodal":
        nodal = nodal_params(model)
        return maxwell_recursions(nodal.arm_stiffness, nodal.arm_tau, dts, exact=exact)
    return volume_arm_recursions(model.params, dts, exact=exact)


def element_coefficients(model, params=None) -> tuple[np.ndarray, np.ndarray]:
    """(rest volumes [m^3], kv [Pa]) of ``model``'s volume elements (volume term on) with
    the parameters ``params`` (None: the model's): the tets', or the particles' for the nodal
    term (the compiled passes' arguments; a (1,) kv broadcast as :meth:`Model.with_params`
    does)."""
    if params is not None:
        model = model.with_params(params)
    if model.volume_element == "nodal":
        return model.node_volumes, nodal_params(model).kv
    return model.rest_volumes, model.params.kv


def element_energy(model, x: np.ndarray) -> float:
    """The volume term's elastic energy [J] at ``x`` (N, 3), per tet or nodal."""
    from particle.volume import volume_energy
    if model.volume_element == "nodal":
        return nodal_volume_energy(x, model.tets, *element_coefficients(model))
    return volume_energy(x, model.tets, model.rest_volumes, model.params.kv)


def element_arm_energy(model, pressure: np.ndarray) -> float:
    """Energy [J] held by the volume arms' springs at the arm pressures ``pressure`` (M, 2)
    [Pa] of the model's volume elements (:func:`particle.volume.volume_arm_energy`)."""
    from particle.volume import volume_arm_energy
    if model.volume_element == "nodal":
        return volume_arm_energy(pressure, nodal_params(model).arm_stiffness, model.node_volumes)
    return volume_arm_energy(pressure, model.params.volume_arm_stiffness, model.rest_volumes)


def tet_moduli(model) -> np.ndarray:
    """(T,) a modulus [Pa] per tet whose per-tet tangent ``sum_t k_t/V0_t g_t g_t^T`` bounds
    the volume term's rank-one part from above: the instantaneous ``kv + kv1 + kv2`` per
    tet, or for the nodal term the mean of its particles' (the Cauchy-Schwarz bound of
    :func:`particle.volume_bounds._nodal_pressure_bound`)."""
    if model.volume_element == "nodal":
        return nodal_params(model).instantaneous[model.tets].mean(axis=1)
    return model.params.volume_instantaneous


def check_volume_element(value) -> str:
    """``value`` if it is one of :data:`VOLUME_ELEMENTS`, else :class:`ParameterError`."""
    if not (isinstance(value, str) and value in VOLUME_ELEMENTS):
        raise ParameterError(f"volume_element = {value!r}: one of {list(VOLUME_ELEMENTS)} (one "
                             "volume constraint per tet, or per particle over its one-ring)")
    return value


def is_nodal(model) -> bool:
    """True when ``model``'s volume term is on and nodal."""
    return model.params.kv is not None and model.volume_element == "nodal"


def refuse_nodal(model, what: str) -> None:
    """:class:`ParameterError` when ``model``'s volume term is nodal: ``what`` (a path of the
    particle model) does not support it yet, and must not run the per-tet term instead."""
    if is_nodal(model):
        raise ParameterError(f"{what} does not support the nodal volume element yet "
                             "(Model.volume_element = 'nodal', scene key "
                             "particle.volume_element); use volume_element = 'tet'")


__all__ = ["NodalParams", "VOLUME_ELEMENTS", "check_volume_element", "element_arm_energy",
           "element_arm_recursion", "element_arm_recursions", "element_coefficients",
           "element_energy", "element_strains", "is_nodal", "mean_tet_pressures",
           "nodal_arm_recursion", "nodal_params", "nodal_pressures", "nodal_volume_energy",
           "nodal_volume_forces_numpy", "nodal_volume_tangent_numpy", "node_average",
           "node_rest_volumes", "node_volume_gradients", "node_volume_strains", "node_volumes_at",
           "refuse_nodal", "tet_moduli"]
