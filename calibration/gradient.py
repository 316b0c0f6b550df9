"""Gradient calibration of every connector (``calibration.method = "gradient"``).

Starting from the paper's global fit (:mod:`calibration.global_fit`), all seven
parameters of every connector are fitted at once to the indentation and
relaxation curves of the calibration points by a regularised Levenberg-Marquardt
iteration with the exact Jacobian of :mod:`particle.sensitivity`.

* **Coordinates** (:class:`Coordinates`), O(1) per relative change and feasible
  by construction where they can be: ``theta = (log K0, alpha s, beta s^2,
  log k1, log tau1, log k2, log tau2)`` per connector (``a = alpha K0``, ``b =
  beta K0``, ``b_i = tau_i k_i``, ``s`` the experiments' strain scale), the paper's
  global coordinates made per connector; with the volume term ``log kv`` per tet, and
  when it relaxes ``log kv1, log kv2`` per tet (their times the global fit's).
* **Residuals**: per point and experiment ``(F_sim - F_ref) / (max|F_ref| sqrt(S))``,
  so a point's squared residual norm is its squared relative RMS error (the
  number every report quotes), summed over both experiments. With
  ``calibration.force_components = "vector"`` the residuals are the force vector's three
  components, scaled alike (the normal curve's maximum): the bonded indenter's
  tangential reaction is data the FE reference has and the normal curves leave out.
* **Regulariser** ``(lambda / E) sum_q (theta_q - theta_glob_q)^T (L + rho I)
  (theta_q - theta_glob_q)`` over the seven coordinates q: ``L`` the graph
  Laplacian of the connectors that share a particle (each pair's squared
  difference), normalised by the mean number of such neighbours, i.e. a
  smoothness penalty between connectors sharing a particle; ``rho I`` a prior
  towards the global fit (``calibration.prior_ratio``, default :data:`PRIOR_RATIO`).
  With per-tet kv the same over the tets sharing a face (for each of ``log kv`` and, with
  a viscoelastic volume term, ``log kv1, log kv2``), and optionally a split prior
  (``calibration.split_prior``) between each connector's log K0 and its tets' log kv
  (:class:`~calibration.gradient_solver.Regulariser`).
* **lambda by k-fold cross-validation over the calibration points only**
  (:func:`cross_validate`; held-out points are never used): on the Gauss-Newton
  linearisation at the global fit, each fold's points are predicted by the step
  fitted to the other points, for every lambda of :data:`WEIGHT_GRID`; the
  lambda with the smallest predicted fold error wins (the linear model is exact
  for small changes and costs one Jacobian; the fit itself is nonlinear). A
  second round repeats the cross-validation on the linearisation at the first
  round's fit (:data:`CV_ROUNDS`) and refits from there if it picks another lambda
  (or the same one while the last fit stopped at its iteration budget).
* **Valid where it is used**: every spring's tangent stiffness ``K0 + 2 a eps
  + 3 b eps^2`` must stay >= ``calibration.stiffness_floor`` x the global K0 on
  its connector's strain range (:class:`Validity`): the experiments' range
  united with the range of the gravity release the FE static sag implies
  (:func:`particle.stability.strain_range_for_release` of the FE sag with
  ``particle.strain_margin``). A step that violates it is rejected like one that
  raises the cost; a hinge penalty keeps springs above twice the floor before
  they reach it.
* **Step**: ``(J^T J + A) delta = -grad`` with the sparse ``A`` = regulariser (+ hinge) +
  ``damping x A1``, solved by the Woodbury identity (J has as many rows as
  curve samples, far fewer than parameters; each point's rows projected on
  their :data:`ROWS_KEPT` leading singular directions, :func:`compress`); the
  damping is adapted by the gain ratio and a step is accepted on the exact
  objective. One Jacobian per accepted step; the points are spread over the
  calibration pool's workers.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import scipy.sparse as sp

from calibration.body import BodyData, BodyRows
from forcecal.scene import BODY_DATA_CHOICES
from calibration.gradient_solver import (BODY_WEIGHT_GRID, N_COORDS, PRIOR_RATIO, ROWS_KEPT,
                                         SHAPE_SMOOTHNESS, WEIGHT_GRID, Linearisation, LMState,
                                         Regulariser, compress, cross_validate, folds_of,
                                         levenberg_marquardt, linearise)
from calibration.parametrisation import GlobalParams, StrainRange, check_spring_range
from calibration.pool import Experiments, Pool, PointWorker, in_point_order
from forcecal.errors import ParameterError
from particle.evaluators import force_components
from particle.model import params_for
from particle.body import parameter_layout
from particle.params import PARAM_NAMES, VOLUME_ARM_NAMES, ConnectorParams
from particle.volume import tet_edge_connectors

log = logging.getLogger(__name__)

#: cross-validation rounds: the first on the linearisation at the global fit, the next at the
#: previous round's fit (where the linear model is closer to the fitted curves)
CV_ROUNDS = 2
HINGE_FACTOR = 2.0  # the hinge pushes springs back above this multiple of the floor
HINGE_WEIGHT = 1.0
HINGE_STRAINS = 5  # strains per connector where the hinge looks (the hard check is exact)


def gradient_backend(experiments: Experiments, points: np.ndarray, params: ConnectorParams):
    """Pool backend: the particle evaluators with adjoint Jacobians
    (:mod:`particle.sensitivity`)."""
    from particle.model import build_model
    from particle.sensitivity import sensitivity_evaluators

    p = experiments.problem
    model = build_model(p, experiments.density, params,
                        volume_element=experiments.volume_element)
    return sensitivity_evaluators(model, p.test_points[points], p.normals[points],
                                  experiments.depths, experiments.times,
                                  experiments.relaxation_depths, experiments.strain_range,
                                  footprints=experiments.held(points))


def point_residuals(worker: PointWorker, params: ConnectorParams, data: "Data",
                    points: Sequence[int]) -> np.ndarray:
    """Call run on a worker: residuals (P' R,) of owned ``points`` (global indices), every
    experiment of ``data`` in one call."""
    if data.directions is None:
        curves = {kind: worker.curves(kind, params, points) for kind in data.kinds}
    else:
        curves = {kind: data.components(worker.force_vectors(kind, params, points))
                  for kind in data.kinds}
    return data.residuals(curves, np.asarray(points))


def point_rows(worker: PointWorker, params: ConnectorParams, coords: "Coordinates",
               data: "Data", keep: int, points: Sequence[int]
               ) -> tuple[np.ndarray, np.ndarray, float]:
    """Call run on a worker: the compressed Gauss-Newton rows of owned ``points`` (global
    indices), every experiment of ``data``: residuals (P' k,), their coordinate Jacobian
    (P' k, size) and the squared residual the compression leaves out (:func:`compress`).

    Done where the curves are: a point's rows are compressed on their own, so the
    workers ship k rows per point instead of every sample, and the chain rule and
    the compression run in parallel.
    """
    local = [worker._local[int(p)] for p in points]
    worker.evaluations += len(local) * len(data.kinds)
    sens = {kind: worker.evaluators[kind].jacobian(params, local, data.directions)
            for kind in data.kinds}
    points = np.asarray(points)
    n_rows = data.rows(points[:1])
    r = data.residuals({kind: s.forces for kind, s in sens.items()}, points)
    # point by point: one point's coordinate Jacobian (rows, size) is a few MB and stays in
    # cache through the chain rule, the weights and the compression (all points at once:
    # ~80 MB per temporary on the liver punch, 0.4 s more per linearisation)
    rows, jac, left_out = [], [], 0.0
    for j in range(len(points)):
        jacs = {kind: coords.chain(s.connectors[j], None if s.kv is None else s.kv[j], params,
                                   None if s.volume_arms is None else s.volume_arms[j])[None]
                for kind, s in sens.items()}
        r_j, J_j, left = compress(r[j * n_rows:(j + 1) * n_rows],
                                  data.jacobian(jacs, points[j:j + 1]), n_rows, keep)
        rows.append(r_j)
        jac.append(J_j)
        left_out += left
    return np.concatenate(rows), np.concatenate(jac), left_out


@dataclass(frozen=True, eq=False)
class Coordinates:
    """Per-connector (and per-tet) optimiser coordinates <-> parameters (module docstring).

    ``theta`` is flat: seven blocks of E connector coordinates ``(log K0, alpha s,
    beta s^2, log k1, log tau1, log k2, log tau2)``, then ``log kv`` of the T tets
    when each tet's kv is fitted (T = 0 otherwise), then, when the volume term relaxes,
    ``log kv1`` and ``log kv2`` of the T tets (their relaxation times fixed: the global
    fit's, the springs' global ``tau1, tau2``; :mod:`calibration.parametrisation` says why).

    Attributes:
        scale: strain scale s of the experiments [1].
        n_connectors: E.
        n_tets: T, 0 without the volume term or with a kv that is not fitted.
        fixed_volume: the volume term's fields of :class:`ConnectorParams` (``kv`` and, if it
            relaxes, ``kv1, bv1, kv2, bv2``; (1,) or (T,) each) that every parameter set
            carries when ``n_tets`` is 0 with the volume term on
            (``calibration.kv_per_tet = false``); None otherwise.
        volume_tau: (T, 2) the volume arms' relaxation times [s] when their stiffnesses are
            fitted per tet (``n_tets`` > 0), None for an elastic volume term.
    """
    scale: float
    n_connectors: int
    n_tets: int = 0
    fixed_volume: dict[str, np.ndarray] | None = None
    volume_tau: np.ndarray | None = None

    @property
    def tet_blocks(self) -> int:
        """Blocks of T per-tet coordinates: log kv, and log kv1, log kv2 with the arms."""
        return (1 + (2 if self.volume_tau is not None else 0)) if self.n_tets else 0

    @property
    def size(self) -> int:
        return N_COORDS * self.n_connectors + self.tet_blocks * self.n_tets

    def block(self, theta: np.ndarray, q: int) -> np.ndarray:
        """(E,) coordinate q of every connector."""
        return theta[q * self.n_connectors:(q + 1) * self.n_connectors]

    def tet_block(self, theta: np.ndarray, q: int) -> np.ndarray:
        """(T,) per-tet coordinate q (0: log kv, 1, 2: log kv1, log kv2)."""
        first = N_COORDS * self.n_connectors + q * self.n_tets
        return theta[first:first + self.n_tets]

    def theta_of(self, params: ConnectorParams) -> np.ndarray:
        """(size,) coordinates of ``params`` (with kv iff ``n_tets``, and the volume arms'
        stiffnesses iff ``volume_tau``)."""
        s, p = self.scale, params
        blocks = [np.log(p.K0), p.a / p.K0 * s, p.b / p.K0 * s * s, np.log(p.k1),
                  np.log(p.tau1), np.log(p.k2), np.log(p.tau2)]
        if self.n_tets:
            blocks.append(np.log(p.kv))
        if self.tet_blocks == 3:
            blocks += [np.log(p.kv1), np.log(p.kv2)]
        return np.concatenate(blocks).astype(float)

    def params(self, theta: np.ndarray) -> ConnectorParams:
        s, b = self.scale, lambda q: self.block(theta, q)  # noqa: E731
        K0 = np.exp(b(0))
        k1, k2 = np.exp(b(3)), np.exp(b(5))
        if not self.n_tets:
            volume = self.fixed_volume or {}
        elif self.tet_blocks == 1:
            volume = {"kv": np.exp(self.tet_block(theta, 0))}
        else:
            kv1, kv2 = np.exp(self.tet_block(theta, 1)), np.exp(self.tet_block(theta, 2))
            volume = {"kv": np.exp(self.tet_block(theta, 0)), "kv1": kv1,
                      "bv1": self.volume_tau[:, 0] * kv1, "kv2": kv2,
                      "bv2": self.volume_tau[:, 1] * kv2}
        return ConnectorParams(K0=K0, a=b(1) / s * K0, b=b(2) / (s * s) * K0, k1=k1,
                               b1=np.exp(b(4)) * k1, k2=k2, b2=np.exp(b(6)) * k2, **volume)

    def chain(self, jac: np.ndarray, jac_kv: np.ndarray | None,
              params: ConnectorParams, jac_arms: np.ndarray | None = None) -> np.ndarray:
        """(..., size) derivatives with respect to the coordinates, from those (..., 7, E)
        with respect to ``K0, a, b, k1, b1, k2, b2``, (..., T) to kv and (..., 4, T) to the
        volume arms' ``kv1, bv1, kv2, bv2`` (with ``volume_tau``)."""
        s, p = self.scale, params
        out = np.empty(jac.shape[:-2] + (N_COORDS, jac.shape[-1]))
        out[..., 0, :] = jac[..., 0, :] * p.K0 + jac[..., 1, :] * p.a + jac[..., 2, :] * p.b
        out[..., 1, :] = jac[..., 1, :] * (p.K0 / s)
        out[..., 2, :] = jac[..., 2, :] * (p.K0 / (s * s))
        out[..., 3, :] = jac[..., 3, :] * p.k1 + jac[..., 4, :] * p.b1
        out[..., 4, :] = jac[..., 4, :] * p.b1
        out[..., 5, :] = jac[..., 5, :] * p.k2 + jac[..., 6, :] * p.b2
        out[..., 6, :] = jac[..., 6, :] * p.b2
        out = out.reshape(jac.shape[:-2] + (-1,))
        if self.n_tets:
            out = np.concatenate([out, jac_kv * p.kv], axis=-1)
        if self.tet_blocks == 3:  # log kv_i at fixed tau_i: kv_i d/dkv_i + bv_i d/dbv_i
            out = np.concatenate([out, jac_arms[..., 0, :] * p.kv1 + jac_arms[..., 1, :] * p.bv1,
                                  jac_arms[..., 2, :] * p.kv2 + jac_arms[..., 3, :] * p.bv2],
                                 axis=-1)
        return out

    def chain_matrix(self, params: ConnectorParams, n_tets: int) -> sp.csr_matrix:
        """(P, size) :meth:`chain` as a sparse matrix, from the parameter layout of
        :func:`particle.body.parameter_layout` (``n_tets`` the model's tets, for the layout
        of a volume term whose kv is not a coordinate: its rows are zero)."""
        e = self.n_connectors
        t = n_tets if params.kv is not None else 0
        layout = parameter_layout(e, t, params.has_volume_arms)
        n_t = self.n_tets
        connector_blocks = [(q * e, e) for q in range(N_COORDS)]
        tet_blocks = [(N_COORDS * e + q * n_t, n_t) for q in range(self.tet_blocks)]
        rows, cols, vals = [], [], []
        for name, where in layout.items():
            jac, jac_kv = np.zeros((1, N_COORDS, e)), np.zeros((1, n_t))
            jac_arms = np.zeros((1, 4, n_t))
            if name in PARAM_NAMES:
                jac[0, PARAM_NAMES.index(name)] = 1.0
            elif not n_t:
                continue  # a volume term that is not fitted
            elif name == "kv":
                jac_kv[0] = 1.0
            else:
                jac_arms[0, VOLUME_ARM_NAMES.index(name)] = 1.0
            out = self.chain(jac, jac_kv, params, jac_arms)[0]
            for start, width in connector_blocks if name in PARAM_NAMES else tet_blocks:
                coefficient = out[start:start + width]
                nonzero = np.flatnonzero(coefficient)
                rows.append(where.start + nonzero)
                cols.append(start + nonzero)
                vals.append(coefficient[nonzero])
        size = max(s.stop for s in layout.values())
        return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(size, self.size))


def shared_laplacian(members: np.ndarray, n_particles: int, shared: int) -> sp.csc_matrix:
    """(M, M) Laplacian of "shares at least ``shared`` particles" between members (M, k)
    (connectors: 1 particle, tets: a face = 3), divided by the mean number of neighbours.

    ``x^T L x = sum over neighbour pairs (x_e - x_f)^2 / mean degree``.
    """
    m, k = members.shape
    inc = sp.csr_matrix((np.ones(m * k), (np.repeat(np.arange(m), k), members.ravel())),
                        shape=(m, n_particles))
    adj = (inc @ inc.T).tocsr()
    adj.setdiag(0.0)
    adj.data[:] = np.where(adj.data >= shared, 1.0, 0.0)
    adj.eliminate_zeros()
    degree = np.asarray(adj.sum(axis=1)).ravel()
    lap = sp.diags(degree) - adj
    return (lap / max(degree.mean(), 1.0)).tocsc()


def neighbour_laplacian(edges: np.ndarray, n_particles: int) -> sp.csc_matrix:
    """(E, E) :func:`shared_laplacian` of connectors sharing a particle."""
    return shared_laplacian(edges, n_particles, 1)


@dataclass(frozen=True, eq=False)
class Validity:
    """Where each spring must stay stiff: per-connector strain range and stiffness floor.

    Attributes:
        low, high: (E,) float64 strain range of each connector [1].
        floor: smallest allowed spring tangent stiffness [N/m]: one for all, or (E,) per
            connector (a global fit with a shape, :func:`calibration.parametrisation.global_shape`).
        K0_global: the global fit's K0 [N/m] (hinge scale).
        scale: strain scale of the coordinates [1].
    """
    low: np.ndarray
    high: np.ndarray
    floor: float | np.ndarray
    K0_global: float
    scale: float

    def check(self, params: ConnectorParams, edges: np.ndarray | None = None) -> None:
        """Raise :class:`ParameterError` naming the first spring below the floor, or arms
        out of order."""
        check_spring_range(params, self.low, self.high, self.floor,
                           "on its strain range (experiments and gravity)")
        order = np.nonzero(~(params.tau1 < params.tau2))[0]
        if len(order):
            raise ParameterError(f"connector {int(order[0])}: tau1 >= tau2 ({len(order)} "
                                 "connectors); the arms must stay ordered")

    def hinge(self, theta: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
        """Hinge residuals (E*H,) and their sparse Jacobian (E*H, size) in the coordinates."""
        n = len(self.low)
        t0, t1, t2 = theta[:n], theta[n:2 * n], theta[2 * n:3 * n]
        frac = np.linspace(0.0, 1.0, HINGE_STRAINS)
        eps = self.low[:, None] + frac[None, :] * (self.high - self.low)[:, None]  # (E, H)
        s = self.scale
        K0 = np.exp(t0)[:, None]
        q = 1.0 + 2.0 * t1[:, None] * eps / s + 3.0 * t2[:, None] * (eps / s) ** 2
        tangent = K0 * q / self.K0_global
        floor = np.broadcast_to(np.asarray(self.floor, dtype=float), (n,))[:, None]
        target = HINGE_FACTOR * floor / self.K0_global
        active = tangent < target
        res = HINGE_WEIGHT * np.where(active, target - tangent, 0.0)
        w = -HINGE_WEIGHT * active * K0 / self.K0_global
        rows = np.arange(n * HINGE_STRAINS).reshape(n, HINGE_STRAINS)
        e = np.repeat(np.arange(n)[:, None], HINGE_STRAINS, axis=1)
        cols = np.concatenate([(0 * n + e).ravel(), (1 * n + e).ravel(), (2 * n + e).ravel()])
        vals = np.concatenate([(w * q).ravel(), (w * 2.0 * eps / s).ravel(),
                               (w * 3.0 * (eps / s) ** 2).ravel()])
        jac = sp.csr_matrix((vals, (np.tile(rows.ravel(), 3), cols)),
                            shape=(n * HINGE_STRAINS, len(theta)))
        return res.ravel(), jac


@dataclass(frozen=True, eq=False)
class Data:
    """The calibration curves and how residuals are scaled.

    Attributes:
        reference: experiment -> (Pc, R) reference curves of the calibration points [N]:
            the normal force (R = S samples), or with ``directions`` its components along
            each (R = D S, direction-major: :meth:`components`).
        weight: experiment -> (Pc,) 1 / (max|F_ref . n| sqrt(S)) per point [1/N]: a point's
            squared residual norm is its squared relative RMS error (of the force vector's
            with ``directions``, relative to the normal curve's maximum).
        directions: (D, 3) the force components fitted (``calibration.force_components =
            "vector"``: x, y, z), None: the normal force.
    """
    reference: dict[str, np.ndarray]
    weight: dict[str, np.ndarray]
    directions: np.ndarray | None = None

    @classmethod
    def of(cls, reference: dict[str, np.ndarray],
           vectors: dict[str, np.ndarray] | None = None) -> "Data":
        """From experiment -> (Pc, S) normal curves ``reference``, and (Pc, S, 3) force
        vectors ``vectors`` to fit the components of instead (None: the normal curves)."""
        weight = {k: 1.0 / (np.max(np.abs(v), axis=1) * np.sqrt(v.shape[1]))
                  for k, v in reference.items()}
        if vectors is None:
            return cls(reference, weight)
        data = cls(reference, weight, np.eye(3))
        return dataclasses.replace(data, reference={k: data.components(vectors[k])
                                                    for k in reference})

    def components(self, vectors: np.ndarray) -> np.ndarray:
        """(P', D S) the components along :attr:`directions` of (P', S, 3) force vectors,
        direction-major (the order of :meth:`particle.sensitivity._Adjoint.jacobian`)."""
        return force_components(vectors, self.directions)

    @property
    def kinds(self) -> tuple[str, ...]:
        return tuple(self.reference)

    def rows(self, points: np.ndarray) -> int:
        return len(points) * sum(v.shape[1] for v in self.reference.values())

    def residuals(self, curves: dict[str, np.ndarray], points: np.ndarray) -> np.ndarray:
        """(rows,) residuals of ``points``: point-major, experiments in order, samples."""
        parts = [(curves[k] - self.reference[k][points]) * self.weight[k][points, None]
                 for k in self.kinds]
        return np.concatenate(parts, axis=1).ravel()

    def jacobian(self, jacs: dict[str, np.ndarray], points: np.ndarray) -> np.ndarray:
        """(rows, size) from per-experiment (P', S, size) coordinate Jacobians."""
        parts = [jacs[k].reshape(len(points), jacs[k].shape[1], -1)
                 * self.weight[k][points, None, None] for k in self.kinds]
        return np.concatenate(parts, axis=1).reshape(self.rows(points), -1)


class Evaluator:
    """Residuals and Jacobians of the calibration points through the pool, and of the
    whole-body data (``body``, evaluated here) weighted by ``sqrt(body_weight)``."""

    def __init__(self, pool: Pool, data: Data, coords: Coordinates,
                 body: BodyData | None = None, body_weight: float = 0.0):
        self.pool, self.data, self.coords = pool, data, coords
        self.body, self.body_weight = body, body_weight
        self.jacobians = 0

    @property
    def fits_body(self) -> bool:
        """Whether the whole-body data enter the objective (present, weight > 0)."""
        return self.body is not None and self.body_weight > 0

    def residuals(self, theta: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(rows,) residuals at ``theta`` (:func:`point_residuals` on each worker), then the
        weighted whole-body residuals (computed here while the workers compute theirs)."""
        params = self.coords.params(theta)
        body: list[np.ndarray] = []
        out, positions = self.pool.by_owner(
            point_residuals, points, params, self.data,
            meanwhile=(lambda: body.append(self.body.residuals(params))) if self.fits_body
            else None)
        surface = in_point_order(out, positions, (self.data.rows(points[:1]),)).ravel()
        if not self.fits_body:
            return surface
        return np.concatenate([surface, np.sqrt(self.body_weight) * body[0]])

    def linearise(self, theta: np.ndarray, points: np.ndarray, keep: int
                  ) -> tuple[np.ndarray, np.ndarray, float]:
        """Compressed rows at ``theta``: residuals, Jacobian (rows, size) and the squared
        residual left out [1] of the points (:func:`point_rows` on each worker, point-major
        in the order of ``points``), then the weighted whole-body rows (those of the fitted
        kinds: the others are only predicted by the cross-validation; none at weight 0)."""
        return self.linearise_groups(theta, points, keep, every=False).weighted(
            self.body_weight)

    def linearise_groups(self, theta: np.ndarray, points: np.ndarray, keep: int, *,
                         every: bool = True) -> "GroupedRows":
        """:meth:`linearise` with the whole-body rows unweighted (whatever the weight), and
        each row's group: of every kind the model has a response to (what the
        cross-validation predicts), or (``every`` False) only what :meth:`linearise` keeps."""
        params = self.coords.params(theta)
        with_body = self.body is not None and (every or self.fits_body)
        body: list[BodyRows] = []
        out, positions = self.pool.by_owner(
            point_rows, points, params, self.coords, self.data, keep,
            meanwhile=(lambda: body.append(self.body.rows(
                params, self.coords.chain_matrix(params, self.body.model.n_tets), keep,
                every=every))) if with_body else None)  # while the workers compute theirs
        kept = min(keep, self.data.rows(points[:1]))
        rows = in_point_order([o[0] for o in out], positions, (kept,)).ravel()
        jac = in_point_order([o[1] for o in out], positions, (kept, self.coords.size))
        jac = jac.reshape(len(points) * kept, -1)
        left = float(sum(o[2] for o in out))
        groups = np.repeat(np.asarray(points), kept)
        self.jacobians += 1
        if not with_body:
            return GroupedRows(rows, jac, left, 0.0, groups, np.ones(len(rows), bool))
        b = body[0]
        return GroupedRows(np.concatenate([rows, b.residual]), np.vstack([jac, b.jacobian]),
                           left, b.left_out, np.concatenate([groups, -1 - b.item]),
                           np.concatenate([np.ones(len(rows), bool), b.fitted]),
                           b.left_out_every)


@dataclass(frozen=True, eq=False)
class GroupedRows:
    """Compressed data rows of the points and the whole-body items, the latter unweighted.

    Attributes:
        r: (rows,) residuals; J: (rows, size) their Jacobian.
        left: squared residual the points' compression left out [1].
        body_left: the same of the whole-body items (unweighted) [1].
        groups: (rows,) each row's calibration point (>= 0), or ``-1 - item`` for a
            whole-body item's (:func:`calibration.gradient_solver.cross_validate`).
        fitted: (rows,) False for the rows of whole-body items of kinds the fit does not use
            (computed for the cross-validation's report only).
        body_left_every: :attr:`body_left` of every item's rows, fitted or not [1].
    """
    r: np.ndarray
    J: np.ndarray
    left: float
    body_left: float
    groups: np.ndarray
    fitted: np.ndarray
    body_left_every: float = 0.0

    @property
    def scored_left_out(self) -> float:
        """The squared residual the rows' compression leaves out of what the
        cross-validation scores (:func:`calibration.gradient_solver.cross_validate`): every
        point's once, each whole-body item's times points / items [1]. A step moves none of
        it (a point's or an item's rows are projected on its Jacobian's leading singular
        directions), so it is the same for every weight and every set of kinds, and adding
        it to a score gives the uncompressed rows' score: what compares two models, whose
        compressions leave out different residuals."""
        body = self.groups < 0
        items = len(np.unique(self.groups[body]))
        points = len(np.unique(self.groups[~body]))
        return self.left + (points / items * self.body_left_every if items else 0.0)

    def weighted(self, weight: float) -> tuple[np.ndarray, np.ndarray, float]:
        """(r, J, left) as the objective weighs them: the fitted whole-body rows times
        ``sqrt(weight)`` (none at weight 0), the others left out."""
        body = self.groups < 0
        keep = ~body | (self.fitted & (weight > 0))
        scale = np.where(body, np.sqrt(max(weight, 0.0)), 1.0)[keep]
        left = self.left + (weight * self.body_left if weight > 0 else 0.0)
        return self.r[keep] * scale, self.J[keep] * scale[:, None], left


@dataclass(frozen=True, eq=False)
class GradientResult:
    """Outcome of :func:`fit_gradient`.

    Attributes:
        params: the fitted per-connector parameters.
        weight: the smoothness weight lambda of the final fit (chosen by cross-validation).
        grid, cv_costs: the weights tried and, per round, their predicted fold costs [1].
        weights: the weight chosen in each round.
        state: the final LM state (objective history [1]).
        jacobians: Jacobian evaluations (all calibration points each).
        coords: the fit's coordinates; theta_start: (coords.size,) where the fit started (the
            global fit).
        body_weight: the whole-body data's weight of the final fit (0: not fitted);
            body_weights: chosen in each round; body_grid: the body weights tried;
            body_cv: per round, the cross-validation's scores (len(body_grid), len(grid));
            body_choice: per round, :func:`body_candidates` (which kinds of whole-body data
            predict the calibration data best); body_data: the whole-body data of the final
            fit (more kinds than at the start when the fit came to carry them).
    """
    params: ConnectorParams
    weight: float
    grid: tuple[float, ...]
    cv_costs: np.ndarray
    state: LMState
    jacobians: int
    weights: tuple[float, ...]
    coords: Coordinates
    theta_start: np.ndarray
    body_weight: float = 0.0
    body_weights: tuple[float, ...] = ()
    body_grid: tuple[float, ...] = ()
    body_cv: list[np.ndarray] = dataclasses.field(default_factory=list)
    body_choice: list[dict] = dataclasses.field(default_factory=list)
    body_data: BodyData | None = None

    @property
    def body_candidates(self) -> dict:
        """Each round's :func:`body_candidates` (for ``params.h5``)."""
        return {f"round_{k + 1}": c for k, c in enumerate(self.body_choice) if c}

    def pulled_back(self, fraction: float) -> ConnectorParams:
        """The parameters a ``fraction`` of the way from the global fit to this fit, in the
        fit's coordinates (1: :attr:`params`; 0: the global fit)."""
        if fraction == 1.0:
            return self.params
        return self.coords.params(self.theta_start
                                  + fraction * (self.state.theta - self.theta_start))

    def summary(self) -> dict:
        out = {"weight": self.weight, "weights": list(self.weights), "grid": list(self.grid),
               "cv_costs": self.cv_costs.tolist(), "objective": self.state.history,
               "iterations": self.state.iteration, "jacobians": self.jacobians}
        if self.body_grid:
            out.update({"body_weight": self.body_weight, "body_weights": list(self.body_weights),
                        "body_grid": list(self.body_grid),
                        "body_cv": [np.asarray(t).tolist() for t in self.body_cv]})
        return out


#: the whole-body data sets whose cross-validation scores a fit reports: every value of
#: ``calibration.body_data``
BODY_CANDIDATES = {name: () if name == "none" else tuple(name.split("+"))
                   for name in BODY_DATA_CHOICES}


def body_candidates(lin: Linearisation, grouped: GroupedRows, reg: Regulariser,
                    folds: list[np.ndarray], grid: Sequence[float],
                    body_grid: Sequence[float], item_kinds: list[str]) -> dict:
    """For each set of whole-body kinds (:data:`BODY_CANDIDATES`), the cross-validation's best
    score when the fit uses that set: every group left out in turn (the point folds, each
    whole-body item of every kind) and predicted by the fit to the rest of the set
    (:func:`calibration.gradient_solver.cross_validate` with ``trained``), so an unused kind
    is predicted by fits that never saw it. The same groups for every set: the scores
    compare which data predict the calibration data best. ``{set: {"score", "weight",
    "body_weight", "left_out"}}``: ``left_out`` (:attr:`GroupedRows.scored_left_out`, the
    same for every set) added to a score compares it with another model's."""
    body = grouped.groups < 0
    kind_of_row = np.full(len(body), "", dtype=object)
    kind_of_row[body] = np.array(item_kinds, dtype=object)[-1 - grouped.groups[body]]
    out = {}
    for name, kinds in BODY_CANDIDATES.items():
        trained = ~body | np.isin(kind_of_row, kinds)
        weight, bw, table = cross_validate(lin, grouped.groups, reg, folds, grid,
                                           body_grid if kinds else (0.0,), trained)
        out[name] = {"score": float(table.min()), "weight": weight, "body_weight": bw,
                     "left_out": grouped.scored_left_out}
    log.info("whole-body data, cross-validation scores: %s", ", ".join(
        f"{k} {v['score']:.4g}" for k, v in out.items()))
    return out


def shape_smoothness_factors(shape_smoothness: float) -> np.ndarray:
    """(N_COORDS,) the regulariser's smoothness factor per connector coordinate:
    ``shape_smoothness`` on the spring shape's ``alpha s`` and ``beta s^2``
    (:class:`Coordinates`), 1 elsewhere."""
    scale = np.ones(N_COORDS)
    scale[[1, 2]] = shape_smoothness
    return scale


def fit_coordinates(start: ConnectorParams, scale: float, n_connectors: int,
                    n_tets: int | None, kv_per_tet: bool
                    ) -> tuple[ConnectorParams, Coordinates]:
    """The gradient fit's start parameters and coordinates from the global fit's ``start``
    (:class:`Coordinates`; ``scale`` the strain scale [1]): the connectors', and with the
    volume term (``n_tets`` its tets, None: no volume term) each tet's kv (and volume arm
    stiffnesses) when ``kv_per_tet``, the start then carrying one row per tet; else every
    tet keeps the start's volume parameters (``fixed_volume``)."""
    if n_tets is None:
        return start, Coordinates(scale, n_connectors)
    if not kv_per_tet:
        return start, Coordinates(scale, n_connectors, 0, fixed_volume={
            n: getattr(start, n) for n in ("kv",) + VOLUME_ARM_NAMES})
    # the global fit's kv and volume arms are one value for every tet ((1,), broadcast by
    # the Model): the gradient fit starts each tet's own from it
    start = params_for(start, n_connectors, n_tets)
    return start, Coordinates(scale, n_connectors, n_tets, volume_tau=(
        start.volume_arm_tau if start.has_volume_arms else None))


def fit_gradient(pool: Pool, glob: GlobalParams, strain: StrainRange,
                 reference: dict[str, np.ndarray], validity: Validity, edges: np.ndarray,
                 n_particles: int, *, folds: int, max_iterations: int,
                 tets: np.ndarray | None = None, kv0: float | None = None,
                 kv_per_tet: bool = True, prior_ratio: float = PRIOR_RATIO,
                 shape_smoothness: float = SHAPE_SMOOTHNESS,
                 split_prior: float = 0.0,
                 force_vectors: dict[str, np.ndarray] | None = None,
                 global_shape: np.ndarray | None = None,
                 body: BodyData | None = None, body_upgrade: BodyData | None = None,
                 body_weight: float | None = None,
                 body_candidates_report: bool = False,
                 checkpoint_get: Callable[[str], object],
                 checkpoint_put: Callable[[str, object], None],
                 grid: Sequence[float] = WEIGHT_GRID,
                 body_grid: Sequence[float] = BODY_WEIGHT_GRID) -> GradientResult:
    """CV for lambda, then the regularised LM fit (module docstring); checkpointed.

    ``reference``: experiment -> (Pc, S) curves of the calibration points (test points
    0..Pc-1 of the pool). ``tets`` (T, 4): fit a per-tet kv of the volume term too, starting
    from the global fit's kv (or ``kv0`` [Pa] if the global parameters carry none); None:
    springs only. ``kv_per_tet`` False: the connectors only, every tet keeping that kv.
    ``prior_ratio``: the regulariser's rho (:class:`calibration.gradient_solver.Regulariser`).
    ``shape_smoothness``: factor on the smoothness penalty of the spring shape coordinates
    (``alpha s``, ``beta s^2``) relative to the other coordinates' (not on the prior).
    ``split_prior``: weight of the regulariser's split prior (:class:`Regulariser`) between
    each connector's log K0 and its tets' log kv (per-tet kv only; 0: none).
    ``force_vectors``: experiment -> (Pc, S, 3) reference force vectors: fit their three
    components instead of the normal curves (``calibration.force_components = "vector"``,
    :class:`Data`); None: the normal curves.
    ``global_shape``: the global fit's (E,) per-connector factors
    (:func:`calibration.parametrisation.global_shape`), None if uniform; the fit starts from
    that and the regulariser measures every connector's departure from it.
    ``body``: whole-body data fitted jointly with the curves (:class:`BodyData`; the model
    must have an equilibrium under its loads at the global fit), each item's squared
    residual times ``body_weight``, or, when that is None, the weight of ``body_grid`` chosen
    with the smoothness weight by the cross-validation (:func:`cross_validate`);
    ``body_upgrade``: the whole-body data of more kinds than ``body`` (those the global fit
    has no response to), fitted from the first round whose start has a response to all;
    ``body_candidates_report``: also score every set of whole-body kinds
    (:func:`body_candidates`, in :attr:`GradientResult.body_choice`).
    """
    start_params = glob.connector_params(len(edges), global_shape)
    if tets is not None and start_params.kv is None:
        start_params = dataclasses.replace(start_params, kv=np.array([kv0], dtype=float))
    start_params, coords = fit_coordinates(start_params, strain.scale, len(edges),
                                           None if tets is None else len(tets), kv_per_tet)
    if not coords.n_tets:
        tets = None  # no kv coordinates, no kv smoothness
    theta0 = coords.theta_of(start_params)
    data = Data.of(reference, force_vectors)
    ev = Evaluator(pool, data, coords, body)
    body_grid = (() if body is None else tuple(body_grid) if body_weight is None
                 else (float(body_weight),))
    points = np.arange(len(next(iter(reference.values()))))
    reg = Regulariser(neighbour_laplacian(edges, n_particles), theta0,
                      None if tets is None else shared_laplacian(tets, n_particles, 3),
                      prior_ratio, shape_smoothness_factors(shape_smoothness),
                      None if tets is None or not split_prior > 0
                      else tet_edge_connectors(tets, edges), split_prior,
                      max(coords.tet_blocks, 1))
    theta, state, weights, cv_costs = theta0, None, [], []
    body_weights, body_cv, body_choice = [], [], []
    for k in range(CV_ROUNDS):
        saved_cv, saved = checkpoint_get(f"gradient_cv_{k}"), checkpoint_get(f"gradient_fit_{k}")
        start, upgraded = None, False
        if (k > 0 and body_upgrade is not None and ev.body is not body_upgrade
                and not any(body_upgrade.carried(coords.params(theta)).values())):
            log.info("gradient fit, round %d: the fit now has a response to every kind of "
                     "whole-body data: %s fitted", k + 1, "+".join(body_upgrade.kinds))
            ev.body, upgraded = body_upgrade, True
        if saved_cv is None:
            t = time.perf_counter()
            grouped = ev.linearise_groups(theta, points, ROWS_KEPT)
            lin = Linearisation.of(theta, grouped.r, grouped.J, reg, grouped.left)
            used = folds_of(len(points), folds)  # at most one fold per point
            weight, bw, table = cross_validate(lin, grouped.groups, reg, used, grid,
                                               body_grid or (0.0,), grouped.fitted)
            costs = table[list(body_grid).index(bw) if len(table) > 1 else 0]
            candidates = ({} if body is None or not body_candidates_report else
                          body_candidates(lin, grouped, reg, used, grid, body_grid,
                                          body.item_kinds))
            checkpoint_put(f"gradient_cv_{k}", {"weight": weight, "costs": costs.tolist(),
                                                "body_weight": bw, "table": table.tolist(),
                                                "candidates": candidates})
            log.info("gradient fit, round %d: smoothness weight %g%s by %d-fold "
                     "cross-validation (%.1f s)", k + 1, weight,
                     f", body weight {bw:g}" if body is not None else "", len(used),
                     time.perf_counter() - t)
            ev.body_weight = bw
            if body is not None:  # the rows as the objective weighs them
                r, J, left = grouped.weighted(bw)
                lin = Linearisation.of(theta, r, J, reg, left)
            start = linearise(ev, theta, points, reg, validity, lin)
        else:
            weight, costs = float(saved_cv["weight"]), np.asarray(saved_cv["costs"], dtype=float)
            bw, table = float(saved_cv["body_weight"]), np.asarray(saved_cv["table"], float)
            candidates = saved_cv["candidates"]
            ev.body_weight = bw
        weights.append(weight)
        cv_costs.append(costs)
        body_weights.append(bw)
        body_cv.append(table)
        body_choice.append(candidates)
        same = k > 0 and not upgraded and (weight, bw) == (weights[-2], body_weights[-2])
        if same and state.done:
            break  # the same weights again, and the last round's fit had converged for them
        state = levenberg_marquardt(
            ev, points, reg, weight, validity,
            None if saved is None else LMState.from_dict(saved), theta_start=theta,
            max_iterations=max_iterations, start=start,
            save=lambda s, k=k: checkpoint_put(f"gradient_fit_{k}", s.as_dict()))
        if same:
            break  # the same weights again: this round continued the last one's fit
        theta = state.theta
    return GradientResult(coords.params(state.theta), weights[-1], tuple(grid),
                          np.array(cv_costs), state, ev.jacobians, tuple(weights), coords,
                          theta0, body_weights[-1], tuple(body_weights), body_grid,
                          body_cv, body_choice, ev.body)
