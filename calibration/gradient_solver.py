"""The solver of the gradient fit (:mod:`calibration.gradient`): a regularised
Levenberg-Marquardt iteration on compressed Gauss-Newton rows, with the smoothness weight
chosen by k-fold cross-validation.

Separate from the fit's model side (coordinates, residuals, validity) because it
only needs residuals and Jacobians: :class:`Regulariser` (the smoothness metric),
:class:`Linearisation` (the Woodbury step and its prediction), :func:`compress`,
:func:`cross_validate`, :func:`levenberg_marquardt` and its checkpointed
:class:`LMState`. The maths is in :mod:`calibration.gradient`'s docstring.
"""

from __future__ import annotations

import functools
import itertools
import logging
from dataclasses import dataclass
from typing import Any, Callable, Protocol, Sequence

import numpy as np
import scipy.sparse as sp
from scipy.linalg import cho_factor, cho_solve
from scipy.sparse.linalg import splu

from calibration.optimize import INFEASIBLE
from forcecal.blas import blas_threads
from forcecal.scene import CalibrationSection

log = logging.getLogger(__name__)

#: coordinates per connector (:class:`calibration.gradient.Coordinates`)
N_COORDS = 7
#: prior weight relative to the smoothness weight (a mild pull towards the global fit that
#: fixes the level of each smooth field where the data say nothing): the scene default of
#: ``calibration.prior_ratio``
PRIOR_RATIO = CalibrationSection().prior_ratio
#: smoothness factor of the spring shape's coordinates (:class:`Regulariser` ``smoothness``):
#: the scene default of ``calibration.shape_smoothness``
SHAPE_SMOOTHNESS = CalibrationSection().shape_smoothness
#: smoothness weights lambda tried by cross-validation (data cost = sum of squared relative
#: RMS errors; lambda multiplies the mean squared neighbour difference per connector)
WEIGHT_GRID = tuple(10.0 ** np.arange(-4.0, 3.01, 0.5))


class LeastSquares(Protocol):
    """What the solver asks of the fit (:class:`calibration.gradient.Evaluator`)."""
    data: Any  # .rows(points): residual rows of ``points``
    coords: Any  # .params(theta): the connector parameters, for :class:`Bounds`

    def residuals(self, theta: np.ndarray, points: np.ndarray) -> np.ndarray: ...

    def linearise(self, theta: np.ndarray, points: np.ndarray, keep: int
                  ) -> tuple[np.ndarray, np.ndarray, float]: ...


class Bounds(Protocol):
    """Where the parameters are valid (:class:`calibration.gradient.Validity`)."""

    def check(self, params: Any) -> None: ...

    def hinge(self, theta: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]: ...


#: blocks of the regulariser's metric up to this size are inverted densely (8 MB per 1000^2)
DENSE_INVERSE_LIMIT = 5000
#: rows kept per calibration point in the Gauss-Newton model (:func:`compress`; its curves
#: have 50 samples on the default liver)
ROWS_KEPT = 12


def _metric_block(lap: sp.spmatrix, rho: float, smoothness: float = 1.0) -> sp.spmatrix:
    """One diagonal block of the metric A1: ``(s L + rho I) / n`` of an (n, n) Laplacian."""
    n = lap.shape[0]
    return (smoothness * lap + rho * sp.identity(n)) / n


