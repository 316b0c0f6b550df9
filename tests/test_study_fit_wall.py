"""The fit-wall study (studies/fit_wall.py) on a mass hanging from one softening spring, whose
largest load, its fold and the frequencies about a loaded state are closed forms."""
import numpy as np

from particle.params import ConnectorParams
from particle.stability import connector_strains
from studies import fit_wall
from tests.particle_models import two_particle_model

L0, K0, A = 0.1, 100.0, -100.0  # rest length [m], spring K(eps) = K0 + A eps [N/m]
WEIGHT = 2.1  # [N]: the fold (factor 2.5 / 2.1) off the bisection's dyadic points
G = np.array([0.0, 0.0, -9.81])


def hanging_spring():
    """Particle 1 hanging ``L0`` below the fixed particle 0 on one spring; its weight 2.1 N."""
    params = ConnectorParams.uniform(1, K0=K0, a=A, k1=10.0, b1=1.0, k2=10.0, b2=1.0)
    return two_particle_model(rest_length=L0, mass=WEIGHT / 9.81, params=params,
                              direction=(0.0, 0.0, -1.0))


def test_the_largest_load_carried_is_the_springs_peak_force():
    """The spring's force ``L0 (K0 eps + A eps^2)`` peaks at ``eps* = K0 / (2 |A|)`` = 0.5 with
    ``K0^2 L0 / (4 |A|)`` = 2.5 N: the weight's factor 2.5 / 2.1 is the fold. The bisection
    brackets it to its resolution (Newton from the last equilibrium finds every state up to
    the fold; what it leaves short of the fold is inside one bracket), and the spring it
    stops at is soft: below the fold by ``d`` in force, ``|eps - eps*| = sqrt(d / (|A| L0))``
    and the tangent ``2 |A| |eps - eps*|``."""
    model = hanging_spring()
    carried = fit_wall.carried_factor(model, G)
    fold = K0 ** 2 * L0 / (4 * abs(A)) / WEIGHT
    assert carried["factor"] <= fold < carried["fails_at"]
    assert carried["fails_at"] - carried["factor"] <= fit_wall.RESOLUTION
    assert "ConvergenceError" in carried["failure"]
    parts = fit_wall.weakest_parts(model, carried["x"], np.zeros_like(model.rest_positions))
    below = (fold - carried["factor"]) * WEIGHT  # [N]
    bound = 2 * abs(A) * np.sqrt(below / (abs(A) * L0)) / K0
    assert parts["connector"] == 0 and 0.0 < parts["connector_tangent_over_K0"] <= bound * 1.0001
    assert parts["connector_fe_strain"] == 0.0  # the "FE" given: no displacement


def test_a_load_the_spring_carries_with_margin_is_not_a_wall():
    carried = fit_wall.carried_factor(hanging_spring(), 0.5 * G)
    assert carried["factor"] == fit_wall.UPPER and carried["fails_at"] is None


def test_the_lowest_frequency_about_a_loaded_state_is_the_pendulums():
    """Under half the weight (1.05 N): ``eps`` solves ``L0 (K0 eps + A eps^2) = 1.05``; the
    sideways motion (stiffness tension / length, the geometric part of the tangent) is the
    lowest, ``sqrt(T / (l m)) / 2 pi``; the axial one ``sqrt((K0 + 2 A eps) / m) / 2 pi``
    is higher."""
    model = hanging_spring()
    x, why = fit_wall.equilibrium(model, G, 0.5)
    assert why is None
    tension = 0.5 * WEIGHT
    eps = (K0 - np.sqrt(K0 ** 2 - 4 * abs(A) * tension / L0)) / (2 * abs(A))
    np.testing.assert_allclose(connector_strains(model, x - model.rest_positions), [eps],
                               rtol=1e-8)
    m = WEIGHT / 9.81
    pendulum = np.sqrt(tension / (L0 * (1 + eps) * m)) / (2 * np.pi)
    assert pendulum < np.sqrt((K0 + 2 * A * eps) / m) / (2 * np.pi)
    np.testing.assert_allclose(fit_wall.lowest_frequency(model, x), pendulum, rtol=1e-8)

