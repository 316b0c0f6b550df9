"""Small-displacement (linear) response of the connector network.

At the rest shape every connector is unstretched, so the particle model's
tangent stiffness is exactly ``sum_c K0_c e_c e_c^T`` (the geometric term
``(F/l)(I - e e^T)`` vanishes with F = 0): the linear network below *is* the
particle model's initial slope, not an approximation of it. Calibration uses
it twice, one sparse solve per test point:

* the closed-form initial guess: K0 = (FE initial slope) / (slope of the
  unit-stiffness network), least squares over the calibration points;
* the strain range the experiments reach (linear estimate), on which the
  spring ``K(eps)`` must stay positive.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from forcecal.errors import MeshError
from forcecal.mesh import TetMesh

@dataclass(frozen=True, eq=False)
class LinearIndentation:
    """Linear response of the network to a unit indentation of each test point.

    Attributes:
        slope: (P,) float64, normal force per unit depth [N/m] for the given stiffness.
        strain: (P, E) float64, connector strains per unit depth [1/m] (times a depth
            in m gives the strain of each connector).
    """
    slope: np.ndarray
    strain: np.ndarray


def stiffness_matrix(mesh: TetMesh, stiffness: np.ndarray) -> sp.csc_matrix:
    """(3N, 3N) linear stiffness ``sum_c k_c e_c e_c^T`` over connectors [N/m]."""
    e = mesh.edges
    d = mesh.vertices[e[:, 1]] - mesh.vertices[e[:, 0]]
    d /= mesh.edge_lengths[:, None]
    blocks = stiffness[:, None, None] * d[:, :, None] * d[:, None, :]  # (E, 3, 3)
    dof_i = 3 * e[:, 0, None] + np.arange(3)  # (E, 3)
    dof_j = 3 * e[:, 1, None] + np.arange(3)
    rows, cols, vals = [], [], []
    for a, b, sign in ((dof_i, dof_i, 1.0), (dof_j, dof_j, 1.0), (dof_i, dof_j, -1.0),
                       (dof_j, dof_i, -1.0)):
        rows.append(np.repeat(a, 3, axis=1).ravel())
        cols.append(np.tile(b, (1, 3)).ravel())
        vals.append(sign * blocks.ravel())
    n = 3 * mesh.n_vertices
    return sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(n, n))


def linear_indentation(mesh: TetMesh, fixed: np.ndarray, nodes: np.ndarray,
                       normals: np.ndarray, stiffness: np.ndarray | None = None,
                       footprints: Sequence[np.ndarray] | None = None) -> LinearIndentation:
    """Indent each node along its normal (vertex fully prescribed, ``fixed`` clamped).

    With ``footprints`` (one array of held vertices per node, a flat punch) every held
    vertex is moved along the node's normal and the slope is the sum of their reactions.

    Args:
        mesh: the mesh (connectors = ``mesh.edges``).
        fixed: (F,) int, clamped vertices.
        nodes: (P,) int, test vertices.
        normals: (P, 3) float, unit indentation directions.
        stiffness: (E,) float, connector stiffness [N/m]; ones if None.
    """
    k = np.ones(len(mesh.edges)) if stiffness is None else np.asarray(stiffness, dtype=float)
    K = stiffness_matrix(mesh, k)
    e = mesh.edges
    direction = (mesh.vertices[e[:, 1]] - mesh.vertices[e[:, 0]]) / mesh.edge_lengths[:, None]
    slope = np.empty(len(nodes))
    strain = np.empty((len(nodes), len(e)))
    for p, (node, normal) in enumerate(zip(nodes, normals)):
        punch = np.atleast_1d(node) if footprints is None else np.asarray(footprints[p])
        punch_dofs = (3 * punch[:, None] + np.arange(3)).ravel()
        held = np.zeros(mesh.n_vertices, dtype=bool)
        held[fixed] = True
        held[punch] = True
        free_dofs = np.nonzero(np.repeat(~held, 3))[0]
        u = np.zeros(3 * mesh.n_vertices)
        u[punch_dofs] = np.tile(normal, len(punch))
        rhs = -(K[free_dofs][:, punch_dofs] @ u[punch_dofs])
        try:
            u[free_dofs] = splu(K[free_dofs][:, free_dofs].tocsc()).solve(rhs)
        except RuntimeError as exc:  # "Factor is exactly singular"
            raise MeshError(f"the connector network is not rigid when vertex {node} is indented "
                            f"(singular stiffness: {exc})") from None
        if not np.all(np.isfinite(u)):
            raise MeshError(f"the connector network is not rigid when vertex {node} is indented")
        slope[p] = normal @ (K[punch_dofs] @ u).reshape(-1, 3).sum(axis=0)
        du = u.reshape(-1, 3)
        strain[p] = np.einsum("ij,ij->i", du[e[:, 1]] - du[e[:, 0]], direction) / mesh.edge_lengths
    return LinearIndentation(slope=slope, strain=strain)
