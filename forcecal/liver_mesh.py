"""The generated liver: a deterministic gmsh model of a liver-like organ (two fused
ellipsoidal lobes on a flat base), its size and the checks of its mesh length made
before gmsh runs. :func:`gmsh_session` (the reproducible gmsh setup) and :func:`mesh_volume`
(its tets as arrays) serve every mesh the project generates."""

from __future__ import annotations

import functools
from contextlib import contextmanager
from typing import Iterator

import numpy as np

from forcecal.errors import MeshError
from forcecal.mesh import TetMesh, check_mesh, orient_tets


@contextmanager
def gmsh_session(name: str) -> Iterator:
    """The ``gmsh`` module, initialised with a model ``name``, for one meshing job; finalised
    on exit.

    One thread and a fixed random seed, terminal output off: the same geometry and
    sizes give the same mesh, bit for bit (the generated meshes are content-hashed).
    """
    import gmsh

    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.RandomSeed", 1)
        gmsh.model.add(name)
        yield gmsh
    finally:
        gmsh.finalize()


def mesh_volume(gmsh, length: float) -> tuple[np.ndarray, np.ndarray]:
    """Tet-mesh the synchronised geometry of a :func:`gmsh_session` at edge length ``length``
    (the geometry's units) in one physical volume: (V, 3) float64 vertices (those the tets
    use, in the order of gmsh's node tags) and (T, 4) int64 tets indexing them, as gmsh
    orients them."""
    gmsh.model.addPhysicalGroup(3, [tag for _, tag in gmsh.model.getEntities(3)], 1)
    gmsh.option.setNumber("Mesh.CharacteristicLengthMin", length)
    gmsh.option.setNumber("Mesh.CharacteristicLengthMax", length)
    gmsh.option.setNumber("Mesh.CharacteristicLengthFromCurvature", 0)
    gmsh.option.setNumber("Mesh.Algorithm3D", 1)
    gmsh.model.mesh.generate(3)
    gmsh.model.mesh.optimize("")
    node_tags, coords, _ = gmsh.model.mesh.getNodes()
    _, _, elem_nodes = gmsh.model.mesh.getElements(3)
    node_tags = np.asarray(node_tags, dtype=np.int64)
    coords = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
    tet_tags = np.concatenate([np.asarray(e, dtype=np.int64) for e in elem_nodes]).reshape(-1, 4)
    used = np.unique(tet_tags)
    order = np.argsort(node_tags)
    return coords[order[np.searchsorted(node_tags[order], used)]], np.searchsorted(used, tet_tags)


#: bounding box of the generated liver [m] (x, y, z extents) and its volume [m^3] and surface
#: area [m^2] (measured on generate_liver(0.004): 0.21 x 0.12 x 0.065 m, 0.84 L, 0.052 m^2)
LIVER_EXTENT = (0.21, 0.12, 0.065)
LIVER_VOLUME = 8.4e-4
LIVER_AREA = 0.052


def liver_length_error(length: float) -> str | None:
    """Why ``length`` cannot be the generated liver's ``mesh.characteristic_length`` (None if
    it can): an edge as long as the organ's smallest extent leaves no interior vertex, and
    gmsh silently clamps it to the geometry's own features (a value in mm, e.g. 40, gives the
    same 26-vertex liver as 0.4)."""
    thickness = min(LIVER_EXTENT)
    if length >= thickness:
        return (f"mesh.characteristic_length = {length:g} m is not small against the generated "
                f"liver ({' x '.join(f'{e:g}' for e in LIVER_EXTENT)} m): it must be below its "
                f"smallest extent, {thickness:g} m (the default is 0.0182 m); scene values are "
                f"in metres: is it in mm? ({length:g} mm is {length / 1000:g})")
    return None


def estimated_liver_vertices(length: float) -> int:
    """Vertices of ``generate_liver(length)`` estimated before meshing, from the organ's
    volume and surface area: 0.647 V / h^3 + 1.078 A / h^2 (fitted to the meshes at h = 4
    and 6 mm; within 10 % of the actual count from h = 4 to 18.2 mm)."""
    return int(round(0.647 * LIVER_VOLUME / length ** 3 + 1.078 * LIVER_AREA / length ** 2))


def generate_liver(characteristic_length: float = 0.0182) -> TetMesh:
    """Deterministic liver-like solid: two fused ellipsoidal lobes, flat bottom at z = -0.025 m.

    Right lobe semi-axes 75 x 60 x 40 mm centred at x = +30 mm, left lobe
    60 x 40 x 25 mm centred at (-45, 10, 0) mm; everything below z = -25 mm is
    cut off, giving a flat base for the fixed-node rule. Overall ~ 0.21 x 0.12 x
    0.065 m, about 0.55 L. gmsh runs single-threaded with a fixed seed: the same length
    gives the same arrays, bit for bit. A process therefore keeps the arrays of the last
    few lengths and returns a new :class:`TetMesh` of them (its derived quantities its
    own) instead of meshing again at every stage that loads the scene; :func:`mesh_liver`
    runs gmsh every time.
    """
    kept = _kept_liver(characteristic_length)
    return TetMesh(kept.vertices, kept.tets)


@functools.lru_cache(maxsize=4)
def _kept_liver(characteristic_length: float) -> TetMesh:
    return mesh_liver(characteristic_length)


def mesh_liver(characteristic_length: float = 0.0182) -> TetMesh:
    """:func:`generate_liver`'s mesh, made by gmsh at this call."""
    if characteristic_length <= 0:
        raise MeshError(f"characteristic_length must be > 0, got {characteristic_length}")
    problem = liver_length_error(characteristic_length)
    if problem:  # before gmsh, which would clamp it silently
        raise MeshError(problem)
    with gmsh_session("forcecal_liver") as gmsh:
        occ = gmsh.model.occ
        right = occ.addSphere(0.03, 0.0, 0.0, 1.0)
        occ.dilate([(3, right)], 0.03, 0.0, 0.0, 0.075, 0.06, 0.04)
        left = occ.addSphere(-0.045, 0.01, 0.0, 1.0)
        occ.dilate([(3, left)], -0.045, 0.01, 0.0, 0.06, 0.04, 0.025)
        fused, _ = occ.fuse([(3, right)], [(3, left)])
        below = occ.addBox(-0.2, -0.2, -0.2, 0.4, 0.4, 0.2 - 0.025)
        occ.cut(fused, [(3, below)])
        occ.synchronize()
        vertices, tets = mesh_volume(gmsh, characteristic_length)
        gmsh.model.remove()
    tets = orient_tets(vertices, tets, "generated liver")
    return check_mesh(TetMesh(vertices, tets))
