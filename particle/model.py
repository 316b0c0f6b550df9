"""The particle model: an immutable :class:`Model` built by :class:`ModelBuilder`; :class:`State`.

One particle per mesh vertex, one Maxwell-Solid connector per mesh edge
(Basafa & Farahmand). A connector joining particles ``i`` and ``j`` with rest
length ``L0`` and elongation ``dx = |x_j - x_i| - L0`` (strain ``eps = dx/L0``)
carries the tension

    F = K(eps) dx + F_arm1 + F_arm2,        K(eps) = K0 + a eps + b eps^2,

along ``(x_j - x_i)/|x_j - x_i|`` (positive = tension, pulls ``i`` toward ``j``).
Each Maxwell arm (spring ``k_i`` in series with a dashpot ``b_i``, ``tau_i =
b_i/k_i``) obeys ``dF/dt = k_i d(dx)/dt - F/tau_i`` and is advanced by the
one-step recursion ``F^t = r_i F^{t-1} + c_i (dx^t - dx^{t-1})``; see
:meth:`ConnectorParams.arm_recursion` for the two coefficient choices.

Style follows NVIDIA Warp's ``warp.sim``: the Model holds flat, read-only
arrays; the State holds what changes in time; integrators and solvers are
separate (:mod:`particle.integrator`, :mod:`particle.statics`).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from forcecal.errors import MeshError, ParameterError
from forcecal.mesh import TetMesh
from forcecal.problem import Problem
from particle.volume import check_kv, signed_volumes, tet_edge_connectors, tet_name

log = logging.getLogger(__name__)

PARAM_NAMES = ("K0", "a", "b", "k1", "b1", "k2", "b2")
N_ARMS = 2
# a strain range: one (lo, hi) pair [1] for every connector, or per-connector (lo (E,), hi (E,))
StrainBounds = tuple[float | np.ndarray, float | np.ndarray]


def _frozen(arr: np.ndarray, dtype) -> np.ndarray:
    out = np.array(arr, dtype=dtype, order="C")  # own copy, so freezing cannot surprise a caller
    out.setflags(write=False)
    return out


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


@dataclass(frozen=True, eq=False)
class ConnectorParams:
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
            model). It does not relax (the arms act on the connectors only). A
            (1,) array is one value for every tet (a global fit's): a Model stores
            it broadcast to (T,).

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

    def __post_init__(self) -> None:
        arrays = [np.atleast_1d(np.asarray(getattr(self, n), dtype=np.float64))
                  for n in PARAM_NAMES]
        shapes = {a.shape for a in arrays}
        if len(shapes) != 1 or arrays[0].ndim != 1:
            raise ParameterError("connector parameters must be seven 1-D arrays of one length, got "
                                 + ", ".join(f"{n} {a.shape}" for n, a in zip(PARAM_NAMES, arrays)))
        for name, arr in zip(PARAM_NAMES, arrays):
            object.__setattr__(self, name, _frozen(arr, np.float64))
        if self.kv is not None:
            kv = np.atleast_1d(np.asarray(self.kv, dtype=np.float64))
            if kv.ndim != 1:
                raise ParameterError(f"kv must be a 1-D array (one value per tet), got {kv.shape}")
            object.__setattr__(self, "kv", _frozen(kv, np.float64))

    @classmethod
    def uniform(cls, n_connectors: int, *, K0: float, a: float = 0.0, b: float = 0.0,
                k1: float, b1: float, k2: float, b2: float) -> "ConnectorParams":
        """The same values for every one of ``n_connectors`` connectors."""
        values = dict(K0=K0, a=a, b=b, k1=k1, b1=b1, k2=k2, b2=b2)
        return cls(**{n: np.full(n_connectors, float(v)) for n, v in values.items()})

    @property
    def n_connectors(self) -> int:
        return self.K0.shape[0]

    @property
    def has_volume(self) -> bool:
        """True when the volume term is on (``kv`` given)."""
        return self.kv is not None

    def connectors(self, index: np.ndarray) -> "ConnectorParams":
        """The parameters of connectors ``index`` (reordered/selected); ``kv`` kept as is."""
        return ConnectorParams(**{name: getattr(self, name)[index] for name in PARAM_NAMES},
                               kv=self.kv)

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

    @property
    def is_linear(self) -> bool:
        """True when a = b = 0 everywhere: K(eps) = K0 and the linear kernels apply."""
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
        """Raise :class:`ParameterError` naming the first non-physical connector or tet; return self.

        Refused: non-finite values, K0 <= 0, k_i <= 0, b_i <= 0, kv <= 0 (naming
        the tet, with its particles if ``tets`` (T, 4) is given), and a secant
        stiffness K(eps) <= 0 anywhere in ``strain_range`` (checked exactly at
        the quadratic's ends and vertex). ``strain_range`` is one (lo, hi) pair
        or per-connector (lo (E,), hi (E,)) arrays [1], checked by
        :func:`connector_strain_bounds`. ``edges`` (E, 2), if given, lets the
        message name the connector's two particles.
        """
        lo, hi = connector_strain_bounds(strain_range, self.n_connectors, edges)

        def where(e: int) -> str:
            return connector_name(e, edges)

        for name in PARAM_NAMES:
            bad = np.nonzero(~np.isfinite(getattr(self, name)))[0]
            if len(bad):
                raise ParameterError(f"{where(bad[0])}: {name} = {getattr(self, name)[bad[0]]} "
                                     "is not finite")
        for name in ("K0", "k1", "b1", "k2", "b2"):
            bad = np.nonzero(getattr(self, name) <= 0.0)[0]
            if len(bad):
                raise ParameterError(f"{where(bad[0])}: {name} = {getattr(self, name)[bad[0]]:g} "
                                     "must be > 0")
        if self.kv is not None:
            check_kv(self.kv, tets)
        kmin, _ = self.extreme_stiffness((lo, hi))
        bad = np.nonzero(kmin <= 0.0)[0]
        if len(bad):
            e = bad[0]
            raise ParameterError(f"{where(e)}: spring stiffness K(eps) = K0 + a eps + b eps^2 "
                                 f"(K0={self.K0[e]:g}, a={self.a[e]:g}, b={self.b[e]:g}) reaches "
                                 f"{kmin[e]:g} N/m <= 0 in the strain range [{lo[e]:g}, "
                                 f"{hi[e]:g}]")
        return self

    def arm_recursion(self, dt: float, *, exact: bool = False) -> tuple[np.ndarray, np.ndarray]:
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
        if not dt > 0.0:
            raise ParameterError(f"arm recursion: time step {dt} s must be > 0")
        k = self.arm_stiffness
        tau = self.arm_tau
        if exact:
            r = np.exp(-dt / tau)
            c = k * tau * (-np.expm1(-dt / tau)) / dt  # 1 - r without cancellation for dt << tau
        else:
            r = tau / (tau + dt)
            c = k * r
        return r, c


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


@dataclass(frozen=True, eq=False)
class Model:
    """Immutable particle model: flat arrays only, shared by every run and solver.

    Attributes:
        rest_positions: (N, 3) float64, particle positions in the undeformed state [m].
        edges: (E, 2) int64, particle ids (i, j) of each connector, i != j.
        rest_lengths: (E,) float64, connector rest lengths L0 [m].
        masses: (N,) float64, particle masses [kg] (> 0).
        fixed: (N,) bool, True for clamped particles (never move).
        params: connector parameters (:class:`ConnectorParams`, E entries; its
            ``kv`` (T,) switches the volume term on).
        tets: (T, 4) int64, particle ids of each tetrahedron of the volume term,
            positively oriented; every tet edge must be a connector. (0, 4) if none.
        rest_volumes: (T,) float64, rest volume V0 of each tet [m^3] (> 0); computed
            from ``rest_positions`` when not given.
        free_nodes: (Nf,) int64, ids of the particles that are not fixed.
        incidence_ptr: (N + 1,) int64, CSR row pointer of the particle -> connector incidence.
        incidence_edge: (2E,) int64, connector ids touching each particle (CSR order).
    """
    rest_positions: np.ndarray
    edges: np.ndarray
    rest_lengths: np.ndarray
    masses: np.ndarray
    fixed: np.ndarray
    params: ConnectorParams
    tets: np.ndarray | None = None
    rest_volumes: np.ndarray | None = None
    free_nodes: np.ndarray = field(init=False)
    incidence_ptr: np.ndarray = field(init=False)
    incidence_edge: np.ndarray = field(init=False)
    tet_connectors: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        for name, dtype in (("rest_positions", np.float64), ("edges", np.int64),
                            ("rest_lengths", np.float64), ("masses", np.float64),
                            ("fixed", bool)):
            object.__setattr__(self, name, _frozen(getattr(self, name), dtype))
        tets = np.zeros((0, 4), np.int64) if self.tets is None else np.asarray(self.tets)
        tets = _frozen(tets.reshape(-1, 4), np.int64)
        bad = np.nonzero(np.any((tets < 0) | (tets >= self.n_particles), axis=1))[0]
        if len(bad):
            raise MeshError(f"{tet_name(bad[0], tets)} refers to unknown particles; particles are "
                            f"0..{self.n_particles - 1}")
        volumes = (signed_volumes(self.rest_positions, tets) if self.rest_volumes is None
                   else np.asarray(self.rest_volumes, dtype=np.float64).reshape(-1))
        if volumes.shape != (len(tets),):
            raise MeshError(f"{len(volumes)} rest volumes for {len(tets)} tets")
        bad = np.nonzero(~(volumes > 0.0) | ~np.isfinite(volumes))[0]
        if len(bad):
            raise MeshError(f"{tet_name(bad[0], tets)}: rest volume {volumes[bad[0]]:.3g} m^3 "
                            "must be > 0 (inverted or degenerate tet)")
        object.__setattr__(self, "tets", tets)
        object.__setattr__(self, "rest_volumes", _frozen(volumes, np.float64))
        object.__setattr__(self, "tet_connectors", _frozen(
            tet_edge_connectors(tets, self.edges) if len(tets) else np.zeros((0, 6)), np.int64))
        object.__setattr__(self, "params", self._check_params(self.params))
        ends = self.edges.ravel()
        order = np.argsort(ends, kind="stable")
        ptr = np.zeros(self.n_particles + 1, dtype=np.int64)
        ptr[1:] = np.cumsum(np.bincount(ends, minlength=self.n_particles))
        object.__setattr__(self, "free_nodes", _frozen(np.nonzero(~self.fixed)[0], np.int64))
        object.__setattr__(self, "incidence_ptr", _frozen(ptr, np.int64))
        object.__setattr__(self, "incidence_edge", _frozen(order // 2, np.int64))

    @property
    def n_particles(self) -> int:
        return self.rest_positions.shape[0]

    @property
    def n_connectors(self) -> int:
        return self.edges.shape[0]

    @property
    def n_tets(self) -> int:
        return self.tets.shape[0]

    @property
    def has_volume(self) -> bool:
        """True when the volume term is on (the parameters carry ``kv``)."""
        return self.params.kv is not None

    def _check_params(self, params: ConnectorParams) -> ConnectorParams:
        """``params`` checked against this model, a (1,) kv broadcast to one per tet."""
        if params.n_connectors != self.n_connectors:
            raise ParameterError(f"parameters have {params.n_connectors} entries but the model "
                                 f"has {self.n_connectors} connectors")
        n_tets = len(self.tets)
        if params.kv is not None and params.kv.shape != (n_tets,):
            if params.kv.shape != (1,) or n_tets == 0:
                raise ParameterError(f"kv has {params.kv.shape[0]} entries but the model has "
                                     f"{n_tets} tets (the volume term needs one kv per tet, or "
                                     "one for all)")
            params = dataclasses.replace(params, kv=np.full(n_tets, params.kv[0]))
        return params

    def with_params(self, params: ConnectorParams) -> "Model":
        """A new Model with other connector parameters (and kv), sharing every topology array."""
        params = self._check_params(params)
        new = object.__new__(Model)
        for f in dataclasses.fields(Model):
            object.__setattr__(new, f.name, getattr(self, f.name))
        object.__setattr__(new, "params", params)
        return new

    def renumbered(self, order: np.ndarray) -> tuple["Model", np.ndarray]:
        """The same model with particle ``order[k]`` as particle k; returns (model, connectors).

        The connectors are re-sorted by their new ends (i < j, lexicographic, as
        a mesh's edges), with their rest lengths and parameters; ``connectors``
        (E,) int64 is the old id of each new connector (for a state's
        ``arm_force``/``dx_prev``). Physics unchanged: only the summation order of
        the particles' forces differs. ``order`` must be a permutation of 0..N-1
        (e.g. :func:`spatial_order`).
        """
        n = self.n_particles
        order = np.asarray(order)
        if (order.shape != (n,) or not np.issubdtype(order.dtype, np.integer)
                or not np.array_equal(np.sort(order), np.arange(n))):
            raise ParameterError(f"a particle order must be a permutation of 0..{n - 1}")
        new_id = np.empty(n, dtype=np.int64)
        new_id[order] = np.arange(n)
        ends = np.sort(new_id[self.edges], axis=1)
        connectors = np.lexsort((ends[:, 1], ends[:, 0]))
        return Model(rest_positions=self.rest_positions[order], edges=ends[connectors],
                     rest_lengths=self.rest_lengths[connectors], masses=self.masses[order],
                     fixed=self.fixed[order], params=self.params.connectors(connectors),
                     tets=new_id[self.tets], rest_volumes=self.rest_volumes), connectors

    def state(self) -> "State":
        """A fresh State: at rest in the undeformed configuration, arms unloaded, t = 0."""
        return State(x=self.rest_positions.copy(), x_prev=self.rest_positions.copy(),
                     arm_force=np.zeros((self.n_connectors, N_ARMS)),
                     dx_prev=np.zeros(self.n_connectors), t=0.0)

    def check_nodes(self, nodes: np.ndarray, what: str, *, movable: bool = True) -> np.ndarray:
        """(k,) int64 particle ids, checked: in range, and (if ``movable``) not fixed."""
        nodes = np.atleast_1d(np.asarray(nodes))
        if nodes.ndim != 1 or not np.issubdtype(nodes.dtype, np.integer):
            raise MeshError(f"{what}: particle ids must be a 1-D list of integers, got {nodes!r}")
        nodes = nodes.astype(np.int64)
        bad = nodes[(nodes < 0) | (nodes >= self.n_particles)]
        if len(bad):
            raise MeshError(f"{what}: unknown particle(s) {bad.tolist()}; the model has particles "
                            f"0..{self.n_particles - 1}")
        if movable and np.any(self.fixed[nodes]):
            raise MeshError(f"{what}: particle(s) {nodes[self.fixed[nodes]].tolist()} are fixed "
                            "and cannot be moved")
        return nodes

    def incident_min_length(self, nodes: np.ndarray) -> np.ndarray:
        """(k,) float64, the shortest rest length among the connectors touching each node [m]."""
        nodes = self.check_nodes(nodes, "incident_min_length", movable=False)
        return np.array([self.rest_lengths[self.incidence_edge[self.incidence_ptr[n]:
                                                               self.incidence_ptr[n + 1]]].min()
                         for n in nodes])


def spatial_order(model: Model) -> np.ndarray:
    """(N,) particle ids sorted along the longest axis of the model's bounding box (stable).

    Renumbered so (:meth:`Model.renumbered`), a contiguous block of connectors
    (sorted by their ends) is a slab of the body: the multi-threaded step's
    blocks then share only the particles near the slabs' faces, which is what
    its threads exchange every step (see :class:`particle.integrator.Run`).
    """
    x = model.rest_positions
    return np.argsort(x[:, int(np.argmax(np.ptp(x, axis=0)))], kind="stable")


@dataclass
class State:
    """Mutable state of one run.

    Attributes:
        x: (N, 3) float64, positions at time t [m].
        x_prev: (N, 3) float64, positions one step earlier (position Verlet) [m];
            equal to ``x`` for a state at rest.
        arm_force: (E, 2) float64, Maxwell arm forces at the last completed step [N].
        dx_prev: (E,) float64, connector elongation at the last completed step [m].
        t: time [s].
        dt: step that ``x_prev`` lags ``x`` by [s]; None for a state at rest that
            has not been stepped (the integrator then uses the start-up step).
    """
    x: np.ndarray
    x_prev: np.ndarray
    arm_force: np.ndarray
    dx_prev: np.ndarray
    t: float = 0.0
    dt: float | None = None

    def copy(self) -> "State":
        return State(self.x.copy(), self.x_prev.copy(), self.arm_force.copy(),
                     self.dx_prev.copy(), self.t, self.dt)

    def displacement(self, model: Model) -> np.ndarray:
        """(N, 3) displacement from the rest positions [m]."""
        return self.x - model.rest_positions


class ModelBuilder:
    """Accumulates particles and connectors, then freezes them into a :class:`Model`.

    ``add_particle``/``add_connector`` add one item; ``add_particles``/
    ``add_connectors`` add arrays (what :func:`build_model` uses).
    """

    def __init__(self) -> None:
        self._x: list[np.ndarray] = []
        self._m: list[np.ndarray] = []
        self._fixed: list[np.ndarray] = []
        self._edges: list[np.ndarray] = []
        self._n = 0

    def add_particle(self, x: Sequence[float], mass: float, fixed: bool = False) -> int:
        """Add one particle at ``x`` [m] with ``mass`` [kg]; returns its id."""
        return int(self.add_particles(np.reshape(x, (1, 3)), [mass], [fixed])[0])

    def add_particles(self, x: np.ndarray, masses: np.ndarray,
                      fixed: np.ndarray | None = None) -> np.ndarray:
        """Add particles (k, 3) [m] with masses (k,) [kg]; returns their ids (k,)."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        m = np.asarray(masses, dtype=np.float64).reshape(-1)
        fx = np.zeros(len(x), bool) if fixed is None else np.asarray(fixed, dtype=bool).reshape(-1)
        if len(m) != len(x) or len(fx) != len(x):
            raise MeshError(f"add_particles: {len(x)} positions, {len(m)} masses, {len(fx)} "
                            "fixed flags")
        if not np.all(np.isfinite(x)):
            raise MeshError(f"add_particles: non-finite position for particle "
                            f"{self._n + int(np.nonzero(~np.isfinite(x).all(1))[0][0])}")
        bad = np.nonzero(~(m > 0) | ~np.isfinite(m))[0]
        if len(bad):
            raise ParameterError(f"particle {self._n + int(bad[0])}: mass {m[bad[0]]} must be a "
                                 "finite number > 0")
        ids = np.arange(self._n, self._n + len(x), dtype=np.int64)
        self._x.append(x)
        self._m.append(m)
        self._fixed.append(fx)
        self._n += len(x)
        return ids

    def add_connector(self, i: int, j: int) -> int:
        """Connect particles ``i`` and ``j``; returns the connector id."""
        return int(self.add_connectors(np.array([[i, j]]))[0])

    def add_connectors(self, pairs: np.ndarray) -> np.ndarray:
        """Add connectors (k, 2) between existing particles; returns their ids (k,)."""
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        first = sum(len(e) for e in self._edges)
        bad = np.nonzero(np.any((pairs < 0) | (pairs >= self._n), axis=1))[0]
        if len(bad):
            raise MeshError(f"connector {first + int(bad[0])} joins unknown particle(s) "
                            f"{pairs[bad[0]].tolist()}; particles are 0..{self._n - 1}")
        same = np.nonzero(pairs[:, 0] == pairs[:, 1])[0]
        if len(same):
            raise MeshError(f"connector {first + int(same[0])} joins particle {pairs[same[0], 0]} "
                            "to itself")
        self._edges.append(pairs)
        return np.arange(first, first + len(pairs), dtype=np.int64)

    def finalize(self, params: ConnectorParams, tets: np.ndarray | None = None) -> Model:
        """Freeze into a :class:`Model` (rest lengths and volumes from the current positions).

        ``tets`` (T, 4): particle ids of the volume term's tetrahedra (positively
        oriented, edges among the connectors), or None.
        """
        if self._n == 0 or not self._edges:
            raise MeshError("ModelBuilder.finalize: the model needs particles and connectors")
        x = np.concatenate(self._x)
        edges = np.concatenate(self._edges)
        key = np.sort(edges, axis=1)
        uniq, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
        if np.any(counts > 1):
            k = int(np.nonzero(counts > 1)[0][0])
            raise MeshError(f"particles {uniq[k].tolist()} are joined by {counts[k]} connectors")
        lengths = np.linalg.norm(x[edges[:, 1]] - x[edges[:, 0]], axis=1)
        zero = np.nonzero(lengths <= 1e-12 * max(1.0, float(np.ptp(x))))[0]
        if len(zero):
            raise MeshError(f"connector {int(zero[0])} (particles {edges[zero[0]].tolist()}) has "
                            "zero rest length")
        model = Model(rest_positions=x, edges=edges, rest_lengths=lengths,
                      masses=np.concatenate(self._m), fixed=np.concatenate(self._fixed),
                      params=params, tets=tets)
        log.debug("model: %d particles (%d fixed), %d connectors", model.n_particles,
                  int(model.fixed.sum()), model.n_connectors)
        return model


def build_model(problem_or_mesh: Problem | TetMesh, density: float, params: ConnectorParams,
                fixed: np.ndarray | None = None) -> Model:
    """Particle model of a mesh: one particle per vertex, one connector per ``mesh.edges`` row.

    Masses are lumped (each tet's mass split equally over its 4 vertices).
    ``fixed`` (vertex ids) defaults to ``problem.fixed`` for a Problem and to
    no fixed vertex for a bare mesh. The model always carries the mesh's tets
    (``Model.tets``, ``rest_volumes``); the volume term is on when ``params.kv`` is given.
    """
    if isinstance(problem_or_mesh, Problem):
        mesh = problem_or_mesh.mesh
        fixed = problem_or_mesh.fixed if fixed is None else fixed
    else:
        mesh = problem_or_mesh
    if not density > 0:
        raise ParameterError(f"density = {density} kg/m^3 must be > 0")
    mask = np.zeros(mesh.n_vertices, dtype=bool)
    if fixed is not None:
        fixed = np.asarray(fixed, dtype=np.int64)
        bad = fixed[(fixed < 0) | (fixed >= mesh.n_vertices)]
        if len(bad):
            raise MeshError(f"fixed vertices {bad.tolist()} are not vertices of the mesh")
        mask[fixed] = True
    builder = ModelBuilder()
    builder.add_particles(mesh.vertices, mesh.lumped_masses(density), mask)
    builder.add_connectors(mesh.edges)
    return builder.finalize(params, tets=mesh.tets)