@dataclass(frozen=True, eq=False)
class Regulariser:
    """``lambda (theta - theta0)^T A1 (theta - theta0)`` with the block-diagonal metric
    ``A1 = I_7 (x) (L + rho I)/E  (+)  (L_tets + rho I)/T`` (module docstring), plus, with
    a split prior, ``sigma S^T S / P``: one row ``e_{log K0 of c} - e_{log kv of t}`` per
    pair (connector c, tet t having c as an edge), P = 6 T pairs. That term penalises moving
    stiffness between a spring and its tets' kv (which surface curves pin only as a sum:
    docs/calibration.md, parameter recovery), not raising both together. It couples the K0 and kv
    blocks, so A1 is then inverted as one matrix.

    Attributes:
        laplacian: (E, E) connectors sharing a particle (:func:`neighbour_laplacian`).
        theta0: (size,) the start (the global fit), also the prior's centre.
        tet_laplacian: (T, T) tets sharing a face, or None without the volume term.
        prior_ratio: rho, the prior's weight relative to the smoothness weight [1].
        smoothness: (N_COORDS,) factor s_q on each connector coordinate's smoothness term,
            ``(s_q L + rho I)/E`` [1] (``calibration.shape_smoothness`` on the spring
            shape's two); None: every factor 1.
        tet_edges: (T, 6) connector id of each tet's edges
            (:func:`particle.volume.tet_edge_connectors`): the split prior's pairs, or None.
        split_prior: sigma, the split prior's weight relative to the smoothness weight
            (``calibration.split_prior``) [1]; 0: no split prior.
        tet_blocks: per-tet coordinate blocks, each with the tets' block ``(L_tets + rho
            I)/T``: 1 (log kv), 3 with the volume arms (log kv, log kv1, log kv2).
    """
    laplacian: sp.csc_matrix
    theta0: np.ndarray
    tet_laplacian: sp.csc_matrix | None = None
    prior_ratio: float = PRIOR_RATIO
    smoothness: np.ndarray | None = None
    tet_edges: np.ndarray | None = None
    split_prior: float = 0.0
    tet_blocks: int = 1

    @property
    def _split(self) -> bool:
        return (self.split_prior > 0 and self.tet_edges is not None
                and self.tet_laplacian is not None and len(self.tet_edges) > 0)

    def _split_term(self) -> sp.csc_matrix:
        """(size, size) ``sigma S^T S / P`` of the split prior."""
        e, t = self.laplacian.shape[0], self.tet_laplacian.shape[0]
        connector = np.asarray(self.tet_edges, dtype=np.int64).ravel()
        p = len(connector)
        tet = np.repeat(np.arange(t), 6)
        rows = np.repeat(np.arange(p), 2)
        cols = np.column_stack([connector, N_COORDS * e + tet]).ravel()
        vals = np.tile([1.0, -1.0], p)
        size = N_COORDS * e + self.tet_blocks * t
        S = sp.csr_matrix((vals, (rows, cols)), shape=(p, size))
        return (self.split_prior / p * (S.T @ S)).tocsc()

    @functools.cached_property
    def _smoothness(self) -> np.ndarray:
        factors = (np.ones(N_COORDS) if self.smoothness is None
                   else np.asarray(self.smoothness, dtype=float))
        if factors.shape != (N_COORDS,) or not np.all(factors > 0):
            raise ValueError(f"smoothness must be {N_COORDS} positive factors, "
                             f"got {self.smoothness!r}")
        return factors

    @functools.cached_property
    def metric(self) -> sp.csc_matrix:
        """(size, size) the penalty's metric A1 (also the LM damping metric)."""
        rho = self.prior_ratio
        blocks = [_metric_block(self.laplacian, rho, s) for s in self._smoothness]
        if self.tet_laplacian is not None:
            blocks += [_metric_block(self.tet_laplacian, rho)] * self.tet_blocks
        metric = sp.block_diag(blocks, format="csc")
        return (metric + self._split_term()).tocsc() if self._split else metric

    @functools.cached_property
    def _blocks(self) -> list[tuple[int, int, int, Callable]]:
        """``(start, copies, n, solve)`` per run of equal diagonal blocks of A1: the seven
        connector coordinates share one (E, E) block where their smoothness factors are
        equal (all seven by default), the tets have their own. ``solve``
        applies the block's inverse to an (n, m) dense or sparse matrix: a dense inverse
        with BLAS while the block is small (:data:`DENSE_INVERSE_LIMIT`; measured on the
        liver punch, 10,685 coordinates and 372 columns: 0.28 s against 0.56 s for
        SuperLU's triangular solves), else the sparse LU."""
        def inverse_of(block: sp.csc_matrix) -> Callable:
            if block.shape[0] <= DENSE_INVERSE_LIMIT:
                dense = np.linalg.inv(block.toarray())
                return lambda y: np.asarray(dense @ y)
            lu = splu(block.tocsc())
            return lambda y: lu.solve(y.toarray() if sp.issparse(y) else np.asarray(y))

        def inverse(lap: sp.csc_matrix, smoothness: float = 1.0) -> Callable:
            return inverse_of(_metric_block(lap, self.prior_ratio, smoothness).tocsc())

        if self._split:  # the split prior couples the K0 and kv blocks: one block
            return [(0, 1, self.metric.shape[0], inverse_of(self.metric))]
        e = self.laplacian.shape[0]
        out, q, inverses = [], 0, {}
        # runs of equal factors share one block and one product; equal factors one inverse
        for factor, run in itertools.groupby(self._smoothness.tolist()):
            copies = len(list(run))
            if factor not in inverses:
                inverses[factor] = inverse(self.laplacian, factor)
            out.append((q * e, copies, e, inverses[factor]))
            q += copies
        if self.tet_laplacian is not None:
            out.append((N_COORDS * e, self.tet_blocks, self.tet_laplacian.shape[0],
                        inverse(self.tet_laplacian)))
        return out

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """(size, m) ``A1^-1 rhs`` for a dense (size, m) ``rhs``."""
        out = np.empty(rhs.shape)
        for start, copies, n, solve in self._blocks:
            stop = start + copies * n
            # (copies n, m) -> (n, copies m): one product for every copy's columns
            y = np.asarray(rhs[start:stop]).reshape(copies, n, -1).transpose(1, 0, 2)
            x = solve(y.reshape(n, -1)).reshape(n, copies, -1).transpose(1, 0, 2)
            out[start:stop] = x.reshape(copies * n, -1)
        return out

    def sandwich(self, rows: sp.spmatrix) -> np.ndarray:
        """(k, k) ``R A1^-1 R^T`` for sparse (k, size) rows ``R``, block by block of A1:
        only the blocks ``R`` touches are solved for (the hinge rows: three of seven)."""
        rows = sp.csc_matrix(rows)
        out = np.zeros((rows.shape[0], rows.shape[0]))
        for start, copies, n, solve in self._blocks:
            for c in range(copies):
                block = rows[:, start + c * n:start + (c + 1) * n]
                if block.nnz:
                    out += np.asarray(block @ solve(block.T.tocsr()))
        return out

    def value(self, theta: np.ndarray, weight: float) -> float:
        d = (theta - self.theta0).ravel()
        return float(weight * d @ (self.metric @ d))


