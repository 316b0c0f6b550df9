"""Closed-form, uncalibrated connector parameters (the baseline every fit is compared with).

Spring stiffness after Van Gelder's rule for spring networks [1], in its 3-D
tetrahedral form [2]:

    K0_c = E_inf * sum_{t containing c} V_t / L_c^2

with ``V_t`` the volumes of the tets sharing connector c and ``L_c`` its rest
length. ``E_inf`` is the long-term small-strain Young's modulus of the FE
material: ``mu_inf = g_inf * 2 (C10 + C01)`` (``g_inf = 1 - sum g_i``) with the
(unrelaxed) bulk modulus kappa, ``E_inf = 9 kappa mu_inf / (3 kappa + mu_inf)``.
No nonlinear terms (``a = b = 0``). Maxwell arms from the Prony series, per
connector: ``k_i = g_i / g_inf * K0_c``, ``b_i = tau_i k_i``.

A check of the rule: stretching every connector by the same strain e stores
``1/2 sum_c K0_c (e L_c)^2 = 3 E V e^2`` (each tet has six edges), exactly the
continuum energy of a uniform dilation of a solid with Poisson's ratio 1/4, the
only one a central-force network can represent.

[1] A. Van Gelder, "Approximate simulation of elastic membranes by triangulated
    spring meshes", J. Graphics Tools 3(2):21-42, 1998.
[2] B. A. Lloyd, G. Szekely, M. Harders, "Identification of spring parameters
    for deformable object simulation", IEEE TVCG 13(5):1081-1094, 2007.
"""

from __future__ import annotations

import numpy as np

from forcecal.errors import ParameterError
from forcecal.mesh import TetMesh
from forcecal.scene import MaterialSection
from particle.params import ConnectorParams


def long_term_young_modulus(material: MaterialSection) -> float:
    """``E_inf = 9 kappa mu_inf / (3 kappa + mu_inf)`` [Pa], ``mu_inf = g_inf 2 (C10 + C01)``."""
    mu = material.long_term_factor * material.shear_modulus
    return 9.0 * material.kappa * mu / (3.0 * material.kappa + mu)


def prony_arms(material: MaterialSection) -> tuple[np.ndarray, np.ndarray]:
    """Arm stiffness ratios ``g_i / g_inf`` [1] and relaxation times ``tau_i`` [s] (two arms).

    Sorted by relaxation time: arm 1 is the fast one (``tau1 < tau2``).
    """
    if len(material.prony_g) != 2:
        raise ParameterError(f"the particle model has exactly two Maxwell arms; the material has "
                             f"{len(material.prony_g)} Prony terms")
    tau = np.asarray(material.prony_tau, dtype=float)
    if tau[0] == tau[1]:
        raise ParameterError(f"the two Prony relaxation times are equal ({tau[0]} s); the arms "
                             "would not be identifiable")
    order = np.argsort(tau)
    return (np.asarray(material.prony_g)[order] / material.long_term_factor, tau[order])


def van_gelder_weights(mesh: TetMesh) -> np.ndarray:
    """(E,) ``sum_{t containing c} V_t / L_c^2`` [m] of every connector: its spring per unit
    Young's modulus (module docstring)."""
    return mesh.edge_tet_volume / mesh.edge_lengths ** 2


def van_gelder_params(mesh: TetMesh, material: MaterialSection) -> ConnectorParams:
    """Per-connector baseline parameters (module docstring) for ``mesh.edges``."""
    K0 = long_term_young_modulus(material) * van_gelder_weights(mesh)
    ratio, tau = prony_arms(material)
    k1, k2 = ratio[0] * K0, ratio[1] * K0
    zero = np.zeros_like(K0)
    return ConnectorParams(K0=K0, a=zero, b=zero.copy(), k1=k1, b1=tau[0] * k1,
                           k2=k2, b2=tau[1] * k2)
