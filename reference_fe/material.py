"""Constitutive model of the FE reference: nearly incompressible Mooney-Rivlin + Prony series.

Strain energy (total Lagrangian, ``C = F^T F``, ``J = det F``)::

    W = C10 (I1b - 3) + C01 (I2b - 3) + kappa/2 (J - 1)^2,
    I1b = J^(-2/3) tr C,  I2b = J^(-4/3) (tr(C)^2 - tr(C C)) / 2.

``C10, C01`` are the *instantaneous* constants. Second Piola-Kirchhoff stresses:
``S_iso0 = 2 dW_iso/dC`` (isochoric, instantaneous) and
``S_vol = kappa (J - 1) J C^-1``; for the Taylor-Hood u-p element ``W_vol`` is
replaced by the perturbed Lagrangian ``p (J - 1) - p^2 / (2 kappa)``, so
``S_vol = p J C^-1`` and the pressure equation is ``J - 1 - p / kappa = 0``.

Viscoelasticity (Simo 1987, in the form of Holzapfel 1996, internal variables in
the reference configuration): with ``g_inf = 1 - sum(g_i)``, after each
converged step ``n -> n+1`` of length ``dt``::

    a_i = exp(-dt / tau_i),   b_i = g_i (1 - a_i) / (dt / tau_i)
    h_i^{n+1} = a_i h_i^n + b_i (S_iso0^{n+1} - S_iso0^n)
    S^{n+1}   = S_vol^{n+1} + g_inf S_iso0^{n+1} + sum_i h_i^{n+1}

The ``b_i`` factor makes the update exact for an ``S_iso0`` that varies
linearly within the step, for any ``dt``. During the step the stress is affine
in ``S_iso0^{n+1}``::

    S^{n+1} = S_vol^{n+1} + gamma S_iso0^{n+1} + H^n,
    gamma = g_inf + sum_i b_i,   H^n = sum_i (a_i h_i^n - b_i S_iso0^n),

which is what the residual form uses (``gamma`` a constant, ``H^n`` a
quadrature-point tensor): one compiled form serves every time step, every
number of Prony terms and the purely hyperelastic case (``gamma = 1, H = 0``).
At ``t = 0+`` a jump gives ``b_i -> g_i`` and the instantaneous response; at
``t -> inf`` ``h_i -> 0`` and the long-term one, whose isochoric part is
``g_inf`` times the instantaneous one: :func:`long_term`.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import ufl

from forcecal.errors import ParameterError
from forcecal.scene import MaterialSection


def check_material(material: MaterialSection) -> MaterialSection:
    """Refuse non-physical constants (a scene file is validated already; this guards direct use)."""
    m = material
    values = {"C10": m.C10, "C01": m.C01, "kappa": m.kappa, "density": m.density}
    bad = {k: v for k, v in values.items() if not np.isfinite(v)}
    if bad or m.C10 <= 0 or m.C01 < 0 or m.kappa <= 0 or m.density <= 0:
        raise ParameterError(f"material {values}: need C10 > 0, C01 >= 0, kappa > 0, "
                             "density > 0, all finite")
    problem = m.prony_error()
    if problem:
        raise ParameterError(f"material Prony series: {problem}")
    return m


def long_term(material: MaterialSection) -> MaterialSection:
    """The fully relaxed (t -> inf) hyperelastic material: C10, C01 scaled by g_inf, no Prony terms.

    The volumetric part does not relax (the Prony series acts on the isochoric
    stress only), so kappa is unchanged.
    """
    g_inf = material.long_term_factor
    return dataclasses.replace(material, C10=g_inf * material.C10, C01=g_inf * material.C01,
                               prony_g=(), prony_tau=())


def prony_step(material: MaterialSection, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Decay ``a_i = exp(-dt/tau_i)`` and gain ``b_i = g_i (1 - a_i)/(dt/tau_i)`` of a step.

    Args:
        dt: step length [s], > 0.
    """
    if not dt > 0:
        raise ParameterError(f"viscoelastic time step dt = {dt} s must be > 0")
    tau = np.asarray(material.prony_tau, dtype=float)
    g = np.asarray(material.prony_g, dtype=float)
    x = dt / tau
    decay = np.exp(-x)
    return decay, g * (-np.expm1(-x)) / x


def isochoric_energy(C: ufl.core.expr.Expr, C10: ufl.core.expr.Expr,
                     C01: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """W_iso = C10 (I1b - 3) + C01 (I2b - 3) of the Mooney-Rivlin model [J/m^3] (UFL)."""
    J = ufl.sqrt(ufl.det(C))
    I1 = ufl.tr(C)
    I2 = 0.5 * (I1 ** 2 - ufl.tr(C * C))
    return C10 * (J ** (-2.0 / 3.0) * I1 - 3.0) + C01 * (J ** (-4.0 / 3.0) * I2 - 3.0)


def isochoric_stress(C: ufl.core.expr.Expr, C10: ufl.core.expr.Expr,
                     C01: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """S_iso0 = 2 dW_iso/dC [Pa] (UFL), written out::

        S_iso0 = 2 C10 J^(-2/3) (I - I1/3 C^-1) + 2 C01 J^(-4/3) (I1 I - C - 2/3 I2 C^-1)

    from dI1/dC = I, dI2/dC = I1 I - C and dJ/dC = J/2 C^-1. The closed form
    compiles to kernels about twice as fast as ``ufl.diff`` of
    :func:`isochoric_energy` (a test checks the two agree).
    """
    I = ufl.Identity(3)
    C_inv = ufl.inv(C)
    J = ufl.sqrt(ufl.det(C))
    I1 = ufl.tr(C)
    I2 = 0.5 * (I1 ** 2 - ufl.tr(C * C))
    return 2.0 * (C10 * J ** (-2.0 / 3.0) * (I - I1 / 3.0 * C_inv)
                  + C01 * J ** (-4.0 / 3.0) * (I1 * I - C - 2.0 / 3.0 * I2 * C_inv))


def pressure_stress(C: ufl.core.expr.Expr, p: ufl.core.expr.Expr) -> ufl.core.expr.Expr:
    """S_vol = p J C^-1 for a hydrostatic pressure p [Pa] (UFL); p = kappa (J - 1) for W_vol."""
    return p * ufl.sqrt(ufl.det(C)) * ufl.inv(C)
