"""The support study (studies/support_stability.py): the rigid-rotation fit that names a mode's
shape, and the extrapolation of the lowest eigenvalue to the limit load."""
import numpy as np
import pytest

from studies.support_stability import limit_estimates, rotation_fit


def test_a_rigid_rotation_about_the_centre_is_recovered_whole():
    """A small rotation ``omega x (x - c)`` of random points: the fit returns ``omega`` and a
    share of 1 (to round-off); a uniform translation is not a rotation about ``c`` (share
    below 1 but not 0: the points lie to one side of ``c``, so a rotation moves them partly
    alike)."""
    rng = np.random.default_rng(3)
    x = rng.uniform(-0.05, 0.05, (40, 3))
    c = np.array([0.0, -0.05, 0.01])
    omega = np.array([0.3, -0.1, 0.05])
    weights = rng.uniform(0.5, 2.0, 40)
    got, share = rotation_fit(np.cross(omega, x - c), x, c, weights)
    np.testing.assert_allclose(got, omega, rtol=1e-12)
    assert share == pytest.approx(1.0, abs=1e-12)
    _, translation = rotation_fit(np.tile([0.0, 0.0, 1e-3], (40, 1)), x, c, weights)
    assert 0.0 < translation < 0.9
    assert rotation_fit(np.zeros((40, 3)), x, c, weights)[1] == 0.0


@pytest.mark.parametrize("critical", [0.6, 1.3])
def test_the_limit_load_is_extrapolated_exactly_for_its_own_law(critical):
    """An eigenvalue linear in the load (a bifurcation) gives the linear estimate exactly; one
    whose square is linear in it (a fold: the square root of the distance to the limit)
    gives the fold estimate exactly, and the linear one beyond it (the square root falls
    faster near the limit)."""
    factors = np.array([0.0, 0.25, 0.5])
    linear = limit_estimates(factors, 40.0 * (critical - factors))
    assert linear["linear"] == pytest.approx(critical, rel=1e-12)
    fold = limit_estimates(factors, 40.0 * np.sqrt(critical - factors))
    assert fold["fold"] == pytest.approx(critical, rel=1e-12)
    assert fold["linear"] > critical
    assert limit_estimates(factors, 40.0 + factors) == {"linear": None, "fold": None}
