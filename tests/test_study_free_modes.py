"""The free-modes study (studies/free_modes.py): its pairing of a model's modes with the FE's."""
import dataclasses

import numpy as np
import pytest

from particle.body import RestOperators
from particle.body import model_modes as fitted_modes
from studies.free_modes import compare, model_modes
from tests.test_body import _box_model


def test_supported_modes_are_the_calibrations_own():
    """With the box's clamp, the study's modes are those the calibration fits."""
    model = _box_model(arms=False)
    clamp = np.nonzero(model.fixed)[0]
    frequencies, vectors, mass, free = model_modes(model, clamp, "long_term", 4)
    values, fitted, _ = fitted_modes(model, RestOperators.of(model), "long_term", 4)
    np.testing.assert_allclose(frequencies, np.sqrt(values) / (2 * np.pi), rtol=1e-12)
    np.testing.assert_array_equal(free, model.free_nodes)
    np.testing.assert_allclose(np.abs(np.sum(mass[:, None] * vectors * fitted, axis=0)), 1.0,
                               rtol=1e-8)  # the same shapes up to sign


@pytest.mark.parametrize("support", ["clamp", "free"])
def test_a_model_against_its_own_modes_has_no_error(support):
    """Pairing a model's modes with themselves (given at the particles as the FE's are) gives
    zero frequency errors and MACs of one; a stiffer copy (every stiffness x 1.21) gives +10 %
    on every mode (frequencies scale with the square root)."""
    model = _box_model(arms=True)
    fixed = np.nonzero(model.fixed)[0] if support == "clamp" else None
    frequencies, vectors, _, free = model_modes(model, fixed, "instantaneous", 4)
    shapes = np.zeros((4, model.n_particles, 3))
    shapes[:, free] = vectors.T.reshape(4, len(free), 3)
    row = compare(frequencies, shapes, model, fixed, "instantaneous")
    np.testing.assert_allclose(row["frequency_error"], 0.0, atol=1e-8)
    np.testing.assert_allclose(row["mac"], 1.0, rtol=1e-8)
    p = model.params
    stiffer = dataclasses.replace(model, params=dataclasses.replace(
        p, **{name: 1.21 * getattr(p, name) for name in ("K0", "k1", "k2", "kv", "kv1", "kv2")}))
    row = compare(frequencies, shapes, stiffer, fixed, "instantaneous")
    np.testing.assert_allclose(row["frequency_error"], 0.1, rtol=1e-8)