@dataclass(frozen=True, eq=False)
class Linearisation:
    """Residuals and Jacobian at theta, with the products the steps need.

    The rows are the dense data rows ``J`` followed by the sparse hinge rows ``H`` (three
    non-zeros each, :meth:`calibration.gradient.Validity.hinge`); ``A1^-1 H^T`` is never
    formed (:meth:`of`).

    Attributes:
        theta: (size,) coordinates.
        r: (m,) residuals (data rows, then the active hinge rows).
        J: (n, size) the data rows' Jacobian (dense).
        H: (m - n, size) the hinge rows' Jacobian (sparse CSR).
        P: (size, n) ``A1^-1 J^T``.
        C: (m, m) ``[J; H] A1^-1 [J; H]^T``.
        offset: squared norm of the residual left out of the rows [1] (:func:`compress`):
            ``|r_full + J_full d|^2 ~ |r + J d|^2 + offset``.
    """
    theta: np.ndarray
    r: np.ndarray
    J: np.ndarray
    H: sp.csr_matrix
    P: np.ndarray
    C: np.ndarray
    offset: float = 0.0

    @classmethod
    @blas_threads()  # the parent's dense algebra on every core: the workers wait meanwhile
    def of(cls, theta: np.ndarray, r: np.ndarray, J: np.ndarray, reg: Regulariser,
           offset: float = 0.0, hinge: sp.spmatrix | None = None) -> "Linearisation":
        """The products for residuals ``r`` of the dense rows ``J`` and then the sparse
        ``hinge`` rows (None: none).

        Why the hinge rows stay sparse: they can outnumber the compressed data rows several
        times (every spring below twice the floor somewhere on its strain range adds rows:
        2,638 at the liver punch's global fit, against 276 data rows). Their block of
        ``A1^-1 [J; H]^T`` would be a dense (size, rows) array (250 MB there) written and
        read at every step; instead ``C``'s hinge blocks come from ``H P`` (data-hinge) and
        ``H_q B^-1 H_q^T`` per coordinate block q that the hinge touches, and a step applies
        ``A1^-1 H^T`` to one vector (:meth:`apply_P`).
        """
        n = len(J)
        P = reg.solve(J.T) if n else np.zeros((J.shape[1], 0))
        data = cls(theta, r[:n], J, sp.csr_matrix((0, J.shape[1])), P, J @ P, offset)
        return data if hinge is None else data.with_hinge(r[n:], hinge, reg)

    def with_hinge(self, r_hinge: np.ndarray, hinge: sp.spmatrix, reg: Regulariser
                   ) -> "Linearisation":
        """This linearisation of data rows only, with the sparse ``hinge`` rows (k, size) and
        their residuals (k,) appended; ``P`` and ``C``'s data block are reused."""
        n, H = len(self.J), sp.csr_matrix(hinge)
        C = np.empty((n + H.shape[0], n + H.shape[0]))
        C[:n, :n] = self.C
        C[n:, :n] = H @ self.P
        C[:n, n:] = C[n:, :n].T
        C[n:, n:] = reg.sandwich(H)
        return Linearisation(self.theta, np.concatenate([self.r, r_hinge]), self.J, H, self.P,
                             C, self.offset)

    def apply_P(self, u: np.ndarray, reg: Regulariser) -> np.ndarray:
        """(size,) ``A1^-1 [J; H]^T u`` for (m,) ``u``."""
        n = len(self.J)
        out = self.P @ u[:n]
        if self.H.shape[0]:
            out += reg.solve((self.H.T @ u[n:])[:, None])[:, 0]
        return out

    def apply_J(self, d: np.ndarray) -> np.ndarray:
        """(m,) ``[J; H] d`` for (size,) ``d``."""
        return np.concatenate([self.J @ d, self.H @ d])

    @blas_threads()
    def step(self, reg: Regulariser, weight: float, damping: float) -> np.ndarray:
        """(size,) minimiser of ``|r + J d|^2 + weight reg(theta + d) + damping d^T A1 d``.

        ``(J^T J + alpha A1) d = -(J^T r + weight A1 d0)``, alpha = weight + damping, by
        Woodbury: ``d = -(1/alpha) [P r + w d0 - P (alpha I + C)^-1 (C r + w J d0)]``.
        """
        alpha = weight + damping
        d0 = (self.theta - reg.theta0).ravel()
        if len(self.r):
            inner = cho_solve(cho_factor(alpha * np.eye(len(self.r)) + self.C),
                              self.C @ self.r + weight * self.apply_J(d0))
            d = self.apply_P(self.r - inner, reg) + weight * d0
        else:
            d = weight * d0
        return (-d / alpha).reshape(self.theta.shape)

    def predict(self, d: np.ndarray) -> np.ndarray:
        return self.r + self.apply_J(d.ravel())


