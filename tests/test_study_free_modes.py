"""The free-free modes study (studies/free_modes.py): its eigen-solves against dense ones."""
import dataclasses

import numpy as np
import pytest
import scipy.linalg as la
import scipy.sparse as sp

from forcecal.errors import ConvergenceError
from particle.body import RestOperators
from particle.body import model_modes as supported_modes
from studies.free_modes import RIGID, compare, lowest_modes, model_modes
from tests.test_body import _box_model

# the 3 x 2 x 2-cell box has 36 particles: dense solves are exact to round-off; eigenvalues
# spread over ~4 decades, so 1e-8 relative is far above the solvers' error
RTOL = 1e-8


def _free(model):
    return dataclasses.replace(model, fixed=np.zeros(model.n_particles, bool))


@pytest.mark.parametrize("modulus", ["instantaneous", "long_term"])
def test_free_free_modes_are_the_dense_spectrum_without_its_six_rigid_modes(modulus):
    """The shifted solve drops exactly the six zero eigenvalues of an unsupported body and
    returns the next ones, mass-normalised, as a dense generalised eigen-solve does."""
    model = _free(_box_model(arms=True))
    ops = RestOperators.of(model)
    K = ops.stiffness(model, modulus)
    dense = la.eigh(K.toarray(), np.diag(ops.mass), eigvals_only=True)
    assert np.all(np.abs(dense[:RIGID]) < 1e-9 * dense[RIGID])  # six rigid modes
    values, vectors = lowest_modes(K, sp.diags(ops.mass), 5, True, "box")
    np.testing.assert_allclose(values, dense[RIGID:RIGID + 5], rtol=RTOL)
    np.testing.assert_allclose(vectors.T @ (ops.mass[:, None] * vectors), np.eye(5),
                               atol=1e-10)
    np.testing.assert_allclose(K @ vectors, (ops.mass[:, None] * vectors) * values,
                               atol=1e-8 * values.max() * np.abs(vectors).max())


def test_supported_modes_are_the_calibrations_own():
    """With the box's clamp, the study's modes are those the calibration fits
    (:func:`particle.body.model_modes`)."""
    model = _box_model(arms=False)
    clamp = np.nonzero(model.fixed)[0]
    frequencies, vectors, mass, free = model_modes(model, clamp, "long_term", 4)
    values, fitted, _ = supported_modes(model, RestOperators.of(model), "long_term", 4)
    np.testing.assert_allclose(frequencies, np.sqrt(values) / (2 * np.pi), rtol=RTOL)
    np.testing.assert_array_equal(free, model.free_nodes)
    # same shapes up to sign
    np.testing.assert_allclose(np.abs(np.sum(mass[:, None] * vectors * fitted, axis=0)), 1.0,
                               rtol=1e-8)


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


def test_a_supported_body_solved_as_free_free_is_refused():
    """A clamped body has no rigid modes: asking for six of them is an error naming it, not
    six elastic modes silently dropped."""
    model = _box_model(arms=False)
    ops = RestOperators.of(model)
    with pytest.raises(ConvergenceError, match="not rigid modes"):
        lowest_modes(ops.stiffness(model, "long_term"), sp.diags(ops.mass), 3, True, "box")
