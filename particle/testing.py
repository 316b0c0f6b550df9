"""Small models with closed-form answers, shared by the particle tests and benchmarks."""

from __future__ import annotations

import numpy as np

from forcecal.mesh import box_mesh
from particle.model import ConnectorParams, Model, ModelBuilder, build_model


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


def two_particle_model(rest_length: float = 0.02, mass: float = 0.01,
                       params: ConnectorParams | None = None,
                       direction: tuple[float, float, float] = (1.0, 0.0, 0.0)) -> Model:
    """Particle 0 fixed at the origin, particle 1 at ``rest_length`` along ``direction``."""
    builder = ModelBuilder()
    builder.add_particle((0.0, 0.0, 0.0), mass, fixed=True)
    builder.add_particle(rest_length * np.asarray(direction) / np.linalg.norm(direction), mass)
    builder.add_connector(0, 1)
    return builder.finalize(viscoelastic_params(1) if params is None else params)


def box_model(n: tuple[int, int, int] = (3, 3, 2), size: float = 0.03, density: float = 1000.0,
              fixed_bottom: bool = True, **param_kwargs) -> Model:
    """Box of side ``size`` [m] (Kuhn-split cells), bottom face (z = 0) fixed if asked."""
    mesh = box_mesh(n, (size,) * 3)
    fixed = np.nonzero(np.isclose(mesh.vertices[:, 2], 0.0))[0] if fixed_bottom else None
    return build_model(mesh, density, viscoelastic_params(len(mesh.edges), **param_kwargs),
                       fixed=fixed)


def top_centre(model: Model) -> int:
    """The particle of the top face (max z) nearest to the face's centre."""
    x = model.rest_positions
    top = np.nonzero(np.isclose(x[:, 2], x[:, 2].max()))[0]
    centre = x[top].mean(axis=0)
    return int(top[np.argmin(np.linalg.norm(x[top] - centre, axis=1))])