def leading_vectors(gram: np.ndarray, keep: int) -> np.ndarray:
    """(n, keep) the eigenvectors of the symmetric ``gram`` (n, n) of its ``keep`` largest
    eigenvalues, largest first, as a C-ordered array: a reversed view of eigh's columns has
    a negative stride, which numpy's matmul does not hand to BLAS (its own loop: measured
    10-40x slower for a point's (12, 150) x (150, 12,455) projection)."""
    _, vectors = np.linalg.eigh(gram)  # ascending
    return np.ascontiguousarray(vectors[:, ::-1][:, :keep])


def compress(r: np.ndarray, J: np.ndarray, rows_per_point: int, keep: int
             ) -> tuple[np.ndarray, np.ndarray, float]:
    """Each point's rows projected on the ``keep`` leading left singular vectors of its block.

    A point's samples move together (a curve has few independent shapes), so its
    Jacobian block (S, size) is numerically of low rank; projecting the rows on the
    leading singular directions ``U_k`` keeps the Gauss-Newton model
    ``|U_k^T (r + J d)|^2`` (exact for ``J d`` in their span) at a fraction of the
    dense algebra (which grows with the square of the rows). The accept/reject
    test of every step uses the exact objective. Returns the rows (P k,), (P k, size)
    and the squared norm of the residual left out.
    """
    if keep >= rows_per_point:
        return r, J, 0.0
    n_points = len(r) // rows_per_point
    r_out = np.empty(n_points * keep)
    J_out = np.empty((n_points * keep, J.shape[1]))
    for p in range(n_points):
        block = slice(p * rows_per_point, (p + 1) * rows_per_point)
        U = leading_vectors(J[block] @ J[block].T, keep)
        r_out[p * keep:(p + 1) * keep] = U.T @ r[block]
        J_out[p * keep:(p + 1) * keep] = U.T @ J[block]
    return r_out, J_out, float(r @ r - r_out @ r_out)


def folds_of(n_points: int, k: int) -> list[np.ndarray]:
    """k folds of point indices 0..n-1 (a fixed shuffle, so folds mix regions of the mesh)."""
    order = np.random.default_rng(0).permutation(n_points)
    return [np.sort(order[f::k]) for f in range(min(k, n_points))]


#: body weights w tried by cross-validation (:func:`cross_validate`): each whole-body item's
#: squared relative error counts w times a calibration point's in the fit
BODY_WEIGHT_GRID = (0.0, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0)


