"""Nelder-Mead (the paper's global fits) and a small Gauss-Newton (the local fits, the gradient
method's global relaxation fit), with the paper's bookkeeping: cost per evaluation and per
iteration, warnings.

:func:`nelder_mead` wraps ``scipy.optimize.minimize(method="Nelder-Mead")``:

* the objective is the cost divided by a scale, by default the cost at the
  start, so ``fatol`` is relative to the initial cost (``xatol`` acts on the
  transformed coordinates); the local phase passes the point's cost at the
  start of the phase, so later sweeps do not chase ever smaller residues;
* the initial simplex is ``x0 + step_i e_i`` (steps chosen per coordinate by the
  caller; scipy's default 5 % of each entry is useless at 0);
* a cost function raising one of :data:`INFEASIBLE` gives +inf there (reason
  logged at DEBUG level, or INFO with ``verbose``);
* every evaluation's absolute cost is recorded (``+inf`` for infeasible
  points), and at the end of every iteration the best cost so far and the
  evaluation count (the paper's Fig. 2c-d);
* a fit that does not reduce the cost, or stops on its budget before meeting
  both tolerances, carries a warning (never a silent success).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.optimize import minimize

from forcecal.errors import ConvergenceError, ParameterError, StabilityError

log = logging.getLogger(__name__)

# what a cost function may raise for a parameter set outside the physical region
# (non-positive spring, unordered arms) or one the particle solvers cannot handle:
# such a point costs +inf, and the reason is logged
INFEASIBLE = (ParameterError, ConvergenceError, StabilityError)
#: Gauss-Newton: forward-difference step relative to each coordinate's scale: the curves'
#: equilibria are converged to 1e-8 of the force scale, so a quotient carries ~1e-4 relative
#: noise and ~1e-4 truncation error, harmless to Gauss-Newton steps
FD_STEP = 1e-4
#: Gauss-Newton: damped trial steps per iteration before it stops at the optimum
MAX_REJECTIONS = 10


@dataclass(frozen=True, eq=False)
class History:
    """Cost history of one optimisation.

    Attributes:
        evaluation_cost: (n_eval,) float64, cost of every evaluation in order [N^2]
            (+inf where the point was infeasible).
        iteration_cost: (n_iter,) float64, best cost at the end of each iteration [N^2].
        iteration_evaluations: (n_iter,) int64, evaluations done by the end of each iteration.
    """
    evaluation_cost: np.ndarray
    iteration_cost: np.ndarray
    iteration_evaluations: np.ndarray

    def as_dict(self) -> dict[str, list]:
        return {k: getattr(self, k).tolist() for k in self.__dataclass_fields__}

    @classmethod
    def from_dict(cls, d: dict[str, list]) -> "History":
        return cls(np.asarray(d["evaluation_cost"], dtype=float),
                   np.asarray(d["iteration_cost"], dtype=float),
                   np.asarray(d["iteration_evaluations"], dtype=np.int64))


@dataclass(frozen=True, eq=False)
class Fit:
    """Result of one optimisation (:func:`nelder_mead` or :func:`gauss_newton`).

    Attributes:
        x: (d,) float64, best coordinates found.
        cost: cost at ``x`` [N^2].
        initial_cost: cost at the start [N^2].
        converged: True if both tolerances were met within the budget.
        history: the cost history.
        warnings: human-readable problems (no reduction, budget exhausted).
    """
    x: np.ndarray
    cost: float
    initial_cost: float
    converged: bool
    history: History
    warnings: tuple[str, ...] = field(default=())

    @property
    def evaluations(self) -> int:
        return len(self.history.evaluation_cost)

    def as_dict(self) -> dict:
        return {"x": self.x.tolist(), "cost": self.cost, "initial_cost": self.initial_cost,
                "converged": self.converged, "history": self.history.as_dict(),
                "warnings": list(self.warnings)}

    @classmethod
    def from_dict(cls, d: dict) -> "Fit":
        return cls(np.asarray(d["x"], dtype=float), float(d["cost"]), float(d["initial_cost"]),
                   bool(d["converged"]), History.from_dict(d["history"]), tuple(d["warnings"]))


def nelder_mead(cost: Callable[[np.ndarray], float], x0: np.ndarray, step: np.ndarray, *,
                name: str, xatol: float, fatol: float, max_evaluations: int,
                scale: float | None = None,
                on_evaluation: Callable[[float], None] | None = None,
                verbose: bool = False) -> Fit:
    """Minimise ``cost`` from ``x0`` (module docstring); ``name`` labels logs and warnings.

    ``fatol`` is relative to ``scale`` [N^2] (default: the cost at ``x0``).

    An infeasible ``x0`` is replaced by the best feasible point of :func:`feasible_start`
    (a warning says so).

    Raises:
        ConvergenceError: no feasible point to start from (:func:`feasible_start`).
    """
    x0 = np.asarray(x0, dtype=float)
    evaluations: list[float] = []
    best = [math.inf, x0]
    iterations: list[tuple[float, int]] = []
    level = logging.INFO if verbose else logging.DEBUG

    def evaluate(x: np.ndarray) -> tuple[float, str]:
        try:
            return float(cost(x)), ""
        except INFEASIBLE as exc:
            return math.inf, str(exc)

    def record(x: np.ndarray, c: float) -> float:
        evaluations.append(c)
        if c < best[0]:
            best[0], best[1] = c, np.array(x)
        if on_evaluation is not None:
            on_evaluation(best[0])
        return c

    start, reason = evaluate(x0)
    warnings = []
    if not math.isfinite(start):
        x0, start, moved = feasible_start(evaluate, x0, step, name, reason)
        warnings.append(moved)
        log.warning(moved)
    record(x0, start)
    if start == 0.0:  # nothing to fit (synthetic data that the start reproduces exactly)
        return Fit(x0, 0.0, 0.0, True, History(np.array([0.0]), np.zeros(0), np.zeros(0, int)))
    scale = start if scale is None or not scale > 0 else float(scale)
    memo = {x0.tobytes(): start}  # scipy evaluates x0 again as the simplex's first vertex

    def objective(x: np.ndarray) -> float:
        c = memo.pop(np.asarray(x, dtype=float).tobytes(), None)
        if c is None:
            c, reason = evaluate(x)
            if reason:
                log.log(level, "%s: cost = +inf at %s: %s", name, np.round(x, 6).tolist(), reason)
            record(x, c)
        return c / scale

    def callback(_xk: np.ndarray) -> None:
        iterations.append((best[0], len(evaluations)))
        log.log(level, "%s: iteration %d, %d evaluations, cost %.6g (%.4g of the start)", name,
                len(iterations), len(evaluations), best[0], best[0] / start)

    simplex = np.vstack([x0, x0 + np.diag(np.asarray(step, dtype=float))])
    res = minimize(objective, x0, method="Nelder-Mead", callback=callback,
                   options={"initial_simplex": simplex, "xatol": xatol, "fatol": fatol,
                            "maxfev": max_evaluations, "maxiter": 100 * max_evaluations})
    if res.status != 0:
        warnings.append(f"{name}: stopped at its budget of {max_evaluations} evaluations without "
                        f"meeting xatol={xatol:g} and fatol={fatol:g} (cost {best[0]:.4g}, "
                        f"start {start:.4g})")
    if best[0] >= start:
        warnings.append(f"{name}: Nelder-Mead did not reduce the cost below its start "
                        f"({start:.6g})")
    for w in warnings:  # returned to the caller, who reports them
        log.log(level, w)
    history = History(np.asarray(evaluations), np.asarray([c for c, _ in iterations], float),
                      np.asarray([n for _, n in iterations], dtype=np.int64))
    return Fit(np.asarray(best[1], dtype=float), best[0], start, res.status == 0, history,
               tuple(warnings))


def feasible_start(evaluate: Callable[[np.ndarray], tuple[float, str]], x0: np.ndarray,
                   step: np.ndarray, name: str, reason: str) -> tuple[np.ndarray, float, str]:
    """Where a fit whose start ``x0`` is infeasible (``reason``) starts instead: the point of
    lowest finite cost among ``x0 +- f step_i`` (each coordinate alone, ``f`` = 1, 2, 4: the
    initial simplex's vertices and their mirror images, then further out), the nearest
    ``f`` first. ``evaluate(x) -> (cost, reason)`` (+inf where infeasible). Returns (the
    point, its cost, a warning naming both starts).

    Raises:
        ConvergenceError: every candidate is infeasible too (naming ``x0``'s reason).
    """
    for factor in (1.0, 2.0, 4.0):
        candidates = [x0 + sign * factor * step[i] * np.eye(len(x0))[i]
                      for i in range(len(x0)) for sign in (1.0, -1.0)]
        costs = [evaluate(x)[0] for x in candidates]
        best = int(np.argmin(costs))
        if math.isfinite(costs[best]):
            x = candidates[best]
            return x, costs[best], (f"{name}: the starting point {x0.tolist()} is infeasible "
                                    f"({reason or 'cost is not finite'}); started from the "
                                    f"feasible point {np.round(x, 6).tolist()} next to it")
    raise ConvergenceError(f"{name}: the starting point {x0.tolist()} is infeasible: "
                           f"{reason or 'cost is not finite'} (and so is every point up to 4 "
                           "initial steps from it along each coordinate)")


def gauss_newton(residuals: Callable[[np.ndarray], np.ndarray], x0: np.ndarray,
                 step: np.ndarray, *, name: str, xatol: float, fatol: float,
                 max_evaluations: int, scale: float | None = None,
                 max_step: float | None = None, bound_finish: float | None = None,
                 on_evaluation: Callable[[float], None] | None = None,
                 verbose: bool = False) -> Fit:
    """Minimise ``|residuals(x)|^2`` from ``x0`` by Levenberg-Marquardt with a forward-difference
    Jacobian; the same bookkeeping and :class:`Fit` as :func:`nelder_mead`.

    For the few coordinates of a smooth least-squares cost (the global relaxation fit of the
    gradient method, every local fit): d + 1 evaluations per iteration (d coordinates; the
    curves warm-start from the last ones, so the difference quotients are cheap), against
    Nelder-Mead's ~10 d-100 d evaluations in all. ``step`` (d,) is each coordinate's scale:
    the difference quotient uses ``FD_STEP step_i`` (backward where forward is
    infeasible). A trial point raising one of :data:`INFEASIBLE` is rejected
    like one that raises the cost (more damping). ``max_step``: the initial radius of a
    trust region on a trial step's largest coordinate (a full Gauss-Newton step from far
    away can land in another basin of a non-convex cost, which Nelder-Mead's small simplex
    does not), doubled after every accepted step that it cut and the linear model predicted
    well (gain > 0.75), so a fit that must travel far is not held to small steps.
    Converged when an accepted step is below ``xatol`` in every coordinate or lowers
    the cost by less than ``fatol`` times ``scale`` (default: the initial cost).
    ``bound_finish``: if a trial step left the feasible region, the fit ends with
    :func:`nelder_mead` from Gauss-Newton's result, its simplex ``bound_finish step``, on
    the rest of the budget. Why: where the optimum lies on the region's boundary (a spring
    tangent at its floor), every Gauss-Newton step points out of it and the damped steps
    crawl along it, while the simplex slides along the boundary (a local fit on the
    h = 0.0182 m bench mesh stopped at cost 0.102 N^2 this way).

    A coordinate along which both difference steps are infeasible (``x`` on the region's
    boundary both ways) is held for that iteration.

    Raises:
        ConvergenceError: the starting point itself is infeasible.
    """
    x = np.asarray(x0, dtype=float).copy()
    step = np.asarray(step, dtype=float)
    evaluations: list[float] = []
    iterations: list[tuple[float, int]] = []
    level = logging.INFO if verbose else logging.DEBUG
    best = [math.inf]
    left_region = False  # a trial step raised one of INFEASIBLE

    def evaluate(z: np.ndarray) -> np.ndarray | None:
        try:
            r = np.asarray(residuals(z), dtype=float)
        except INFEASIBLE as exc:
            log.log(level, "%s: infeasible at %s: %s", name, np.round(z, 6).tolist(), exc)
            r = None
        c = float(r @ r) if r is not None and np.all(np.isfinite(r)) else math.inf
        evaluations.append(c)
        best[0] = min(best[0], c)
        if on_evaluation is not None:
            on_evaluation(best[0])
        return r if math.isfinite(c) else None

    r = evaluate(x)
    if r is None:
        raise ConvergenceError(f"{name}: the starting point {x.tolist()} is infeasible")
    start = cost = float(r @ r)
    tolerance = fatol * (start if scale is None else scale)
    damping, converged, radius = 1e-3, False, max_step
    while start > 0.0 and len(evaluations) + len(x) + 1 <= max_evaluations:
        jac = np.empty((len(r), len(x)))
        for i, h in enumerate(FD_STEP * step):
            for sign in (1.0, -1.0):
                z = x.copy()
                z[i] += sign * h
                rz = evaluate(z)
                if rz is not None:
                    jac[:, i] = (rz - r) / (sign * h)
                    break
            else:
                # x lies on the feasible region's boundary both ways along this coordinate
                # (e.g. a spring's tangent at its ceiling at one end of its strain range and
                # at the ceiling or floor at the other): hold it this iteration (a zero
                # column gives it a zero step) and let the boundary finish slide along it
                log.log(level, "%s: coordinate %d held: infeasible on both sides of %s", name,
                        i, np.round(x, 6).tolist())
                jac[:, i] = 0.0
                left_region = True
        jtj, grad = jac.T @ jac, jac.T @ r
        if not np.any(grad):  # a cost flat to round-off: no direction gains (converged)
            converged = True
            break
        diagonal = np.maximum(np.diag(jtj), 1e-12 * np.max(np.diag(jtj)))
        accepted = False
        for _ in range(MAX_REJECTIONS):
            if len(evaluations) >= max_evaluations:
                break
            d = np.linalg.solve(jtj + damping * np.diag(diagonal), -grad)
            capped = radius is not None and np.abs(d).max() > radius
            if capped:
                d *= radius / np.abs(d).max()
            r_new = evaluate(x + d)
            left_region = left_region or r_new is None
            new = math.inf if r_new is None else float(r_new @ r_new)
            predicted = cost - float(np.sum((r + jac @ d) ** 2))
            if new < cost:
                gain = (cost - new) / predicted if predicted > 0 else 0.0
                damping *= 1.0 / 3.0 if gain > 0.75 else (2.0 if gain < 0.25 else 1.0)
                if capped and gain > 0.75:
                    radius *= 2.0  # the model predicts well at the radius: let it reach further
                accepted = True
                break
            damping *= 4.0
        if not accepted:
            # every damped step raised the cost: at the optimum to round-off (unless the
            # budget ran out first)
            converged = len(evaluations) < max_evaluations
            break
        gained = cost - new
        x, r, cost = x + d, r_new, new
        iterations.append((cost, len(evaluations)))
        log.log(level, "%s: iteration %d, %d evaluations, cost %.6g (%.4g of the start)", name,
                len(iterations), len(evaluations), cost, cost / start)
        if np.all(np.abs(d) < xatol) or gained < tolerance:
            converged = True
            break
    converged = converged or start == 0.0
    budget = max_evaluations - len(evaluations)
    if bound_finish is not None and left_region and budget > len(x) + 1:
        log.log(level, "%s: a step left the feasible region; Nelder-Mead finishes from cost %.6g",
                name, cost)
        offset = len(evaluations)

        def finish_cost(z: np.ndarray) -> float:
            rz = np.asarray(residuals(z), dtype=float)
            return float(rz @ rz)
        nm = nelder_mead(finish_cost, x, bound_finish * step, name=f"{name} (Nelder-Mead finish)",
                         xatol=xatol, fatol=fatol, max_evaluations=budget,
                         scale=start if scale is None else scale, verbose=verbose)
        evaluations += nm.history.evaluation_cost.tolist()
        iterations += [(c, n + offset) for c, n in zip(nm.history.iteration_cost,
                                                        nm.history.iteration_evaluations)]
        if nm.cost < cost:
            x, cost = nm.x, nm.cost
        converged = nm.converged
    warnings = []
    if not converged:
        warnings.append(f"{name}: stopped at its budget of {max_evaluations} evaluations without "
                        f"meeting xatol={xatol:g} and fatol={fatol:g} (cost {cost:.4g}, "
                        f"start {start:.4g})")
    if cost >= start > 0.0:
        warnings.append(f"{name}: Gauss-Newton did not reduce the cost below its start "
                        f"({start:.6g})")
    for w in warnings:
        log.log(level, w)
    history = History(np.asarray(evaluations), np.asarray([c for c, _ in iterations], float),
                      np.asarray([n for _, n in iterations], dtype=np.int64))
    return Fit(x, cost, start, converged, history, tuple(warnings))
