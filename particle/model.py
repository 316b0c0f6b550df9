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
from forcecal.mesh import TetMesh, check_mesh_arrays, vertex_ids
from forcecal.problem import Problem
from particle.nodal_volume import check_volume_element, node_rest_volumes
from particle.params import N_ARMS, VOLUME_ARM_NAMES, ConnectorParams, FrozenArrays, frozen_copy
from particle.volume import signed_volumes, tet_edge_connectors, tet_name

log = logging.getLogger(__name__)

@dataclass(frozen=True, eq=False)
class Model(FrozenArrays):
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
        volume_element: ``"tet"`` (the volume term's constraint per tet,
            :mod:`particle.volume`) or ``"nodal"`` (per particle over its one-ring,
            :mod:`particle.nodal_volume`; every particle must then belong to a tet). The
            parameters stay per tet either way.
        node_volumes: (N,) float64, each particle's rest volume ``V0_n = sum_{t ∋ n}
            V0_t / 4`` [m^3] (the nodal term's; 0 for a particle in no tet).
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
    volume_element: str = "tet"
    node_volumes: np.ndarray = field(init=False)
    free_nodes: np.ndarray = field(init=False)
    incidence_ptr: np.ndarray = field(init=False)
    incidence_edge: np.ndarray = field(init=False)
    tet_connectors: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        for name, dtype in (("rest_positions", np.float64), ("edges", np.int64),
                            ("rest_lengths", np.float64), ("masses", np.float64),
                            ("fixed", bool)):
            object.__setattr__(self, name, frozen_copy(getattr(self, name), dtype))
        tets, volumes = checked_tets(self.rest_positions, self.tets, self.rest_volumes)
        object.__setattr__(self, "tets", tets)
        object.__setattr__(self, "rest_volumes", frozen_copy(volumes, np.float64))
        check_volume_element(self.volume_element)
        node_volumes = node_rest_volumes(tets, volumes, self.n_particles)
        if self.volume_element == "nodal" and len(tets) and not np.all(node_volumes > 0.0):
            n = int(np.nonzero(~(node_volumes > 0.0))[0][0])
            raise MeshError(f"particle {n} belongs to no tet; the nodal volume element needs "
                            "every particle in one (its volume is a quarter of its tets')")
        object.__setattr__(self, "node_volumes", frozen_copy(node_volumes, np.float64))
        object.__setattr__(self, "tet_connectors", frozen_copy(
            tet_edge_connectors(tets, self.edges) if len(tets) else np.zeros((0, 6)), np.int64))
        object.__setattr__(self, "params", self._check_params(self.params))
        ptr, edge = incidence(self.edges, self.n_particles)
        object.__setattr__(self, "free_nodes", frozen_copy(np.nonzero(~self.fixed)[0], np.int64))
        object.__setattr__(self, "incidence_ptr", frozen_copy(ptr, np.int64))
        object.__setattr__(self, "incidence_edge", frozen_copy(edge, np.int64))

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

    @property
    def n_volume_elements(self) -> int:
        """The volume term's elements: its tets, or its particles when it is nodal (the rows
        of the volume arms' state)."""
        return self.n_particles if self.volume_element == "nodal" else self.n_tets

    def _check_params(self, params: ConnectorParams) -> ConnectorParams:
        """``params`` checked against this model, a (1,) kv broadcast to one per tet."""
        return params_for(params, self.n_connectors, len(self.tets))

    def with_params(self, params: ConnectorParams) -> "Model":
        """A new Model with other connector parameters (and kv), sharing every topology array."""
        params = self._check_params(params)
        new = object.__new__(Model)
        for f in dataclasses.fields(Model):
            object.__setattr__(new, f.name, getattr(self, f.name))
        object.__setattr__(new, "params", params)
        return new

    def with_volume_element(self, element: str) -> "Model":
        """The same model with the volume term on ``element`` (:attr:`volume_element`)."""
        return self if element == self.volume_element else dataclasses.replace(
            self, volume_element=element)

    def renumbered(self, order: np.ndarray) -> tuple["Model", np.ndarray]:
        """The same model with particle ``order[k]`` as particle k; returns (model, connectors).

        Connectors as :func:`renumbering` sorts them, with their rest lengths and
        parameters; ``connectors`` (E,) int64 is the old id of each new one (for a
        state's ``arm_force``/``dx_prev``). Physics unchanged: only the summation
        order of the forces differs. ``order``: e.g. :func:`spatial_order`.
        """
        order = np.asarray(order)
        new_id, edges, connectors = renumbering(self.edges, order, self.n_particles)
        return Model(rest_positions=self.rest_positions[order], edges=edges,
                     rest_lengths=self.rest_lengths[connectors], masses=self.masses[order],
                     fixed=self.fixed[order], params=self.params.connectors(connectors),
                     tets=new_id[self.tets], rest_volumes=self.rest_volumes,
                     volume_element=self.volume_element), connectors

    def state(self) -> "State":
        """A fresh State: at rest in the undeformed configuration, arms unloaded (the volume
        term's too, when it has arms), t = 0."""
        arms = self.params.has_volume_arms
        rows = self.n_volume_elements
        return State(x=self.rest_positions.copy(), x_prev=self.rest_positions.copy(),
                     arm_force=np.zeros((self.n_connectors, N_ARMS)),
                     dx_prev=np.zeros(self.n_connectors), t=0.0,
                     volume_arm=np.zeros((rows, N_ARMS)) if arms else None,
                     volume_prev=np.zeros(rows) if arms else None)

    def check_nodes(self, nodes: np.ndarray, what: str, *, movable: bool = True) -> np.ndarray:
        """(k,) int64 particle ids, checked: in range, and (if ``movable``) not fixed."""
        nodes = np.atleast_1d(np.asarray(nodes))
        if nodes.shape == (0,):  # [] is float64 to numpy: an empty list of ids all the same
            nodes = nodes.astype(np.int64)
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


def checked_tets(rest_positions: np.ndarray, tets: np.ndarray | None,
                 rest_volumes: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(tets (T, 4) int64, rest volumes (T,) [m^3]) of a model, read-only; the volumes
    computed from ``rest_positions`` when not given. :class:`MeshError` names the first tet
    with an unknown particle or a volume that is not > 0."""
    n = len(rest_positions)
    tets = np.zeros((0, 4), np.int64) if tets is None else vertex_ids(tets, "tets")
    if tets.size == 0:
        tets = tets.reshape(0, 4)
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise MeshError(f"tets must be a (T, 4) array of particle ids, got shape {tets.shape}")
    tets = frozen_copy(tets, np.int64)
    bad = np.nonzero(np.any((tets < 0) | (tets >= n), axis=1))[0]
    if len(bad):
        raise MeshError(f"{tet_name(bad[0], tets)} refers to unknown particles; particles are "
                        f"0..{n - 1}")
    volumes = (signed_volumes(rest_positions, tets) if rest_volumes is None
               else np.asarray(rest_volumes, dtype=np.float64).reshape(-1))
    if volumes.shape != (len(tets),):
        raise MeshError(f"{len(volumes)} rest volumes for {len(tets)} tets")
    bad = np.nonzero(~(volumes > 0.0) | ~np.isfinite(volumes))[0]
    if len(bad):
        raise MeshError(f"{tet_name(bad[0], tets)}: rest volume {volumes[bad[0]]:.3g} m^3 "
                        "must be > 0 (inverted or degenerate tet)")
    return tets, frozen_copy(volumes, np.float64)


def incidence(edges: np.ndarray, n_particles: int) -> tuple[np.ndarray, np.ndarray]:
    """(ptr (N + 1,), connector ids (2E,)): the particle -> connector incidence in CSR form."""
    ends = edges.ravel()
    order = np.argsort(ends, kind="stable")
    ptr = np.zeros(n_particles + 1, dtype=np.int64)
    ptr[1:] = np.cumsum(np.bincount(ends, minlength=n_particles))
    return ptr, order // 2


def params_for(params: ConnectorParams, n_connectors: int, n_tets: int) -> ConnectorParams:
    """``params`` checked against a model's connector and tet counts, a (1,) kv (and volume
    arms) broadcast to one per tet; :class:`ParameterError` when they do not fit."""
    if params.n_connectors != n_connectors:
        raise ParameterError(f"parameters have {params.n_connectors} entries but the model "
                             f"has {n_connectors} connectors")
    if params.kv is not None and params.kv.shape != (n_tets,):
        if params.kv.shape != (1,) or n_tets == 0:
            raise ParameterError(f"kv has {params.kv.shape[0]} entries but the model has "
                                 f"{n_tets} tets (the volume term needs one kv per tet, or "
                                 "one for all)")
        names = ("kv",) + (VOLUME_ARM_NAMES if params.has_volume_arms else ())
        params = dataclasses.replace(params, **{n: np.full(n_tets, getattr(params, n)[0])
                                                for n in names})
    return params


def renumbering(edges: np.ndarray, order: np.ndarray, n: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(new id of each particle (N,), new edges (E, 2), old id of each new connector (E,)) when
    particle ``order[k]`` becomes particle k; the connectors sorted by their new ends (i < j,
    lexicographic, as a mesh's edges). :class:`ParameterError` unless ``order`` is a
    permutation of 0..``n``-1."""
    if (order.shape != (n,) or not np.issubdtype(order.dtype, np.integer)
            or not np.array_equal(np.sort(order), np.arange(n))):
        raise ParameterError(f"a particle order must be a permutation of 0..{n - 1}")
    new_id = np.empty(n, dtype=np.int64)
    new_id[order] = np.arange(n)
    ends = np.sort(new_id[edges], axis=1)
    connectors = np.lexsort((ends[:, 1], ends[:, 0]))
    return new_id, ends[connectors], connectors


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
        volume_arm: (T, 2) float64, the volume term's arm pressures at the last completed
            step [Pa], or None: the model's volume term has no arms (or is off).
        volume_prev: (T,) float64, each tet's volume strain ``V/V0 - 1`` at the last
            completed step [1] (with ``volume_arm``; None likewise).
    """
    x: np.ndarray
    x_prev: np.ndarray
    arm_force: np.ndarray
    dx_prev: np.ndarray
    t: float = 0.0
    dt: float | None = None
    volume_arm: np.ndarray | None = None
    volume_prev: np.ndarray | None = None

    def copy(self) -> "State":
        return State(self.x.copy(), self.x_prev.copy(), self.arm_force.copy(),
                     self.dx_prev.copy(), self.t, self.dt,
                     None if self.volume_arm is None else self.volume_arm.copy(),
                     None if self.volume_prev is None else self.volume_prev.copy())

    def displacement(self, model: Model) -> np.ndarray:
        """(N, 3) displacement from the rest positions [m]."""
        return self.x - model.rest_positions


def check_gravity(gravity) -> np.ndarray | None:
    """``gravity`` as a (3,) float64 acceleration [m/s^2] (None stays None), checked: three
    finite numbers, else :class:`ParameterError` (the one check of every run and solver that
    takes a gravity vector)."""
    if gravity is None:
        return None
    try:
        g = np.asarray(gravity, dtype=np.float64)
    except (TypeError, ValueError):
        g = None
    if g is None or g.shape != (3,):
        shown = gravity.tolist() if isinstance(gravity, np.ndarray) else repr(gravity)
        raise ParameterError(f"gravity = {shown} must be 3 components (x, y, z) in m/s^2, "
                             "e.g. [0, 0, -9.81]")
    if not np.all(np.isfinite(g)):
        raise ParameterError(f"gravity {g.tolist()} m/s^2 is not finite")
    return g


@dataclass(frozen=True, eq=False)
class Prescribed:
    """Particles whose positions follow piecewise-linear keyframes (held after the last).

    Attributes:
        nodes: (k,) int64, prescribed particle ids.
        times: (K,) float64, increasing keyframe times [s].
        positions: (K, k, 3) float64, positions at the keyframes [m].
    """
    nodes: np.ndarray
    times: np.ndarray
    positions: np.ndarray

    def __post_init__(self) -> None:
        nodes = np.atleast_1d(np.asarray(self.nodes, dtype=np.int64))
        times = np.atleast_1d(np.asarray(self.times, dtype=np.float64))
        pos = np.asarray(self.positions, dtype=np.float64).reshape(len(times), len(nodes), 3)
        if len(times) == 0 or np.any(np.diff(times) <= 0) or not np.all(np.isfinite(pos)):
            raise ParameterError("prescribed motion needs increasing keyframe times and finite "
                                 "positions")
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "positions", pos)

    @classmethod
    def hold(cls, nodes, positions) -> "Prescribed":
        """Nodes held at fixed positions (k, 3) [m]."""
        return cls(nodes, [0.0], np.asarray(positions, dtype=np.float64)[None])


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

    def finalize(self, params: ConnectorParams, tets: np.ndarray | None = None,
                 volume_element: str = "tet") -> Model:
        """Freeze into a :class:`Model` (rest lengths and volumes from the current positions).

        ``tets`` (T, 4): particle ids of the volume term's tetrahedra (positively
        oriented, edges among the connectors), or None; ``volume_element``: the volume
        term's element (:attr:`Model.volume_element`).
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
                      params=params, tets=tets, volume_element=volume_element)
        log.debug("model: %d particles (%d fixed), %d connectors", model.n_particles,
                  int(model.fixed.sum()), model.n_connectors)
        return model


