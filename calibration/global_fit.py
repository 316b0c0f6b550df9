"""Closed-form initial guess and global tuning (one parameter set for every connector).

* Initial guess: ``K0 = argmin sum_j (K0 u_j - s_j)^2 = sum s_j u_j / sum u_j^2``
  with ``s_j`` the FE's initial static slope at calibration point j (from its
  first two samples, ``F = s d + c d^2`` through the origin) and ``u_j`` the
  slope of the unit-stiffness linear network (exactly the particle model's
  initial slope per unit K0, :mod:`calibration.network`); ``a = b = 0``; arms
  from the Prony series, ``k_i = g_i/g_inf K0``, ``tau_i`` from the material.
  With the volume term (``particle.volume``), ``kv`` starts at the bulk modulus
  of the spring network itself, ``K0 sum L^2/(9 V)``
  (:func:`particle.volume.network_bulk_modulus`), i.e. the term doubles the
  network's resistance to a uniform dilation. Why not the material's kappa: the
  FE material is nearly incompressible (kappa/mu = 125 on the default liver)
  and a kv that large locks the network as P1 tets lock (5-12x too stiff, see
  the generalisation notes) and divides the explicit step by ~sqrt(kappa/mu);
  the fitted kv lies between, and the static fit searches it in log
  coordinates (first simplex step a factor 2). A relaxing volume term
  (``particle.volume = "viscoelastic"``) starts with the material's Prony ratios
  too, ``kv_i = g_i/g_inf kv``: the volume term relaxes as the springs do, the
  FE's shear modulus' share, which its arms then fit. With a global shape
  (``calibration.global_shape``) every connector's stiffnesses are the set's
  times its fixed factor: the unit network has stiffnesses ``w_c``, K0 is the
  scale, and everything below holds as written.
* Step 1, static: Nelder-Mead over ``x = (alpha s, beta s^2)`` on the static
  curves of all calibration points; for each x the curve of a uniform network
  is exactly proportional to K0, so K0 is solved in closed form (least squares)
  from one evaluation at a reference K0 -- a 2-D search instead of 3-D.
* Step 2, relaxation: Nelder-Mead over ``(log k1, log tau1, log k2, log tau2)``
  on the relaxation curves with the step-1 spring fixed (with the volume arms also
  ``log(kv1/kv), log(kv2/kv)``, kv fixed: the static fit identifies only the long-term
  kv, the relaxation curves its arms).
* The gradient method (:mod:`calibration.gradient`) runs step 2 by Gauss-Newton
  on the same coordinates and cost (:func:`calibration.optimize.gauss_newton`,
  forward-difference Jacobians): on the liver punch it reaches Nelder-Mead's
  minimum (cost 115.038 N^2 both) in 27 curve evaluations instead of 118 (6.0
  against 44.2 s). Step 1 stays Nelder-Mead for both methods: its cost has two
  basins, and Gauss-Newton from the closed-form start walks to a softening
  spring against the stiffness floor (cost 5.246 N^2) where the simplex finds
  the stiffening one (5.075 N^2).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from calibration.baseline import prony_arms
from calibration.optimize import Fit, gauss_newton, nelder_mead
from calibration.parametrisation import (GlobalParams, StrainRange, check_feasible,
                                         connector_floor)
from calibration.pool import Pool
from calibration.progress import cost_ticker, progress_bar
from forcecal.errors import DataFileError, ParameterError
from forcecal.mesh import TetMesh
from forcecal.scene import CalibrationSection, MaterialSection
from particle.volume import network_bulk_modulus

STATIC_STEP = 0.25  # initial simplex: K changes by 25 % at the largest strain
VOLUME_STEP = float(np.log(2.0))  # initial simplex: kv/K0 doubled
RELAXATION_STEP = 0.3  # initial simplex: arm stiffnesses and times change by a factor 1.35
#: Newton tolerance (relative to the indenter force) of the curves a Nelder-Mead fit
#: compares; the evaluators' own, 1e-8, serves difference quotients (Gauss-Newton, the
#: adjoint) and every reported curve. Nelder-Mead only ranks costs, and at 1e-6 the cost
#: moves by less than ``fatol`` (1e-6 of the initial cost): on the default liver the
#: relaxation cost at the fit's optimum (8.9097 N^2) came out 3e-7 (cold) and -1.4e-7
#: (warm-started) of itself off its 1e-8 value. Measured there: 1.9 instead of 3.5
#: modified-Newton solves per relaxation step; the global relaxation fit 106 evaluations
#: (124 at 1e-8; the path differs within the tolerances, the coordinates by < ``xatol``),
#: every reported error within 0.003 points; calibration 48.7 -> 38.7 s (median of 3 pairs).
NELDER_MEAD_RTOL = 1e-6
NELDER_MEAD, GAUSS_NEWTON = "nelder-mead", "gauss-newton"
#: the global fits' optimizers: the paper's Nelder-Mead, or Gauss-Newton on the same
#: least-squares cost (the gradient method's relaxation step, module docstring)
OPTIMIZERS = (NELDER_MEAD, GAUSS_NEWTON)


def fe_initial_slopes(depths: np.ndarray, forces: np.ndarray) -> np.ndarray:
    """(P,) initial slopes dF/dd at d = 0 [N/m] of curves (P, S) sampled at ``depths`` [m].

    The quadratic ``F = s d + c d^2`` through the origin and the first two samples.
    """
    d1, d2 = depths[0], depths[1]
    return (forces[:, 0] * d2 ** 2 - forces[:, 1] * d1 ** 2) / (d1 * d2 * (d2 - d1))


def initial_guess(material: MaterialSection, fe_slope: np.ndarray,
                  unit_slope: np.ndarray, mesh: TetMesh | None = None,
                  shape: np.ndarray | None = None, volume_arms: bool = False) -> GlobalParams:
    """Closed-form start (module docstring) from per-point FE and unit-network slopes [N/m].

    ``mesh`` given: the volume term is on and kv starts at the network's bulk modulus;
    ``volume_arms``: it relaxes, its arms at the Prony ratios ``kv_i = g_i/g_inf kv``.
    ``shape``: the connectors' (E,) factors of the global set (None: uniform); the unit
    network's slopes must be those of stiffnesses ``shape``.
    """
    K0 = float(np.dot(fe_slope, unit_slope) / np.dot(unit_slope, unit_slope))
    if not K0 > 0:
        raise DataFileError(f"the FE's initial static slopes {np.round(fe_slope, 6).tolist()} "
                            "N/m give no positive stiffness; are the reference forces signed "
                            "along the inward normal?")
    ratio, tau = prony_arms(material)
    kv = 0.0
    if mesh is not None:  # the network of stiffnesses K0 shape: sum K0 w L^2 / (9 V)
        lengths2 = mesh.edge_lengths ** 2
        mean_factor = 1.0 if shape is None else float(np.sum(shape * lengths2) / np.sum(lengths2))
        kv = network_bulk_modulus(mesh, K0 * mean_factor)
    elif volume_arms:
        raise ParameterError("volume arms need the volume term (a mesh for its kv)")
    arms = ({"kv1": float(ratio[0] * kv), "kv2": float(ratio[1] * kv)} if volume_arms else {})
    return GlobalParams(K0=K0, alpha=0.0, beta=0.0, k1=float(ratio[0] * K0), tau1=float(tau[0]),
                        k2=float(ratio[1] * K0), tau2=float(tau[1]), kv=kv, **arms)


def fit_static(pool: Pool, start: GlobalParams, strain: StrainRange, reference: np.ndarray,
               n_connectors: int, settings: CalibrationSection, *, optimizer: str = NELDER_MEAD,
               feasible: StrainRange | None = None, shape: np.ndarray | None = None,
               progress: bool = True, verbose: bool = False) -> tuple[GlobalParams, Fit]:
    """Step 1: spring ``K0, a, b`` (and ``kv`` if the volume term is on) on the static curves
    ``reference`` (Pc, S) [N], by ``optimizer`` (:data:`OPTIMIZERS`). The spring's tangent
    stays above the floor on ``feasible`` (default ``strain``, the experiments' range; the
    calibration passes that united with the gravity release range of the FE sag).
    ``shape``: the connectors' (E,) factors (:func:`calibration.parametrisation.global_shape`)
    or None (uniform)."""
    points = np.arange(len(reference))
    K0_of: dict[bytes, float] = {}
    # K(eps)/K0 does not depend on the K0 solved for; a connector's floor scales with its shape
    floor = connector_floor(settings.stiffness_floor, start.K0, shape)
    feasible = strain if feasible is None else feasible

    def residuals(x: np.ndarray) -> np.ndarray:
        params = start.with_static_coordinates(x, start.K0, strain).connector_params(
            n_connectors, shape)
        check_feasible(params, feasible, floor)
        sim = pool.curves("indentation", params, points)
        scale = float(np.sum(reference * sim) / np.sum(sim * sim))
        if not scale > 0:
            raise ParameterError(f"the static curves at alpha s, beta s^2 = {x.tolist()} do not "
                                 "push back (least-squares K0 <= 0)")
        K0_of[np.asarray(x, dtype=float).tobytes()] = scale * start.K0
        return (reference - scale * sim).ravel()

    x0 = start.static_coordinates(strain)
    steps = np.r_[np.full(2, STATIC_STEP), np.full(len(x0) - 2, VOLUME_STEP)]
    fit = _minimise(pool, residuals, x0, steps, "global static fit", optimizer,
                    settings.static_max_evaluations, settings, progress, verbose)
    return start.with_static_coordinates(fit.x, K0_of[fit.x.tobytes()], strain), fit


def fit_relaxation(pool: Pool, start: GlobalParams, strain: StrainRange, reference: np.ndarray,
                   n_connectors: int, settings: CalibrationSection, *,
                   optimizer: str = NELDER_MEAD, feasible: StrainRange | None = None,
                   shape: np.ndarray | None = None, progress: bool = True,
                   verbose: bool = False) -> tuple[GlobalParams, Fit]:
    """Step 2: arms ``k1, tau1, k2, tau2`` (and the volume arms' ``kv1, kv2`` when ``start``
    has them) on the relaxation curves (Pc, S) [N], spring fixed, by ``optimizer``
    (:data:`OPTIMIZERS`); ``feasible`` and ``shape`` as :func:`fit_static`."""
    points = np.arange(len(reference))
    feasible = strain if feasible is None else feasible
    floor = connector_floor(settings.stiffness_floor, start.K0, shape)

    def residuals(y: np.ndarray) -> np.ndarray:
        params = start.with_relaxation_coordinates(y).connector_params(n_connectors, shape)
        check_feasible(params, feasible, floor)
        return (reference - pool.curves("relaxation", params, points)).ravel()

    y0 = start.relaxation_coordinates()
    fit = _minimise(pool, residuals, y0, np.full(len(y0), RELAXATION_STEP),
                    "global relaxation fit", optimizer, settings.relaxation_max_evaluations,
                    settings, progress, verbose)
    return start.with_relaxation_coordinates(fit.x), fit


def _minimise(pool: Pool, residuals: Callable[[np.ndarray], np.ndarray], x0: np.ndarray,
              steps: np.ndarray, name: str, optimizer: str, budget: int,
              settings: CalibrationSection, progress: bool, verbose: bool) -> Fit:
    """The sum of squared ``residuals`` (curves of ``pool``) minimised from ``x0`` by
    ``optimizer``; ``steps``: the initial simplex (Nelder-Mead, its curves solved to
    :data:`NELDER_MEAD_RTOL`) or the coordinates' scales (Gauss-Newton)."""
    if optimizer not in OPTIMIZERS:
        raise ParameterError(f"unknown global optimizer {optimizer!r}; one of {OPTIMIZERS}")
    rtol = NELDER_MEAD_RTOL if optimizer == NELDER_MEAD else None
    with progress_bar(name.removesuffix(" fit"), budget, progress) as bar, \
            pool.newton_tolerance(rtol):
        kw = dict(name=name, xatol=settings.xatol, fatol=settings.fatol,
                  max_evaluations=budget, on_evaluation=cost_ticker(bar), verbose=verbose)
        if optimizer == GAUSS_NEWTON:
            return gauss_newton(residuals, x0, steps, **kw)

        def cost(x: np.ndarray) -> float:
            r = residuals(x)
            return float(np.sum(r * r))  # numpy's pairwise sum, as the paper's fits always did
        return nelder_mead(cost, x0, steps, **kw)