@blas_threads()
def cross_validate(lin: Linearisation, groups: np.ndarray, reg: Regulariser,
                   folds: list[np.ndarray], grid: Sequence[float] = WEIGHT_GRID,
                   body_grid: Sequence[float] = (0.0,), trained: np.ndarray | None = None
                   ) -> tuple[float, float, np.ndarray]:
    """Smoothness weight (and body weight) by cross-validation on the linearisation ``lin``.

    ``groups`` (rows,) names the data each row of ``lin`` belongs to: a calibration point
    (>= 0, its index) or a whole-body item (``-1 - item``), the body rows unweighted. The
    groups left out in turn are the point ``folds`` and each whole-body item on its own. For
    each body weight ``w`` of ``body_grid`` and smoothness weight of ``grid``, the
    Gauss-Newton step fitted to every other row (the body rows weighted by ``w``) predicts
    the left-out rows ``r + J delta`` (unweighted). The score adds the points' predicted
    squared errors and the body items', the latter scaled by (points / items) so that the
    body data as a whole weigh as much as the surface points (without body rows: the points'
    predicted squared fold residual, as the smoothness weight was always chosen).
    ``trained`` (rows,) False for whole-body rows that are predicted but never fitted (the
    kinds a fit does not use: how well a fit predicts data it did not see); None: all.

    One eigen-decomposition per body weight: each group's fit comes from the whole fit by the
    block-inverse identity (the comment below; tested against refits by brute force).

    Returns (smoothness weight, body weight, scores (len(body_grid), len(grid))).
    """
    groups = np.asarray(groups)
    body = groups < 0
    trained = np.ones(len(groups), bool) if trained is None else np.asarray(trained, bool)
    items = [np.flatnonzero(groups == g) for g in np.unique(groups[body])]
    n_points = len(np.unique(groups[~body]))
    if not (items and trained[body].any()):
        body_grid = (0.0,)
    left_out = [(np.isin(groups, fold) & ~body, 1.0) for fold in folds]
    left_out += [(np.isin(np.arange(len(groups)), rows), n_points / len(items))
                 for rows in items]
    # the fits are ridge regressions in delta = theta + d - theta0 (the prior's centre):
    # minimise |S (y0 + J delta)|^2_T + alpha delta^T A1 delta, y0 = r - J (theta - theta0),
    # S the rows' weights; solved in the rows' space with K = S C S = U diag(e) U^T over the
    # rows that train at this body weight, and each left-out group's fit from the whole fit's
    # G = (alpha I + K)^-1 by the block-inverse identity (no refit per group):
    # z = (G y)_T' - G_T'F G_FF^-1 (G y)_F solves the system without F, and the group's rows
    # are predicted unweighted, y0_F - C_FT' S z (also rows that never train)
    y0 = lin.r - lin.J @ (lin.theta - reg.theta0)
    costs = np.zeros((len(body_grid), len(grid)))
    for b, body_weight in enumerate(body_grid):
        scale = np.where(body, np.sqrt(body_weight), 1.0) * trained
        live = np.flatnonzero(scale > 0)
        s = scale[live]
        e, U = np.linalg.eigh(s[:, None] * lin.C[np.ix_(live, live)] * s[None, :])
        C_S = lin.C[:, live] * s[None, :]  # C_{all, T} S
        y = s * y0[live]
        position = np.full(len(groups), -1)
        position[live] = np.arange(len(live))
        # each group's rows of U, C_S and y0, gathered once for the whole grid
        held = []
        for test, share in left_out:
            f = position[test & (scale > 0)]
            held.append((share, f, U[f], C_S[test], y0[test]))
        for g, alpha in enumerate(grid):  # alpha: the smoothness weight (no damping)
            inverse = 1.0 / (alpha + e)
            Gy = U @ (inverse * (U.T @ y))
            for share, f, U_f, C_test, y0_test in held:
                z = Gy
                if len(f):  # G_FF and G_T'F v from U's rows: no (n, n) product per group
                    v = cho_solve(cho_factor((U_f * inverse[None, :]) @ U_f.T), Gy[f])
                    z = Gy - U @ (inverse * (U_f.T @ v))
                    z[f] = 0.0
                predicted = y0_test - C_test @ z
                costs[b, g] += share * float(predicted @ predicted)
    b, best = np.unravel_index(int(np.argmin(costs)), costs.shape)
    if best in (0, len(grid) - 1):
        log.warning("cross-validation picked the smoothness weight %g at the end of the grid "
                    "[%g, %g]", grid[best], grid[0], grid[-1])
    if len(body_grid) > 1 and b == len(body_grid) - 1:
        log.warning("cross-validation picked the body weight %g at the end of the grid %s",
                    body_grid[b], list(body_grid))
    return float(grid[best]), float(body_grid[b]), costs


