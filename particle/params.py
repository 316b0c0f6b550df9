"""Connector parameters: the Maxwell-Solid constants of every connector and the strain ranges
they are checked on.

A connector of rest length ``L0`` and elongation ``dx`` (strain ``eps = dx/L0``)
carries ``F = K(eps) dx + F_arm1 + F_arm2`` with ``K(eps) = K0 + a eps + b eps^2``;
each Maxwell arm (spring ``k_i`` in series with a dashpot ``b_i``, ``tau_i =
b_i/k_i``) follows ``dF/dt = k_i d(dx)/dt - F/tau_i`` (:func:`arm_recursion`). The
optional volume term adds a stiffness ``kv`` per tetrahedron (:mod:`particle.volume`),
elastic or, with its own Maxwell arms ``kv_i, bv_i``, viscoelastic.
:class:`ConnectorParams` holds them as flat (E,) (and (T,)) arrays, immutable like the
:class:`~particle.model.Model` that carries them.
"""

from __future__ import annotations

import dataclasses
import operator
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from forcecal.errors import ParameterError
from particle.volume import check_kv

PARAM_NAMES = ("K0", "a", "b", "k1", "b1", "k2", "b2")
#: the volume term's Maxwell arms, per tet: stiffness [Pa] and viscosity [Pa s] of arm 1, 2
VOLUME_ARM_NAMES = ("kv1", "bv1", "kv2", "bv2")
N_ARMS = 2
# a strain range: one (lo, hi) pair [1] for every connector, or per-connector (lo (E,), hi (E,))
StrainBounds = tuple[float | np.ndarray, float | np.ndarray]


def frozen_copy(arr: np.ndarray, dtype) -> np.ndarray:
    """A read-only C-contiguous copy of ``arr`` as ``dtype`` (the immutable arrays of a model)."""
    out = np.array(arr, dtype=dtype, order="C")  # own copy, so freezing cannot surprise a caller
    out.setflags(write=False)
    return out


class FrozenArrays:
    """Base of the immutable dataclasses whose array fields are :func:`frozen_copy` s
    (:class:`ConnectorParams`, :class:`particle.model.Model`): an unpickled one freezes them
    again. Pickle does not keep numpy's write flag, so a model sent to a calibration worker
    would arrive with writable arrays: mutable where the original is not, and typed by numba
    as other signatures, every kernel then compiled a second time in each worker process with
    an empty cache (the static Newton loop alone ~5 s)."""

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)  # as pickle does without this method
        for f in dataclasses.fields(self):
            value = state.get(f.name)
            if isinstance(value, np.ndarray):
                value.setflags(write=False)


def _quadratic_extremes(c0: np.ndarray, c1: np.ndarray, c2: np.ndarray, lo, hi
                        ) -> tuple[np.ndarray, np.ndarray]:
    """(E,) min and max of ``c0 + c1 eps + c2 eps^2`` over ``[lo, hi]`` (floats or (E,) arrays).

    The extremes lie at the ends or at the vertex ``-c1/(2 c2)``. The vertex is
    inside exactly when the slope ``c1 + 2 c2 eps`` changes sign between the
    ends, which is decided without dividing, so a tiny ``c2`` cannot overflow;
    the division is done only where the vertex is inside (``|vertex| <
    max(|lo|, |hi|)`` there).
    """
    lo, hi = np.broadcast_arrays(np.asarray(lo, dtype=np.float64), np.asarray(hi, np.float64))

    def value(eps):
        return c0 + (c1 + c2 * eps) * eps

    at_lo, at_hi = value(lo), value(hi)
    inside = np.sign(c1 + 2.0 * c2 * lo) * np.sign(c1 + 2.0 * c2 * hi) < 0.0
    vertex = np.divide(-c1, 2.0 * c2, out=np.zeros_like(at_lo), where=inside)
    at_vertex = np.where(inside, value(vertex), at_lo)
    return (np.minimum(np.minimum(at_lo, at_hi), at_vertex),
            np.maximum(np.maximum(at_lo, at_hi), at_vertex))


