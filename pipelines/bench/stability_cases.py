"""The models on which the stable-step bound is checked against the empirical limit.

Three box aspects, a sliver and a coarse liver (:func:`stability_meshes`), each with
every parameter set of :data:`PARAMETER_SETS` (:func:`stability_cases`), and a cube
with every surface particle clamped, prestrained to each of :data:`PRESTRAINS`
(:func:`clamped_cube`). The tests (``tests/test_stability_particle.py``) and
``make bench`` (:mod:`pipelines.bench.stability`) use the same cases, so the ratio
estimate/empirical the benchmark reports is the one tested.
"""

from __future__ import annotations

import numpy as np

from forcecal.liver_mesh import generate_liver
from forcecal.mesh import TetMesh, box_mesh
from forcecal.point_selection import fixed_nodes
from particle.model import Model, build_model
from particle.params import viscoelastic_params

K0 = 50.0  # N/m, the particle tests' connector stiffness
DENSITY = 1060.0  # kg/m^3
# (K0 multiplier, a/K0, b/K0, Prony g): the parameter sets of the stability study
PARAMETER_SETS: dict[str, tuple[float, float, float, tuple[float, float]]] = {
    "linear": (1.0, 0.0, 0.0, (0.35, 0.25)),
    "stiff nonlinear": (1.0, -2.0, 40.0, (0.35, 0.25)),
    "strong arms": (1.0, 0.0, 0.0, (0.45, 0.45)),
}
# strains (inside the estimate's default range +-0.5) at which the clamped cube is prestrained
PRESTRAINS = (-0.4, 0.0, 0.4)


def sliver_mesh(height: float = 1e-3, size: float = 0.02) -> TetMesh:
    """Six vertices, five tets around one sliver of relative volume ``height``/3.

    The sliver A B C D has its four vertices within ``height x size`` of a
    plane (diagonals AB at z = 0 and CD at z = height x size); an apex E above
    and F below close it into a solid with one well-shaped tet on each of its
    faces. F and A are meant to be held.
    """
    v = size * np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [1.0, 0.0, height],
                         [0.0, 1.0, height], [0.5, 0.5, 1.0], [0.5, 0.5, -1.0]])
    tets = np.array([[0, 1, 2, 3], [0, 2, 3, 4], [1, 2, 3, 4], [0, 1, 2, 5], [0, 1, 3, 5]])
    x = v[tets]
    volume = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]),
                       x[:, 3] - x[:, 0])
    tets[volume < 0] = tets[volume < 0][:, [0, 2, 1, 3]]  # positive orientation
    return TetMesh(v, tets)


def stability_meshes(quick: bool = False) -> dict[str, tuple[TetMesh, np.ndarray]]:
    """Meshes of the study and their clamped vertices: three box aspects, a sliver, a liver."""
    out = {}
    for name, n, size in (("cube 3x3x2", (3, 3, 2), (0.03, 0.03, 0.03)),
                          ("bar 8x2x2", (8, 2, 2), (0.08, 0.02, 0.02)),
                          ("plate 4x4x1", (4, 4, 1), (0.04, 0.04, 0.005))):
        mesh = box_mesh(n, size)
        out[name] = (mesh, np.nonzero(np.isclose(mesh.vertices[:, 0], 0.0))[0])
    out["sliver"] = (sliver_mesh(), np.array([0, 5]))
    if not quick:
        liver = generate_liver(0.04)
        out["liver h=0.04"] = (liver, fixed_nodes(liver))
    return out


def case_model(mesh: TetMesh, fixed: np.ndarray, parameter_set: str, *,
               density: float = DENSITY) -> Model:
    """Particle model of ``mesh`` with one of :data:`PARAMETER_SETS` (K0 scaled by mean edge)."""
    scale, a, b, g = PARAMETER_SETS[parameter_set]
    k0 = scale * K0 * float(mesh.edge_lengths.mean()) / 0.01  # same material on every mesh
    params = viscoelastic_params(len(mesh.edges), k0, a=a * k0, b=b * k0, g=g, tau=(0.05, 0.5))
    return build_model(mesh, density, params, fixed=fixed)


def stability_cases(quick: bool = False) -> dict[str, Model]:
    """Every mesh of :func:`stability_meshes` with every parameter set, named ``mesh / set``."""
    return {f"{m} / {p}": case_model(mesh, fixed, p)
            for m, (mesh, fixed) in stability_meshes(quick).items() for p in PARAMETER_SETS}


def clamped_cube(parameter_set: str) -> Model:
    """A 4x4x4 Kuhn box with every surface particle clamped (the prestrain study's model)."""
    mesh = box_mesh((4, 4, 4), (0.04, 0.04, 0.04))
    return case_model(mesh, mesh.surface_vertices, parameter_set)