@dataclass
class LMState:
    """Where the Levenberg-Marquardt iteration stands (what the checkpoint stores)."""
    theta: np.ndarray
    damping: float
    cost: float
    history: list[float]
    iteration: int = 0
    done: bool = False

    def as_dict(self) -> dict:
        return {"theta": self.theta.tolist(), "damping": self.damping, "cost": self.cost,
                "history": list(self.history), "iteration": self.iteration, "done": self.done}

    @classmethod
    def from_dict(cls, d: dict) -> "LMState":
        return cls(np.asarray(d["theta"], dtype=float), float(d["damping"]), float(d["cost"]),
                   [float(c) for c in d["history"]], int(d["iteration"]), bool(d["done"]))


def linearise(ev: LeastSquares, theta: np.ndarray, points: np.ndarray, reg: Regulariser,
              validity: Bounds, data: Linearisation | None = None) -> Linearisation:
    """Compressed data rows (computed, or ``data``: their linearisation at ``theta``, as the
    cross-validation has it) plus the active hinge rows at ``theta``."""
    if data is None:
        r, J, offset = ev.linearise(theta, points, ROWS_KEPT)
        data = Linearisation.of(theta, r, J, reg, offset)
    h, Jh = validity.hinge(theta)
    active = np.nonzero(h)[0]
    return data.with_hinge(h[active], Jh[active], reg) if len(active) else data


def levenberg_marquardt(ev: LeastSquares, points: np.ndarray, reg: Regulariser, weight: float,
                        validity: Bounds, state: LMState | None, *,
                        theta_start: np.ndarray | None = None, max_iterations: int,
                        tolerance: float = 1e-3,
                        save: Callable[[LMState], None] = lambda s: None,
                        start: Linearisation | None = None) -> LMState:
    """Regularised LM from ``state`` (or ``theta_start``, default ``reg.theta0``); ``save``
    after every iteration.

    The damping is ``damping x A1`` (the regulariser's metric), adapted by the
    gain ratio. Stops when an accepted step lowers the objective by less than
    ``tolerance`` of it, after ``max_iterations`` iterations, or when no damping
    makes a step acceptable. ``start`` is the linearisation at ``reg.theta0`` if
    already computed (at ``theta_start``).
    """
    def objective(theta: np.ndarray, r: np.ndarray) -> float:
        h, _ = validity.hinge(theta)
        return float(r @ r + reg.value(theta, weight) + h @ h)

    if state is None:
        theta = reg.theta0 if theta_start is None else theta_start
        lin = start if start is not None else linearise(ev, theta, points, reg, validity)
        cost = objective(theta, lin.r[:len(lin.J)]) + lin.offset
        state = LMState(theta.copy(), weight, cost, [cost])
    elif not state.done:
        lin = linearise(ev, state.theta, points, reg, validity)
    while not state.done and state.iteration < max_iterations:
        accepted = False
        for _ in range(12):
            d = lin.step(reg, weight, state.damping)
            trial = state.theta + d
            try:
                validity.check(ev.coords.params(trial))
                r_new = ev.residuals(trial, points)
            except INFEASIBLE as exc:
                log.info("gradient fit: step rejected (%s); more damping", exc)
                state.damping *= 4.0
                continue
            new = objective(trial, r_new)
            lin_new = lin.predict(d)
            predicted = state.cost - float(lin_new @ lin_new + lin.offset
                                           + reg.value(trial, weight))
            gain = (state.cost - new) / predicted if predicted > 0 else -1.0
            if new < state.cost:
                accepted = True
                state.damping *= 1.0 / 3.0 if gain > 0.75 else (2.0 if gain < 0.25 else 1.0)
                break
            state.damping *= 4.0
        state.iteration += 1
        if not accepted:
            log.info("gradient fit: no damped step lowers the objective; stopping")
            state.done = True
            save(state)
            break
        gained = state.cost - new
        state.theta, state.cost = trial, new
        state.history.append(new)
        log.info("gradient fit iteration %d: objective %.6g (damping %.3g)", state.iteration,
                 new, state.damping)
        if gained < tolerance * new:
            state.done = True
        save(state)
        if not state.done and state.iteration < max_iterations:
            lin = linearise(ev, state.theta, points, reg, validity)
    return state
