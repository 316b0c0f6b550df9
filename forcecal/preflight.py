"""Mesh preflight: what a mesh and its support imply, found in seconds before any FE work.

:func:`mesh_preflight` measures a checked mesh (:func:`forcecal.mesh.check_mesh` has already
refused inverted, zero-volume, duplicate, unused and disconnected elements, naming them) and
its clamp, and says what each number implies:

* counts and edge lengths; the tet quality by the **normalised radius ratio**
  ``q = 3 r_in / r_circ`` (:func:`tet_quality`: 1 for the regular tet, 0 for a flat one; a
  sliver has four well-spread vertices in one plane and a small q although no edge is short),
  with the worst tets named;
* the face-connected parts (:func:`face_connected_parts`): tets that share a face are one
  part; parts that touch only through a vertex or an edge are hinged there;
* whether the support holds the body (:func:`check_support`): the small-strain stiffness of
  linear tets with the scene's long-term material, the fixed vertices clamped. A rigid or
  hinged motion that costs no energy (a zero eigenvalue) is refused before any FE work
  (:class:`~forcecal.errors.StabilityError` naming the vertices that move and the parts they
  belong to); the linear sag under the scene's gravity says whether the body can carry its
  weight (it is a lower bound of the FE sag: linear tets lock, and a slender body softens
  under load);
* the explicit particle step the stiffest closed-form connector allows
  (:func:`particle_step_estimate`) and the FE reference's estimated cost
  (:func:`forcecal.cost.fe_work`).

Pure numpy/scipy: it runs in the reference stage (logged, stored in ``reference.h5``) and
in the report (``report.json`` key ``mesh_preflight``).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spl
from scipy.sparse.csgraph import connected_components

from forcecal.errors import StabilityError
from forcecal.mesh import TET_FACES, TetMesh
from forcecal.scene import MaterialSection, Scene

log = logging.getLogger(__name__)

QUALITY_MEASURE = ("normalised radius ratio 3 r_in / r_circ (1: regular tet, 0: flat; "
                   "below 0.1: a sliver or a needle)")
#: tets below this quality are counted as badly shaped (a P2 element on one is nearly singular)
POOR_QUALITY = 0.1
#: how many of the worst tets the preflight names
N_WORST = 5
#: a stiffness eigenvalue below this fraction of the largest one (bounded by Gershgorin) is a
#: motion that costs no energy: round-off puts a free body's rigid modes near 1e-16, while the
#: softest physical mode seen (a 1446-vertex figure with thin limbs at 2.4 kPa) is 5e-9
RIGID_MODE_RATIO = 1e-11
#: a linear sag under full gravity above this fraction of the body's bounding-box diagonal means
#: the support does not hold the body (the FE sag check refuses 0.5; the linear estimate is
#: smaller than the FE sag, see the module docstring)
SAG_LIMIT = 0.25


def tet_quality(mesh: TetMesh) -> np.ndarray:
    """(T,) normalised radius ratio ``3 r_in / r_circ`` of every tet [1]: 1 for the regular
    tet, tending to 0 for a flat one (sliver, needle, cap or wedge).

    ``r_in = 3 V / A`` (A the total face area), ``r_circ = |a^2 (b x c) + b^2 (c x a) +
    c^2 (a x b)| / (12 V)`` with a, b, c the edges from vertex 0.
    """
    x = mesh.vertices[mesh.tets]
    a, b, c = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
    volume = np.abs(mesh.signed_volumes)
    p = x[:, TET_FACES]  # (T, 4, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(p[:, :, 1] - p[:, :, 0], p[:, :, 2] - p[:, :, 0]),
                                axis=2).sum(axis=1)
    sq = lambda v: np.einsum("ij,ij->i", v, v)[:, None]  # noqa: E731 - squared lengths
    circ = np.linalg.norm(sq(a) * np.cross(b, c) + sq(b) * np.cross(c, a)
                          + sq(c) * np.cross(a, b), axis=1) / (12.0 * volume)
    return 9.0 * volume / (area * circ)


def face_connected_parts(mesh: TetMesh) -> tuple[int, np.ndarray]:
    """(number of parts, (T,) part of each tet): tets sharing a face belong to one part."""
    faces = np.sort(mesh.tets[:, TET_FACES].reshape(-1, 3), axis=1)
    _, face_id = np.unique(faces, axis=0, return_inverse=True)
    tet_of = np.repeat(np.arange(mesh.n_tets), 4)
    graph = sp.coo_matrix((np.ones(len(face_id)), (tet_of, face_id.ravel()))).tocsr()
    n_parts, labels = connected_components(graph @ graph.T, directed=False)
    return int(n_parts), labels


def small_strain_stiffness(mesh: TetMesh, shear_modulus: float, bulk_modulus: float
                           ) -> sp.csr_matrix:
    """(3N, 3N) stiffness of linear tets, isotropic small-strain material [N/m]; dof ``3 v + k``
    is component k of vertex v.

    Args:
        shear_modulus: mu [Pa].
        bulk_modulus: K [Pa] (Lame's lambda = K - 2 mu / 3).
    """
    x = mesh.vertices[mesh.tets]
    edges = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=2)
    inv = np.linalg.inv(edges)  # rows: gradients of the barycentric coordinates 1..3
    grad = np.concatenate([-inv.sum(axis=1, keepdims=True), inv], axis=1)  # (T, 4, 3)
    n_tets = mesh.n_tets
    strain = np.zeros((n_tets, 6, 12))  # Voigt: xx, yy, zz, 2xy, 2yz, 2zx
    for k in range(4):
        gx, gy, gz = grad[:, k, 0], grad[:, k, 1], grad[:, k, 2]
        col = 3 * k
        strain[:, 0, col], strain[:, 1, col + 1], strain[:, 2, col + 2] = gx, gy, gz
        strain[:, 3, col], strain[:, 3, col + 1] = gy, gx
        strain[:, 4, col + 1], strain[:, 4, col + 2] = gz, gy
        strain[:, 5, col], strain[:, 5, col + 2] = gz, gx
    lame = bulk_modulus - 2.0 * shear_modulus / 3.0
    elastic = np.zeros((6, 6))
    elastic[:3, :3] = lame
    elastic[np.arange(3), np.arange(3)] += 2.0 * shear_modulus
    elastic[np.arange(3, 6), np.arange(3, 6)] = shear_modulus
    local = np.einsum("tji,jk,tkl->til", strain, elastic, strain) * np.abs(
        mesh.signed_volumes)[:, None, None]
    dofs = (3 * mesh.tets[:, :, None] + np.arange(3)).reshape(n_tets, 12)
    rows = np.repeat(dofs, 12, axis=1).ravel()
    cols = np.tile(dofs, (1, 12)).ravel()
    n = 3 * mesh.n_vertices
    return sp.coo_matrix((local.ravel(), (rows, cols)), shape=(n, n)).tocsr()


@dataclass(frozen=True)
class SupportCheck:
    """What the linear check of the support found.

    Attributes:
        rigid_modes: motions that cost no energy with the fixed vertices clamped (0 when the
            support holds the body; at least 1 otherwise, up to the 6 searched).
        free_vertices: (K,) vertices those motions move (empty when ``rigid_modes == 0``).
        softest_ratio: the smallest stiffness eigenvalue over the Gershgorin bound of the
            largest [1].
        sag_m: largest vertex displacement of the linear sag under the scene's gravity [m]
            (nan when there are rigid modes).
        sag_vertex: the vertex where it is largest (-1 when there are rigid modes).
        body_size_m: diagonal of the mesh's bounding box [m].
        seconds: wall time of the check [s].
        displacement: (N, 3) the linear sag of every vertex [m] (None with rigid modes).
    """
    rigid_modes: int
    free_vertices: np.ndarray
    softest_ratio: float
    sag_m: float
    sag_vertex: int
    body_size_m: float
    seconds: float
    displacement: np.ndarray | None = None

    @property
    def holds(self) -> bool:
        """No rigid mode, and a linear sag below :data:`SAG_LIMIT` x the body's size."""
        return self.rigid_modes == 0 and self.sag_m <= SAG_LIMIT * self.body_size_m


def long_term_moduli(material: MaterialSection) -> tuple[float, float]:
    """(mu_inf, kappa) [Pa]: the long-term small-strain shear modulus ``g_inf 2 (C10 + C01)``
    and the bulk modulus (the Prony series relaxes the isochoric part only)."""
    return material.long_term_factor * material.shear_modulus, material.kappa


def check_support(mesh: TetMesh, fixed: np.ndarray, material: MaterialSection,
                  gravity: np.ndarray, n_modes: int = 6) -> SupportCheck:
    """Whether the clamped ``fixed`` vertices hold the body (module docstring): the softest
    motions of the small-strain stiffness with them clamped, and the linear sag under
    ``gravity`` (3,) [m/s^2] with the long-term material (:func:`long_term_moduli`).

    Costs a sparse factorisation of 3 x (free vertices) unknowns: 0.3 s at 1446 vertices.
    """
    start = time.perf_counter()
    stiffness = small_strain_stiffness(mesh, *long_term_moduli(material))
    free = np.ones(mesh.n_vertices, dtype=bool)
    free[np.asarray(fixed, dtype=np.int64)] = False
    free_dofs = np.nonzero(np.repeat(free, 3))[0]
    k_free = stiffness[free_dofs][:, free_dofs].tocsc()
    largest = float(np.abs(k_free).sum(axis=1).max())  # Gershgorin bound of the top eigenvalue
    values, vectors = _softest_modes(k_free, min(n_modes, len(free_dofs)), largest)
    zero = values < RIGID_MODE_RATIO * largest
    size = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    if zero.any():
        motion = np.zeros(3 * mesh.n_vertices)
        motion[free_dofs] = np.sqrt((vectors[:, zero] ** 2).sum(axis=1))
        per_vertex = np.linalg.norm(motion.reshape(-1, 3), axis=1)
        moving = np.nonzero(per_vertex > 1e-3 * per_vertex.max())[0]
        return SupportCheck(int(zero.sum()), moving, float(values[0] / largest), math.nan, -1,
                            size, time.perf_counter() - start)
    load = np.outer(mesh.lumped_masses(material.density), np.asarray(gravity, float)).ravel()
    sag = np.zeros(3 * mesh.n_vertices)
    sag[free_dofs] = spl.splu(k_free).solve(load[free_dofs])
    norms = np.linalg.norm(sag.reshape(-1, 3), axis=1)
    vertex = int(np.argmax(norms))
    return SupportCheck(0, np.zeros(0, np.int64), float(values[0] / largest),
                        float(norms[vertex]), vertex, size, time.perf_counter() - start,
                        sag.reshape(-1, 3))


def _softest_modes(matrix: sp.csc_matrix, k: int, largest: float) -> tuple[np.ndarray,
                                                                              np.ndarray]:
    """The ``k`` smallest eigenvalues (ascending) and eigenvectors of a symmetric positive
    semi-definite matrix: dense for small ones, else shift-invert Lanczos about a small
    negative shift (the matrix may be singular: that is what is looked for)."""
    n = matrix.shape[0]
    if n <= 300:
        values, vectors = scipy.linalg.eigh(matrix.toarray(), subset_by_index=[0, k - 1])
        return values, vectors
    start = np.random.default_rng(0).uniform(0.5, 1.5, n)  # reproducible
    try:
        values, vectors = spl.eigsh(matrix, k=k, sigma=-1e-9 * largest, which="LM", v0=start)
    except spl.ArpackNoConvergence as exc:  # the modes it found (the softest come first)
        values, vectors = exc.eigenvalues, exc.eigenvectors
        if not len(values):
            raise StabilityError(f"the support check's eigenvalue solve (n = {n}) did not "
                                 f"converge: {exc}") from None
    order = np.argsort(values)
    return values[order], vectors[:, order]


def particle_step_estimate(mesh: TetMesh, material: MaterialSection) -> tuple[float, int]:
    """(step [s], edge index): the explicit step a single closed-form connector allows,
    smallest over the edges: ``2 / sqrt(k_e (1/m_i + 1/m_j))`` with the instantaneous
    Van Gelder stiffness ``k_e = E_0 sum V_t / L_e^2`` (``E_0 = 9 kappa mu_0 / (3 kappa +
    mu_0)``) and the lumped masses. An upper bound of the model's stable step (a particle
    has several connectors): short edges and flat tets around light particles set it."""
    mu, kappa = material.shear_modulus, material.kappa
    young = 9.0 * kappa * mu / (3.0 * kappa + mu)
    k = young * mesh.edge_tet_volume / mesh.edge_lengths ** 2
    mass = mesh.lumped_masses(material.density)
    e = mesh.edges
    step = 2.0 / np.sqrt(k * (1.0 / mass[e[:, 0]] + 1.0 / mass[e[:, 1]]))
    edge = int(np.argmin(step))
    return float(step[edge]), edge


def mesh_preflight(scene: Scene, mesh: TetMesh, fixed: np.ndarray, *,
                   support: SupportCheck | None = None) -> dict:
    """The preflight of ``mesh`` clamped at ``fixed`` for ``scene``, as stored in
    ``report.json`` (``mesh_preflight``) and ``reference.h5``; ``support``: a
    :func:`check_support` result already computed (else computed here).

    Keys: ``vertices``, ``tets``, ``edges``, ``fixed_vertices``, ``edge_min_m``,
    ``edge_mean_m``, ``edge_max_m``, ``quality_measure``, ``quality_min``,
    ``quality_median``, ``poor_tets`` (quality below ``poor_quality``), ``worst_tets``
    (``[{"tet", "quality", "vertices"}]``, worst first), ``parts`` (face-connected),
    ``support`` (the :class:`SupportCheck` numbers), ``particle_dt_s`` and
    ``particle_dt_edge`` (:func:`particle_step_estimate`), ``fe_cost``
    (``vertex_steps``, ``core_seconds``: :func:`forcecal.cost.fe_work`,
    :func:`forcecal.cost.fe_core_seconds`), ``implications``
    (one sentence per finding), ``warnings`` (those of them that are), ``seconds``.
    """
    from forcecal.cost import fe_core_seconds, fe_work

    start = time.perf_counter()
    fixed = np.asarray(fixed, dtype=np.int64)
    if support is None:
        support = check_support(mesh, fixed, scene.material, scene.gravity.acceleration)
    lengths = mesh.edge_lengths
    quality = tet_quality(mesh)
    worst = np.argsort(quality, kind="stable")[:N_WORST]
    n_parts, labels = face_connected_parts(mesh)
    dt, dt_edge = particle_step_estimate(mesh, scene.material)
    work = sum(fe_work(scene, mesh.n_vertices, len(mesh.edges)).values())
    out = {
        "vertices": mesh.n_vertices, "tets": mesh.n_tets, "edges": len(mesh.edges),
        "fixed_vertices": len(fixed),
        "edge_min_m": float(lengths.min()), "edge_mean_m": float(lengths.mean()),
        "edge_max_m": float(lengths.max()),
        "quality_measure": QUALITY_MEASURE,
        "quality_min": float(quality.min()), "quality_median": float(np.median(quality)),
        "poor_quality": POOR_QUALITY, "poor_tets": int((quality < POOR_QUALITY).sum()),
        "worst_tets": [{"tet": int(t), "quality": float(quality[t]),
                        "vertices": mesh.tets[t].tolist()} for t in worst],
        "parts": n_parts,
        "support": {"holds": support.holds, "rigid_modes": support.rigid_modes,
                    "free_vertices": len(support.free_vertices),
                    "softest_eigenvalue_ratio": support.softest_ratio,
                    "linear_sag_m": None if math.isnan(support.sag_m) else support.sag_m,
                    "linear_sag_vertex": support.sag_vertex,
                    "body_size_m": support.body_size_m, "sag_limit": SAG_LIMIT,
                    "seconds": support.seconds},
        "particle_dt_s": dt, "particle_dt_edge": mesh.edges[dt_edge].tolist(),
        "fe_cost": {"vertex_steps": float(work),
                    "core_seconds": float(fe_core_seconds(scene, work, mesh.n_vertices,
                                                          len(mesh.edges)))},
    }
    said = _implications(out, mesh, labels, quality, lengths[dt_edge])
    out["implications"] = [sentence for _, sentence in said]
    out["warnings"] = [sentence for warn, sentence in said if warn]
    out["seconds"] = time.perf_counter() - start + support.seconds
    return out


def _implications(pf: dict, mesh: TetMesh, labels: np.ndarray, quality: np.ndarray,
                  dt_edge_length: float) -> list[tuple[bool, str]]:
    """(whether it is a warning, sentence): one per finding of the preflight ``pf`` (what the
    number means for a run)."""
    said: list[tuple[bool, str]] = []
    worst = pf["worst_tets"][0]
    if pf["poor_tets"]:
        said.append((True, f"{pf['poor_tets']} tets have a quality below {POOR_QUALITY:g} "
                     f"(worst: tet {worst['tet']}, {worst['quality']:.3g}, vertices "
                     f"{worst['vertices']}): quadratic (P2/TH) elements on them are nearly "
                     "singular; an FE step that fails near them is a mesh problem"))
    if pf["parts"] > 1:
        largest = sorted(np.bincount(labels).tolist(), reverse=True)[:6]
        said.append((True, f"{pf['parts']} face-connected parts ({largest} tets) joined only "
                     f"through {_part_contacts(mesh, labels)}: each is hinged there unless "
                     "clamped on its own"))
    s = pf["support"]
    if s["linear_sag_m"] is not None:
        sag, size = s["linear_sag_m"] * 1e3, s["body_size_m"] * 1e3
        ratio = sag / size
        if s["holds"]:
            said.append((False, f"linear sag under full gravity {sag:.3g} mm at vertex "
                         f"{s['linear_sag_vertex']} ({ratio:.2g} x the body's size {size:.3g} "
                         "mm): the support holds the body"))
        else:
            said.append((True, f"the support does not hold the body under its weight: the "
                         f"linear sag under full gravity is {sag:.3g} mm at vertex "
                         f"{s['linear_sag_vertex']}, {ratio:.2g} x the body's size {size:.3g} "
                         "mm (a lower bound of the FE sag): the material is too soft for this "
                         "shape and clamp; the FE gravity test is expected to fail (it runs "
                         "first; the force checks still run)"))
    dt = pf["particle_dt_s"]
    said.append((False, f"the explicit particle step can be at most about {dt * 1e6:.3g} us "
                 f"(closed-form connector {pf['particle_dt_edge']}, length "
                 f"{dt_edge_length * 1e3:.3g} mm; shortest edge {pf['edge_min_m'] * 1e3:.3g} "
                 f"mm): at least {math.ceil(1e-3 / dt)} substeps per 1 ms haptic step"))
    cost = pf["fe_cost"]
    said.append((False, f"FE reference: about {cost['vertex_steps']:.3g} vertex-steps, "
                 f"about {cost['core_seconds'] / 60:.3g} core-minutes"))
    return said


def _part_contacts(mesh: TetMesh, labels: np.ndarray) -> str:
    """The vertices shared by tets of different face-connected parts, as words."""
    owner = np.full(mesh.n_vertices, -1)
    shared = np.zeros(mesh.n_vertices, dtype=bool)
    for tet, part in zip(mesh.tets, labels):
        for v in tet:
            if owner[v] == -1:
                owner[v] = part
            elif owner[v] != part:
                shared[v] = True
    ids = np.nonzero(shared)[0]
    return f"{len(ids)} shared vertices ({ids[:10].tolist()})"


def support_refusal(check: SupportCheck, mesh: TetMesh, fixed: np.ndarray) -> StabilityError:
    """The error naming why the support does not hold the body (rigid modes): the vertices
    that move freely and the face-connected parts they belong to."""
    n_parts, labels = face_connected_parts(mesh)
    moving = check.free_vertices
    on_tet = np.isin(mesh.tets, moving).all(axis=1)
    parts = np.unique(labels[on_tet])
    held = np.unique(labels[np.isin(mesh.tets, fixed).any(axis=1)])
    where = (f"; they fill face-connected part(s) {parts.tolist()} of {n_parts}, "
             f"{'none' if not len(np.intersect1d(parts, held)) else 'some'} of them clamped"
             if len(parts) else "")
    hinge = (f" ({_part_contacts(mesh, labels)} join the parts)" if n_parts > 1 else "")
    return StabilityError(
        f"the support does not hold the body: with the {len(fixed)} fixed vertices clamped, "
        f"{check.rigid_modes} motion(s) cost no energy (small-strain stiffness eigenvalue "
        f"{check.softest_ratio:.2g} x the largest); they move {len(moving)} vertices (e.g. "
        f"{moving[:10].tolist()}){where}{hinge}: clamp every part (fixed.axis, fixed.side, "
        "fixed.tolerance) or mesh it as one solid")


def run_preflight(scene: Scene, mesh: TetMesh, fixed: np.ndarray) -> dict:
    """:func:`mesh_preflight`, logged; refuses a support with rigid modes before any FE work.

    Raises:
        StabilityError: a motion of the body costs no energy (:func:`support_refusal`).
    """
    support = check_support(mesh, fixed, scene.material, scene.gravity.acceleration)
    if support.rigid_modes:
        raise support_refusal(support, mesh, fixed)
    pf = mesh_preflight(scene, mesh, fixed, support=support)
    log.info("mesh preflight (%.2g s): %d vertices, %d tets, %d edges (min/mean/max %.3g / %.3g "
             "/ %.3g mm), tet quality (%s) min %.3g, median %.3g, %d face-connected part(s)",
             pf["seconds"], pf["vertices"], pf["tets"], pf["edges"], pf["edge_min_m"] * 1e3,
             pf["edge_mean_m"] * 1e3, pf["edge_max_m"] * 1e3, "radius ratio",
             pf["quality_min"], pf["quality_median"], pf["parts"])
    for sentence in pf["implications"]:
        (log.warning if sentence in pf["warnings"] else log.info)("mesh preflight: %s",
                                                                   sentence)
    return pf