def connector_name(e: int, edges: np.ndarray | None = None) -> str:
    """``connector e``, with its two particles when ``edges`` (E, 2) is given (for messages)."""
    if edges is None:
        return f"connector {int(e)}"
    return f"connector {int(e)} (particles {int(edges[e, 0])}-{int(edges[e, 1])})"


def connector_strain_bounds(strain_range: StrainBounds, n_connectors: int,
                            edges: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(lo (E,), hi (E,)) strains [1] of ``strain_range``: a (lo, hi) pair or per-connector arrays.

    The one check of a strain range, for parameter validation and the
    stability limit alike: every range must be finite, ordered (lo <= hi; a
    connector held at one strain has lo = hi) and above -1 (zero length),
    else :class:`ParameterError` names the first bad connector (with its
    particles if ``edges`` (E, 2) is given).
    """
    if len(strain_range) != 2:
        raise ParameterError(f"a strain range is a (lo, hi) pair, got {strain_range!r}")
    lo, hi = (np.asarray(b, dtype=np.float64) for b in strain_range)
    for bound in (lo, hi):
        if bound.shape not in ((), (n_connectors,)):
            raise ParameterError(f"strain range bounds of shape {bound.shape}: expected one "
                                 f"number or one per connector ({n_connectors},)")
    if lo.shape == hi.shape == () and not (np.isfinite(lo) and np.isfinite(hi) and lo > -1.0
                                           and lo <= hi):
        raise ParameterError(f"strain range [{lo:g}, {hi:g}] must be finite, ordered and above "
                             "-1 (a connector cannot shrink to zero length)")
    lo, hi = np.broadcast_to(lo, (n_connectors,)), np.broadcast_to(hi, (n_connectors,))
    bad = np.nonzero(~(np.isfinite(lo) & np.isfinite(hi) & (lo > -1.0) & (lo <= hi)))[0]
    if len(bad):
        e = int(bad[0])
        raise ParameterError(f"{connector_name(e, edges)}: strain range [{lo[e]:g}, {hi[e]:g}] "
                             "must be finite, ordered and above -1 (a connector cannot shrink to "
                             "zero length)")
    return lo, hi


def check_count(value, name: str, hint: str) -> int:
    """``value`` as an int if it is an integer >= 0 (numpy integers too), else
    :class:`ParameterError` naming ``name`` with ``hint`` (a float would be truncated)."""
    try:
        n = operator.index(value)
    except TypeError:
        n = -1
    if n < 0:
        raise ParameterError(f"{name} = {value!r} must be an integer >= 0 ({hint})")
    return n


@dataclass(frozen=True, eq=False)
class ConnectorParams(FrozenArrays):
    """Per-connector Maxwell-Solid parameters; seven (E,) float64 arrays.

    Attributes:
        K0: (E,) float64, small-strain stiffness of the elastic spring [N/m].
        a: (E,) float64, linear strain coefficient of the spring stiffness [N/m].
        b: (E,) float64, quadratic strain coefficient of the spring stiffness [N/m].
        k1, k2: (E,) float64, spring stiffness of Maxwell arm 1 and 2 [N/m].
        b1, b2: (E,) float64, dashpot coefficient of Maxwell arm 1 and 2 [N s/m].
        kv: (T,) float64, volume stiffness of each tetrahedron [Pa = N/m^2] (the
            elastic volume term of :mod:`particle.volume`, energy ``kv/2 V0 (V/V0 -
            1)^2``), or None: the volume term is off (the paper's springs-only
            model). Its long-term stiffness: with no volume arms it does not relax. A
            (1,) array is one value for every tet (a global fit's): a Model stores
            it broadcast to (T,).
        kv1, kv2: (T,) float64, stiffness of the volume term's Maxwell arm 1 and 2 [Pa],
            or None (all four None: the volume term is elastic). Each arm is a spring
            ``kv_i`` in series with a dashpot ``bv_i`` acting on the tet's volume strain
            ``V/V0 - 1`` (:mod:`particle.volume`), so the term's instantaneous stiffness
            is ``kv + kv1 + kv2`` and its long-term one ``kv``. (1,) broadcast like kv.
        bv1, bv2: (T,) float64, dashpot of the volume arms [Pa s] (``tau = bv_i/kv_i``).

    Instances are immutable; calibration builds new ones with
    ``dataclasses.replace(params, K0=...)`` (``kv=...`` likewise).
    """
    K0: np.ndarray
    a: np.ndarray
    b: np.ndarray
    k1: np.ndarray
    b1: np.ndarray
    k2: np.ndarray
    b2: np.ndarray
    kv: np.ndarray | None = None
    kv1: np.ndarray | None = None
    bv1: np.ndarray | None = None
    kv2: np.ndarray | None = None
    bv2: np.ndarray | None = None

    def __post_init__(self) -> None:
        arrays = [np.atleast_1d(np.asarray(getattr(self, n), dtype=np.float64))
                  for n in PARAM_NAMES]
        shapes = {a.shape for a in arrays}
        if len(shapes) != 1 or arrays[0].ndim != 1:
            raise ParameterError("connector parameters must be seven 1-D arrays of one length, got "
                                 + ", ".join(f"{n} {a.shape}" for n, a in zip(PARAM_NAMES, arrays)))
        for name, arr in zip(PARAM_NAMES, arrays):
            object.__setattr__(self, name, frozen_copy(arr, np.float64))
        if self.kv is not None:
            kv = np.atleast_1d(np.asarray(self.kv, dtype=np.float64))
            if kv.ndim != 1:
                raise ParameterError(f"kv must be a 1-D array (one value per tet), got {kv.shape}")
            object.__setattr__(self, "kv", frozen_copy(kv, np.float64))
        given = [n for n in VOLUME_ARM_NAMES if getattr(self, n) is not None]
        if given and (len(given) < len(VOLUME_ARM_NAMES) or self.kv is None):
            raise ParameterError(f"the volume term's arms need kv and all of "
                                 f"{', '.join(VOLUME_ARM_NAMES)}; got kv "
                                 f"{'None' if self.kv is None else 'given'} and {given}")
        for name in given:
            arm = np.atleast_1d(np.asarray(getattr(self, name), dtype=np.float64))
            if arm.shape != self.kv.shape:
                raise ParameterError(f"{name} of shape {arm.shape} does not match kv's "
                                     f"{self.kv.shape} (one value per tet, or one for all)")
            object.__setattr__(self, name, frozen_copy(arm, np.float64))

    @classmethod
    def uniform(cls, n_connectors: int, *, K0: float, a: float = 0.0, b: float = 0.0,
                k1: float, b1: float, k2: float, b2: float) -> "ConnectorParams":
        """The same values for every one of ``n_connectors`` connectors (an integer >= 0,
        else :class:`ParameterError`)."""
        n = check_count(n_connectors, "n_connectors", "e.g. len(problem.mesh.edges)")
        values = dict(K0=K0, a=a, b=b, k1=k1, b1=b1, k2=k2, b2=b2)
        return cls(**{n_: np.full(n, float(v)) for n_, v in values.items()})

    @property
    def n_connectors(self) -> int:
        return self.K0.shape[0]

    @property
    def has_volume(self) -> bool:
        """True when the volume term is on (``kv`` given)."""
        return self.kv is not None

    @property
    def has_volume_arms(self) -> bool:
        """True when the volume term has Maxwell arms (it relaxes)."""
        return self.kv1 is not None

    @property
    def volume_arm_stiffness(self) -> np.ndarray:
        """(T, 2) float64, the volume arms' stiffnesses (kv1, kv2) [Pa]."""
        return np.column_stack([self.kv1, self.kv2])

    @property
    def volume_arm_tau(self) -> np.ndarray:
        """(T, 2) float64, the volume arms' relaxation times (bv1/kv1, bv2/kv2) [s]."""
        return np.column_stack([self.bv1 / self.kv1, self.bv2 / self.kv2])

    @property
    def volume_instantaneous(self) -> np.ndarray:
        """(T,) float64, the volume term's instantaneous stiffness kv + kv1 + kv2 [Pa] (kv
        itself when it is elastic)."""
        return self.kv + self.kv1 + self.kv2 if self.has_volume_arms else self.kv

    def scaled(self, factor: np.ndarray) -> "ConnectorParams":
        """Every connector's stiffnesses and dashpots (``K0, a, b, k_i, b_i``) times its
        (E,) ``factor``; ``K(eps)/K0``, relaxation times and the volume term unchanged."""
        return dataclasses.replace(self, **{name: getattr(self, name) * factor
                                            for name in PARAM_NAMES})

    def connectors(self, index: np.ndarray) -> "ConnectorParams":
        """The parameters of connectors ``index`` (reordered/selected); the volume term's
        (per tet) kept as is."""
        return dataclasses.replace(self, **{name: getattr(self, name)[index]
                                            for name in PARAM_NAMES})

    @property
    def tau1(self) -> np.ndarray:
        """(E,) float64, relaxation time of arm 1, b1/k1 [s]."""
        return self.b1 / self.k1

    @property
    def tau2(self) -> np.ndarray:
        """(E,) float64, relaxation time of arm 2, b2/k2 [s]."""
        return self.b2 / self.k2

    @property
    def arm_stiffness(self) -> np.ndarray:
        """(E, 2) float64, arm spring stiffnesses (k1, k2) [N/m]."""
        return np.column_stack([self.k1, self.k2])

    @property
    def arm_tau(self) -> np.ndarray:
        """(E, 2) float64, arm relaxation times (tau1, tau2) [s]."""
        return np.column_stack([self.tau1, self.tau2])

    @cached_property
    def is_linear(self) -> bool:
        """True when a = b = 0 everywhere: K(eps) = K0 and the linear kernels apply (kept:
        the arrays are read-only copies, and every static solve asks)."""
        return not (np.any(self.a) or np.any(self.b))

    def stiffness(self, strain: np.ndarray) -> np.ndarray:
        """(E,) secant stiffness K(eps) = K0 + a eps + b eps^2 [N/m] at per-connector strains."""
        return self.K0 + self.a * strain + self.b * strain * strain

    def tangent_stiffness(self, strain: np.ndarray) -> np.ndarray:
        """(E,) tangent d(K dx)/d(dx) = K0 + 2 a eps + 3 b eps^2 [N/m]."""
        return self.K0 + 2.0 * self.a * strain + 3.0 * self.b * strain * strain

    def extreme_stiffness(self, strain_range: StrainBounds) -> tuple[np.ndarray, np.ndarray]:
        """(E,) min and max of the secant K0 + a eps + b eps^2 over ``strain_range`` [N/m].

        ``strain_range`` is one (lo, hi) pair or per-connector (lo (E,), hi (E,)) arrays.
        """
        return _quadratic_extremes(self.K0, self.a, self.b, *strain_range)

    def extreme_tangent_stiffness(self, strain_range: StrainBounds
                                  ) -> tuple[np.ndarray, np.ndarray]:
        """(E,) min and max of the tangent K0 + 2 a eps + 3 b eps^2 over ``strain_range`` [N/m]."""
        return _quadratic_extremes(self.K0, 2.0 * self.a, 3.0 * self.b, *strain_range)

    def validate(self, strain_range: StrainBounds = (-0.5, 0.5),
                 edges: np.ndarray | None = None, tets: np.ndarray | None = None
                 ) -> "ConnectorParams":
        """:func:`validate_params` of these parameters (returns them)."""
        return validate_params(self, strain_range, edges, tets)

    def arm_recursion(self, dt: float, *, exact: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """:func:`arm_recursion` of these parameters."""
        return arm_recursion(self, dt, exact=exact)

    def volume_arm_recursion(self, dt: float, *, exact: bool = False
                             ) -> tuple[np.ndarray, np.ndarray]:
        """(r, c), each (T, 2), of the volume arms' step ``P^t = r P^{t-1} + c (j^t -
        j^{t-1})`` in the volume strain ``j = V/V0 - 1`` (``c`` [Pa]): the connectors'
        recursion (:func:`arm_recursion`) with ``kv_i``, ``bv_i``."""
        r, c = volume_arm_recursions(self, np.array([check_step(dt)]), exact=exact)
        return r[0], c[0]


def same_values(p: ConnectorParams, q: ConnectorParams) -> bool:
    """True if every array of ``p`` and ``q`` (and kv, or its absence) is equal element by
    element."""
    if p is q:
        return True
    if (p.kv is None) != (q.kv is None) or p.has_volume_arms != q.has_volume_arms:
        return False
    names = (PARAM_NAMES + (() if p.kv is None else ("kv",))
             + (VOLUME_ARM_NAMES if p.has_volume_arms else ()))
    return all(np.array_equal(getattr(p, n), getattr(q, n)) for n in names)


def viscoelastic_params(n_connectors: int, K0: float = 50.0, *, a: float = 0.0, b: float = 0.0,
                        g: tuple[float, float] = (0.35, 0.25),
                        tau: tuple[float, float] = (0.05, 0.5)) -> ConnectorParams:
    """Uniform parameters whose arms hold the fractions ``g`` of the instantaneous stiffness.

    ``k_i = g_i/(1 - g_1 - g_2) K0`` (the Prony split of the FE material),
    ``b_i = tau_i k_i``.
    """
    g_inf = 1.0 - sum(g)
    k1, k2 = (gi / g_inf * K0 for gi in g)
    return ConnectorParams.uniform(n_connectors, K0=K0, a=a, b=b, k1=k1, b1=tau[0] * k1,
                                   k2=k2, b2=tau[1] * k2)


def validate_params(params: ConnectorParams, strain_range: StrainBounds = (-0.5, 0.5),
                    edges: np.ndarray | None = None, tets: np.ndarray | None = None
                    ) -> ConnectorParams:
    """Raise :class:`ParameterError` naming the first non-physical connector or tet; return
    ``params``.

    Refused: non-finite values, K0 <= 0, k_i <= 0, b_i <= 0, kv <= 0 and, with the
    volume arms, kv_i <= 0 or bv_i <= 0 (naming the tet, with its particles if
    ``tets`` (T, 4) is given), and a secant
    stiffness K(eps) <= 0 anywhere in ``strain_range`` (checked exactly at
    the quadratic's ends and vertex). ``strain_range`` is one (lo, hi) pair
    or per-connector (lo (E,), hi (E,)) arrays [1], checked by
    :func:`connector_strain_bounds`. ``edges`` (E, 2), if given, lets the
    message name the connector's two particles.
    """
    lo, hi = connector_strain_bounds(strain_range, params.n_connectors, edges)

    def where(e: int) -> str:
        return connector_name(e, edges)

    for name in PARAM_NAMES:
        bad = np.nonzero(~np.isfinite(getattr(params, name)))[0]
        if len(bad):
            raise ParameterError(f"{where(bad[0])}: {name} = {getattr(params, name)[bad[0]]} "
                                 "is not finite")
    for name in ("K0", "k1", "b1", "k2", "b2"):
        bad = np.nonzero(getattr(params, name) <= 0.0)[0]
        if len(bad):
            raise ParameterError(f"{where(bad[0])}: {name} = {getattr(params, name)[bad[0]]:g} "
                                 "must be > 0")
    if params.kv is not None:
        check_kv(params.kv, tets)
    if params.has_volume_arms:
        for name in VOLUME_ARM_NAMES:
            check_kv(getattr(params, name), tets, name)
    kmin, _ = params.extreme_stiffness((lo, hi))
    bad = np.nonzero(kmin <= 0.0)[0]
    if len(bad):
        e = bad[0]
        raise ParameterError(f"{where(e)}: spring stiffness K(eps) = K0 + a eps + b eps^2 "
                             f"(K0={params.K0[e]:g}, a={params.a[e]:g}, b={params.b[e]:g}) reaches "
                             f"{kmin[e]:g} N/m <= 0 in the strain range [{lo[e]:g}, "
                             f"{hi[e]:g}]")
    return params


def arm_recursion(params: ConnectorParams, dt: float, *, exact: bool = False
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients (r, c), each (E, 2), of ``F_arm^t = r F_arm^{t-1} + c (dx^t - dx^{t-1})``.

    ``exact=False`` is the paper's recursion, backward Euler of the Maxwell
    arm: ``F^t = k b/(k dt + b) ((dx^t - dx^{t-1}) + F^{t-1}/k)``, i.e.
    ``r = b/(b + k dt)``, ``c = k r``; used by the explicit runs, where
    ``dt/tau`` is tiny.

    ``exact=True`` integrates ``dF/dt = k d(dx)/dt - F/tau`` exactly for an
    elongation that is linear within the step: ``r = exp(-dt/tau)``, ``c =
    k tau (1 - r)/dt``. Both agree to first order in dt/tau; the exact form
    stays right for the coarse steps (dt up to ~tau) of the quasi-static
    relaxation path, where backward Euler would be badly off.
    """
    r, c = arm_recursions(params, np.array([check_step(dt)], dtype=np.float64), exact=exact)
    return r[0], c[0]


def check_step(dt: float) -> float:
    """``dt`` [s] if it is > 0, else :class:`ParameterError` (an arm recursion's step)."""
    if not dt > 0.0:
        raise ParameterError(f"arm recursion: time step {dt} s must be > 0")
    return dt


def arm_recursions(params: ConnectorParams, dts: np.ndarray, *, exact: bool = False
                   ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`arm_recursion` for S time steps ``dts`` (S,) [s] at once: (r, c), each (S, E, 2).

    One array expression instead of S calls (a relaxation curve's 50 sample steps
    cost 0.08 ms each as separate calls on 1,400 connectors); element by element
    the same operations, so the same numbers bit for bit.
    """
    return maxwell_recursions(params.arm_stiffness, params.arm_tau, dts, exact=exact)


def volume_arm_recursions(params: ConnectorParams, dts: np.ndarray, *, exact: bool = False
                          ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`arm_recursions` of the volume term's arms: (r, c), each (S, T, 2) (``c``
    [Pa] per unit volume strain)."""
    return maxwell_recursions(params.volume_arm_stiffness, params.volume_arm_tau, dts,
                              exact=exact)


def maxwell_recursions(k: np.ndarray, tau: np.ndarray, dts: np.ndarray, *,
                       exact: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(r, c), each (S, M, 2), of M pairs of Maxwell arms of stiffnesses ``k`` (M, 2) and
    relaxation times ``tau`` (M, 2) [s] for S time steps ``dts`` (S,) [s]: the one
    recursion of every arm (connectors and volume term; :func:`arm_recursion` says which
    form ``exact`` picks)."""
    dts = np.asarray(dts, dtype=np.float64).reshape(-1)
    if not np.all(dts > 0.0):
        raise ParameterError(f"arm recursion: time steps {dts[~(dts > 0.0)].tolist()} s must "
                             "be > 0")
    dt = dts[:, None, None]
    if exact:
        r = np.exp(-dt / tau)
        c = k * tau * (-np.expm1(-dt / tau)) / dt  # 1 - r without cancellation for dt << tau
    else:
        r = tau / (tau + dt)
        c = k * r
    return r, c
