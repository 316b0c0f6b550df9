"""The spaces the optimisers search, and how a point in them becomes connector parameters.

Global parameters (one value for every connector), :class:`GlobalParams`:
``K0`` [N/m], ``alpha = a/K0`` and ``beta = b/K0`` [1] (so
``K(eps) = K0 (1 + alpha eps + beta eps^2)``), arm stiffnesses ``k1, k2`` [N/m]
and relaxation times ``tau1 < tau2`` [s] (``b_i = tau_i k_i``); with the
volume term (scene key ``particle.volume``) the volume stiffness ``kv`` [Pa] of
every tet (0 = the term is off), and when it relaxes (``particle.volume =
"viscoelastic"``) its arms' stiffnesses ``kv1, kv2`` [Pa] (0 = elastic), whose
relaxation times are the springs' ``tau1, tau2`` (``bv_i = tau_i kv_i``). With
``calibration.global_shape = "van_gelder"`` (:func:`global_shape`) connector c's
stiffnesses are these values times a fixed geometric factor ``w_c`` (mean 1), so the
set is still one value per parameter.

Optimiser coordinates are dimensionless and O(1) per unit change:

* static:  ``x = (alpha s, beta s^2)`` with ``s`` the strain scale of the
  experiments (:class:`StrainRange`), i.e. the relative change of K at the
  largest strain; with the volume term a third coordinate ``log(kv/K0 x 1 m)``.
  K0 is not searched: the static curve of a uniform network with ``a = alpha
  K0, b = beta K0`` (and ``kv = (kv/K0) K0``) is exactly proportional to K0
  (every force scales, the equilibrium shape does not), so K0 is the
  closed-form least-squares factor for each (alpha, beta, kv/K0);
* relaxation: ``y = (log k1, log tau1, log k2, log tau2)``; optimising log tau
  rather than log b keeps the two arms identifiable, and ``tau1 < tau2`` is
  required (the swapped half is the same model). With the volume arms two more,
  ``log(kv1/kv), log(kv2/kv)``: the volume term's relative arm stiffnesses (its
  Prony-like ratios; ``kv`` is fixed by the static fit, as ``K0`` is).

Why the volume arms share the springs' relaxation times: the FE material has one
relaxation spectrum (its Prony times), acting on the deviatoric stress; on coarse
linear tets both the springs and the per-tet volume term carry that shear-like
stiffness, so both relax with its times, each with its own share (its ratios
``k_i/K0`` and ``kv_i/kv``). Times of their own would add two coordinates the
surface relaxation curves cannot separate from the springs' (a sum of four
exponentials fitted to curves that two describe: an ill-conditioned Prony fit),
while the split of each arm's stiffness between springs and volume term is
identified as the static fit identifies ``kv/K0``: the two terms load the
indented neighbourhood differently.

Local tuning (:class:`Rings`) gives every calibration point j offsets in the
same coordinates that apply to its first ring (the connectors incident to j):
static ``z_j = (log s_K0, s dalpha, s^2 dbeta)``, relaxation
``z_j = (log s_k1, log s_tau1, log s_k2, log s_tau2)``. A connector in several
rings gets the mean of their offsets, i.e. the geometric mean of the
multiplicative factors (arithmetic mean of the additive alpha/beta offsets).
The factors are searched within ``[1/MAX_LOCAL_FACTOR, MAX_LOCAL_FACTOR]``
(:func:`check_offsets`): a local correction compensates the discretisation
around one point, and a direction the point's curve barely constrains must not
carry a connector off to 1e-40 or 1e8 times the global value, which no other
experiment then survives.

A parameter set is *infeasible* (cost = +inf, reason logged) if some spring's
tangent stiffness ``d(K dx)/d(dx) = K0 + 2 a eps + 3 b eps^2`` falls below the
floor ``calibration.stiffness_floor x`` the global K0 anywhere in the strain
range (the secant ``K(eps)``, the tangent's mean over ``[0, eps]``, then stays
above it too), or some connector has ``tau1 >= tau2``. The floor keeps local
tuning from making nearly stiffness-less springs, or springs whose force stops
rising with the elongation: they fit the indentation curves at the calibration
points but leave the organ without support elsewhere, and the gravity sag then
has no equilibrium (two 8-point calibrations of the mesh study, with secant
minima of 0.02 % and 0.5 % of K0 and negative tangents, failed so; with the
floor both sag and release). The FE material keeps the global spring's tangent
above 93 % of K0 on the default liver's range and the local factors only
compensate the discretisation, so a 10-fold softening (floor 0.1) is generous.
Local tuning also keeps every spring's tangent below ``calibration.stiffness_ceiling``
times the global spring's largest on the connector's range (one decade above, as the floor
is one below; :func:`calibration.core.local_validity` says why).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.sparse as sp

from calibration.baseline import van_gelder_weights
from forcecal.errors import ParameterError
from forcecal.mesh import TetMesh
from particle.params import ConnectorParams

STATIC_DIM = 3
RELAXATION_DIM = 4
#: largest local factor on K0, k_i and tau_i (either way) of one point's ring offsets
MAX_LOCAL_FACTOR = 100.0
#: which offset coordinates are log factors, per local phase
LOG_OFFSETS = {"static": np.array([True, False, False]),
               "relaxation": np.array([True, True, True, True])}


@dataclass(frozen=True)
class StrainRange:
    """Connector strains the experiments reach (linear-network estimate times a margin).

    Attributes:
        low: most compressive strain [1] (< 0).
        high: largest tensile strain [1] (> 0).
    """
    low: float
    high: float

    @property
    def scale(self) -> float:
        """Largest strain magnitude [1]: the unit of the static optimiser coordinates."""
        return max(-self.low, self.high)

    @property
    def bounds(self) -> tuple[float, float]:
        return (self.low, self.high)


@dataclass(frozen=True)
class GlobalParams:
    """One parameter set for every connector (module docstring for the meaning)."""
    K0: float
    alpha: float
    beta: float
    k1: float
    tau1: float
    k2: float
    tau2: float
    kv: float = 0.0
    kv1: float = 0.0
    kv2: float = 0.0

    @property
    def has_volume(self) -> bool:
        return self.kv > 0.0

    @property
    def has_volume_arms(self) -> bool:
        """True when the volume term relaxes (its arms' stiffnesses kv1, kv2 > 0)."""
        return self.kv1 > 0.0

    def connector_params(self, n_connectors: int, shape: np.ndarray | None = None
                         ) -> ConnectorParams:
        """Connector parameters (and, with the volume term, one kv (1,) for every tet).

        ``shape`` None: the same values for every connector (the paper's global set);
        (E,) positive factors (:func:`global_shape`): connector c's stiffnesses ``K0, a, b,
        k_i, b_i`` times ``shape[c]``, its spring's ``K(eps)/K0`` and its relaxation times
        the same for all.
        """
        params = ConnectorParams.uniform(n_connectors, K0=self.K0, a=self.alpha * self.K0,
                                         b=self.beta * self.K0, k1=self.k1,
                                         b1=self.tau1 * self.k1, k2=self.k2,
                                         b2=self.tau2 * self.k2)
        if shape is not None:
            params = params.scaled(check_shape(shape, n_connectors))
        return dataclasses.replace(params, **self.volume_arrays)

    @property
    def volume_arrays(self) -> dict[str, np.ndarray | None]:
        """The volume term's fields of :class:`ConnectorParams`, each (1,) (one value for every
        tet) or None: ``kv`` (None if the term is off) and ``kv1, bv1, kv2, bv2`` (None if
        it is elastic; ``bv_i = tau_i kv_i``)."""
        arms = self.has_volume_arms
        return {"kv": np.array([self.kv]) if self.has_volume else None,
                "kv1": np.array([self.kv1]) if arms else None,
                "bv1": np.array([self.tau1 * self.kv1]) if arms else None,
                "kv2": np.array([self.kv2]) if arms else None,
                "bv2": np.array([self.tau2 * self.kv2]) if arms else None}

    def static_coordinates(self, strain: StrainRange) -> np.ndarray:
        s = strain.scale
        x = [self.alpha * s, self.beta * s * s]
        return np.array(x + [np.log(self.kv / self.K0)] if self.has_volume else x)

    def with_static_coordinates(self, x: np.ndarray, K0: float, strain: StrainRange
                                ) -> "GlobalParams":
        """The static coordinates ``x`` with ``K0`` [N/m]; the volume arms keep their ratios
        ``kv_i/kv`` (the static curves are long-term: they see kv alone)."""
        s = strain.scale
        kv = float(K0 * np.exp(x[2])) if self.has_volume else 0.0
        ratio = kv / self.kv if self.has_volume_arms else 0.0
        return dataclasses.replace(self, K0=float(K0), alpha=float(x[0]) / s,
                                   beta=float(x[1]) / (s * s), kv=kv, kv1=ratio * self.kv1,
                                   kv2=ratio * self.kv2)

    def relaxation_coordinates(self) -> np.ndarray:
        y = np.log([self.k1, self.tau1, self.k2, self.tau2])
        if not self.has_volume_arms:
            return y
        return np.r_[y, np.log([self.kv1 / self.kv, self.kv2 / self.kv])]

    def with_relaxation_coordinates(self, y: np.ndarray) -> "GlobalParams":
        k1, tau1, k2, tau2 = np.exp(np.asarray(y[:4], dtype=float))
        volume = {}
        if self.has_volume_arms:
            volume = {f"kv{i + 1}": float(self.kv * np.exp(y[4 + i])) for i in range(2)}
        return dataclasses.replace(self, k1=float(k1), tau1=float(tau1), k2=float(k2),
                                   tau2=float(tau2), **volume)

    def as_dict(self) -> dict[str, float]:
        return {k: float(getattr(self, k)) for k in self.__dataclass_fields__}


def global_shape(mesh: TetMesh, name: str) -> np.ndarray | None:
    """The (E,) per-connector factors of the global fit's stiffnesses, mean 1, or None.

    ``"uniform"``: None, every connector the same (the paper's global tuning).
    ``"van_gelder"``: proportional to the closed-form baseline's spring of each edge,
    ``sum_{t containing c} V_t / L_c^2`` (:mod:`calibration.baseline`): the share of
    the surrounding material each connector stands for. One set of uniform springs on
    an irregular mesh is stiffer where edges are short and many, so its force varies
    with the local mesh as well as with the material; Van Gelder's weights make a
    uniform dilation store the continuum's energy in every tet. The global fit still
    searches one value per parameter (their scale), so both shapes have the same
    number of fitted parameters and their global costs compare directly.
    """
    if name == "uniform":
        return None
    if name == "van_gelder":
        w = van_gelder_weights(mesh)
        return w / w.mean()
    raise ParameterError(f"unknown calibration.global_shape {name!r}; one of 'uniform', "
                         "'van_gelder'")


def connector_floor(stiffness_floor: float, K0: float,
                    shape: np.ndarray | None) -> float | np.ndarray:
    """Smallest allowed spring tangent stiffness [N/m]: ``stiffness_floor`` x the global
    ``K0``, per connector times its ``shape`` factor (a scalar when the set is uniform)."""
    return stiffness_floor * K0 * (1.0 if shape is None else shape)


def check_shape(shape: np.ndarray, n_connectors: int) -> np.ndarray:
    """``shape`` as (E,) float64, refused unless it has E finite positive factors."""
    shape = np.asarray(shape, dtype=float)
    if shape.shape != (n_connectors,) or not np.all(np.isfinite(shape) & (shape > 0.0)):
        raise ParameterError(f"a global shape needs {n_connectors} finite positive factors, got "
                             f"shape {shape.shape}, min {np.min(shape) if shape.size else None}")
    return shape


@dataclass(frozen=True, eq=False)
class Rings:
    """First rings of the calibration points and how their offsets reach the connectors.

    Attributes:
        members: tuple of Pc (R_j,) int64 arrays, each point's ring (:func:`build_rings`).
        weights: (E, Pc) CSR float64, ``1/n_c`` where connector c is in ring ``order[k]``
            (column k) and belongs to ``n_c`` rings (rows of connectors in no ring are empty).
        order: (Pc,) int64, the points by increasing vertex id: a connector's mean over its
            rings is summed in that order, so it does not depend on the points' order (a sum
            of three or more offsets rounds differently in another order).
    """
    members: tuple[np.ndarray, ...]
    weights: sp.csr_matrix
    order: np.ndarray

    @property
    def n_points(self) -> int:
        return len(self.members)

    def connector_offsets(self, z: np.ndarray) -> np.ndarray:
        """(E, d) mean offset of each connector's rings for per-point offsets z (Pc, d)."""
        return np.asarray(self.weights @ np.asarray(z)[self.order])


def build_rings(mesh: TetMesh, points: np.ndarray,
                footprints: Sequence[np.ndarray] | None = None) -> Rings:
    """Rings of ``points`` (vertex ids) in ``mesh``: the connectors the indenter of each point
    loads directly, i.e. those with exactly one end among the particles it holds.

    ``footprints`` (one array of held particles per point, a flat punch) or None (each
    point holds itself: its ring is the connectors incident to it, the paper's first
    ring). A connector with both ends in a footprint moves rigidly with the punch and
    carries no force in that point's experiment: in the first ring of a punch's centre
    (6-8 of its 6-12 connectors on the punch scene) its offsets would have no data to fit.
    """
    e = mesh.edges
    held = [np.atleast_1d(p) for p in points] if footprints is None else list(footprints)
    if len(held) != len(points):
        raise ValueError(f"{len(held)} footprints for {len(points)} points")
    members = tuple(np.nonzero(np.isin(e[:, 0], h) != np.isin(e[:, 1], h))[0] for h in held)
    order = np.argsort(np.asarray(points), kind="stable")
    rank = np.empty(len(points), dtype=np.int64)
    rank[order] = np.arange(len(points))
    rows = np.concatenate(members)
    cols = np.repeat(rank, [len(m) for m in members])
    count = np.bincount(rows, minlength=len(e)).astype(float)
    weights = sp.csr_matrix((1.0 / count[rows], (rows, cols)), shape=(len(e), len(points)))
    return Rings(members=members, weights=weights, order=order)


def local_params(glob: GlobalParams, rings: Rings, strain: StrainRange,
                 z_static: np.ndarray, z_relaxation: np.ndarray,
                 shape: np.ndarray | None = None) -> ConnectorParams:
    """Per-connector parameters: global values modified by the ring offsets (module docstring).

    Args:
        z_static: (Pc, 3) static offsets of the calibration points.
        z_relaxation: (Pc, 4) relaxation offsets.
        shape: the global fit's (E,) per-connector factors (:func:`global_shape`) or None.
    """
    s = strain.scale
    o = rings.connector_offsets(z_static)
    r = rings.connector_offsets(z_relaxation)
    K0 = glob.K0 * np.exp(o[:, 0])
    alpha = glob.alpha + o[:, 1] / s
    beta = glob.beta + o[:, 2] / (s * s)
    k1, tau1 = glob.k1 * np.exp(r[:, 0]), glob.tau1 * np.exp(r[:, 1])
    k2, tau2 = glob.k2 * np.exp(r[:, 2]), glob.tau2 * np.exp(r[:, 3])
    params = ConnectorParams(K0=K0, a=alpha * K0, b=beta * K0, k1=k1, b1=tau1 * k1,
                             k2=k2, b2=tau2 * k2, **glob.volume_arrays)
    return params if shape is None else params.scaled(check_shape(shape, len(K0)))


def check_offsets(phase: str, z: np.ndarray) -> None:
    """Raise :class:`ParameterError` if a log-factor offset of one point (``phase`` "static" or
    "relaxation", ``z`` its offsets) leaves ``[1/MAX_LOCAL_FACTOR, MAX_LOCAL_FACTOR]``."""
    z = np.asarray(z, dtype=float)
    out = np.nonzero(LOG_OFFSETS[phase] & ~(np.abs(z) <= np.log(MAX_LOCAL_FACTOR)))[0]
    if len(out):
        i = int(out[0])
        raise ParameterError(f"local {phase} offset {i} is a factor {np.exp(z[i]):.3g}, outside "
                             f"[1/{MAX_LOCAL_FACTOR:g}, {MAX_LOCAL_FACTOR:g}] of the global value")


def check_spring_range(params: ConnectorParams, low: float | np.ndarray,
                       high: float | np.ndarray, floor: float | np.ndarray, where: str,
                       ceiling: float | np.ndarray | None = None) -> None:
    """Raise :class:`ParameterError` naming the first spring whose tangent stiffness
    ``K0 + 2 a eps + 3 b eps^2`` falls below ``floor`` [N/m], or rises above ``ceiling`` [N/m]
    (if given), somewhere on its strain range ``[low, high]`` (each a scalar or (E,));
    ``where`` names the range in the message."""
    tangent, top = params.extreme_tangent_stiffness((low, high))
    low, high, floor = (np.broadcast_to(np.asarray(v, dtype=float), tangent.shape)
                        for v in (low, high, floor))
    soft = np.nonzero(~(tangent >= floor))[0]
    if len(soft):
        e = int(soft[0])
        raise ParameterError(f"connector {e}: spring tangent stiffness K0 + 2 a eps + 3 b eps^2 "
                             f"reaches {tangent[e]:g} N/m < the floor {floor[e]:g} N/m {where} "
                             f"[{low[e]:.3g}, {high[e]:.3g}] ({len(soft)} connectors)")
    if ceiling is None:
        return
    ceiling = np.broadcast_to(np.asarray(ceiling, dtype=float), top.shape)
    stiff = np.nonzero(~(top <= ceiling))[0]
    if len(stiff):
        e = int(stiff[0])
        raise ParameterError(f"connector {e}: spring tangent stiffness K0 + 2 a eps + 3 b eps^2 "
                             f"reaches {top[e]:g} N/m > the ceiling {ceiling[e]:g} N/m {where} "
                             f"[{low[e]:.3g}, {high[e]:.3g}] ({len(stiff)} connectors)")


def check_feasible(params: ConnectorParams, strain: StrainRange,
                   floor: float | np.ndarray) -> None:
    """Raise :class:`ParameterError` if ``params`` is outside the searched region.

    ``floor`` [N/m]: the smallest spring tangent stiffness allowed in the strain range
    (a scalar, or (E,) per connector).
    """
    params.validate(strain.bounds)
    check_spring_range(params, strain.low, strain.high, floor, "in the strain range")
    order = np.nonzero(params.b1 / params.k1 >= params.b2 / params.k2)[0]
    if len(order):
        raise ParameterError(f"connector {int(order[0])}: tau1 >= tau2 "
                             f"({len(order)} connectors); the arms must stay ordered")