def check_density(density) -> float:
    """``density`` [kg/m^3] as a float if it is one finite number > 0, else
    :class:`ParameterError`."""
    try:
        value = float(np.asarray(density, dtype=np.float64).reshape(()))
    except (TypeError, ValueError):
        value = None
    if value is None or not (np.isfinite(value) and value > 0):
        shown = density.tolist() if isinstance(density, np.ndarray) else repr(density)
        raise ParameterError(f"density = {shown} kg/m^3 must be one finite number > 0 "
                             "(e.g. 1060.0)")
    return value


def build_model(problem_or_mesh: Problem | TetMesh, density: float, params: ConnectorParams,
                fixed: np.ndarray | None = None, volume_element: str = "tet") -> Model:
    """Particle model of a mesh: one particle per vertex, one connector per ``mesh.edges`` row.

    Masses are lumped (each tet's mass split equally over its 4 vertices).
    ``fixed`` (vertex ids) defaults to ``problem.fixed`` for a Problem and to
    no fixed vertex for a bare mesh. The model always carries the mesh's tets
    (``Model.tets``, ``rest_volumes``); the volume term is on when ``params.kv`` is given,
    its element ``volume_element`` (:attr:`Model.volume_element`).
    """
    if isinstance(problem_or_mesh, Problem):
        mesh = problem_or_mesh.mesh
        fixed = problem_or_mesh.fixed if fixed is None else fixed
    elif isinstance(problem_or_mesh, TetMesh):
        mesh = problem_or_mesh
    else:
        raise MeshError(f"build_model needs a Problem or a TetMesh, got "
                        f"{type(problem_or_mesh).__name__}")
    check_mesh_arrays(mesh)  # shapes, finite coordinates, ids in range; volumes: checked_tets
    density = check_density(density)
    mask = np.zeros(mesh.n_vertices, dtype=bool)
    if fixed is not None:
        fixed = vertex_ids(fixed, "fixed vertices").reshape(-1)
        bad = fixed[(fixed < 0) | (fixed >= mesh.n_vertices)]
        if len(bad):
            raise MeshError(f"fixed vertices {bad.tolist()} are not vertices of the mesh")
        mask[fixed] = True
    builder = ModelBuilder()
    builder.add_particles(mesh.vertices, mesh.lumped_masses(density), mask)
    builder.add_connectors(mesh.edges)
    return builder.finalize(params, tets=mesh.tets, volume_element=volume_element)
