"""The scaled-floor study (studies/scaled_floor.py): its material scaling and the fixed-point
match of the rest modes."""
import numpy as np

from forcecal.scene import MaterialSection
from studies import scaled_floor


def test_the_scale_acts_on_the_shear_moduli_only():
    material = MaterialSection(C10=500.0, C01=100.0, kappa=1e5, density=1000.0)
    scaled = scaled_floor.scaled_material(material, 0.7)
    assert (scaled.C10, scaled.C01) == (350.0, 70.0)
    assert (scaled.kappa, scaled.density, scaled.prony_g, scaled.prony_tau) == (
        material.kappa, material.density, material.prony_g, material.prony_tau)


def test_the_matched_scale_makes_the_mean_frequency_ratio_one(monkeypatch):
    """Frequencies ``f0 sqrt(s)`` (an incompressible body's: shear only): the fixed point
    ``s <- s (mean f_FE / f)^2`` lands on ``(f_FE / f0)^2`` in one step when the FE's modes
    are a multiple of the model's, and on the squared mean ratio when they are not."""
    f0 = np.array([5.0, 6.0, 8.0, 9.0, 10.0, 12.0])
    monkeypatch.setattr(scaled_floor, "rest_frequencies",
                        lambda scene, problem, scale: f0 * np.sqrt(scale))
    scale, steps = scaled_floor.matched_scale(None, None, 0.9 * f0)
    np.testing.assert_allclose(scale, 0.81, rtol=1e-12)
    np.testing.assert_allclose(steps[1]["mean_frequency_ratio"], 1.0, rtol=1e-12)
    uneven = f0 * np.array([0.8, 0.9, 1.0, 1.0, 0.9, 0.8])
    scale, steps = scaled_floor.matched_scale(None, None, uneven)
    np.testing.assert_allclose(np.mean(uneven / (f0 * np.sqrt(scale))), 1.0, rtol=1e-6)


def test_largest_frequency_of_a_two_mass_chain():
    """Two masses m on springs k (wall - m - m): ``omega^2 = (3 +- sqrt 5) k / (2 m)``, the
    larger one returned (the explicit step's limit is 2 over it)."""
    import scipy.sparse as sp

    k, m = 400.0, 0.25
    stiffness = sp.csr_matrix(np.array([[2 * k, -k], [-k, k]]))
    np.testing.assert_allclose(scaled_floor.largest_frequency(stiffness, np.full(2, m)),
                               np.sqrt((3 + np.sqrt(5)) * k / (2 * m)), rtol=1e-10)
