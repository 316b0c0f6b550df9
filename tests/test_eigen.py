"""The unsupported body's modes (forcecal/eigen.py) against a dense generalised eigen-solve."""
import dataclasses

import numpy as np
import pytest
import scipy.linalg as la
import scipy.sparse as sp

from forcecal.eigen import RIGID_MODES, free_modes
from forcecal.errors import ConvergenceError
from particle.body import RestOperators
from tests.test_body import _box_model

# the 3 x 2 x 2-cell box has 36 particles: dense solves are exact to round-off; its
# eigenvalues spread over ~4 decades, so 1e-8 relative is far above the solvers' error
RTOL = 1e-8


@pytest.mark.parametrize("modulus", ["instantaneous", "long_term"])
def test_free_free_modes_are_the_dense_spectrum_without_its_six_rigid_modes(modulus):
    """The shifted solve leaves out exactly the six zero eigenvalues of an unsupported body and
    returns the next ones, mass-normalised, as a dense generalised eigen-solve does."""
    model = _box_model(arms=True)
    model = dataclasses.replace(model, fixed=np.zeros(model.n_particles, bool))
    ops = RestOperators.of(model)
    K = ops.stiffness(model, modulus)
    dense = la.eigh(K.toarray(), np.diag(ops.mass), eigvals_only=True)
    assert np.all(np.abs(dense[:RIGID_MODES]) < 1e-9 * dense[RIGID_MODES])  # six rigid modes
    values, vectors = free_modes(K, sp.diags(ops.mass), 5, "box")
    np.testing.assert_allclose(values, dense[RIGID_MODES:RIGID_MODES + 5], rtol=RTOL)
    np.testing.assert_allclose(vectors.T @ (ops.mass[:, None] * vectors), np.eye(5),
                               atol=1e-10)
    np.testing.assert_allclose(K @ vectors, (ops.mass[:, None] * vectors) * values,
                               atol=1e-8 * values.max() * np.abs(vectors).max())


def test_a_supported_body_is_refused():
    """A clamped body has no rigid modes: asking for the unsupported body's modes of it is an
    error naming it, not six elastic modes silently left out."""
    model = _box_model(arms=False)
    ops = RestOperators.of(model)
    with pytest.raises(ConvergenceError, match="box: the six lowest eigenvalues .* are not "
                                               "rigid modes"):
        free_modes(ops.stiffness(model, "long_term"), sp.diags(ops.mass), 3, "box")


def test_the_same_solve_gives_the_same_bits_whatever_was_solved_before():
    """ARPACK's own start vector comes from a generator whose state persists in the process
    (two identical solves differed by 2e-15 in the eigenvalues before a fixed start vector):
    a solve repeated after another one returns the same eigenpairs bit for bit, held and
    unsupported."""
    from forcecal.eigen import nearest_modes
    model = _box_model(arms=True)
    ops = RestOperators.of(model)
    K, M = ops.stiffness(model, "instantaneous"), sp.diags(ops.mass)
    first = nearest_modes(K, M, 6, 0.0, "box")
    nearest_modes(ops.stiffness(model, "long_term"), M, 4, 0.0, "another solve")
    again = nearest_modes(K, M, 6, 0.0, "box")
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a, b)
    free = dataclasses.replace(model, fixed=np.zeros(model.n_particles, bool))
    ops = RestOperators.of(free)
    K, M = ops.stiffness(free, "long_term"), sp.diags(ops.mass)
    first = free_modes(K, M, 4, "box")
    free_modes(ops.stiffness(free, "instantaneous"), M, 3, "another solve")
    for a, b in zip(first, free_modes(K, M, 4, "box")):
        np.testing.assert_array_equal(a, b)
