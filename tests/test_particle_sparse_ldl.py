"""Sparse L D L^T (particle/sparse_ldl.py) against SuperLU (statics.superlu) and dense algebra."""
import dataclasses
import logging
import pickle

import numpy as np
import pytest
import scipy.sparse as sp

from forcecal.errors import ConvergenceError
from particle import sparse_ldl
from particle.statics import (EquilibriumSolver, TangentPattern, factorize, ldl_factor, superlu,
                              tangent_data)
from tests.particle_models import box_model, top_centre

DOWN = np.array([0.0, 0.0, -1.0])


def real_tangent(kv: float | None, depth: float = 0.003):
    """(pattern, data) of the constrained tangent at an indentation of a box's top centre
    (nonlinear springs; with the volume term if ``kv`` [Pa])."""
    model = box_model((4, 4, 3), a=-30.0, b=400.0, tau=(0.01, 0.05))
    if kv is not None:
        model = model.with_params(dataclasses.replace(model.params,
                                                      kv=np.full(model.n_tets, kv)))
    node = top_centre(model)
    pat = TangentPattern.of(model)
    solver = EquilibriumSolver(model, [node], pat)
    guess = model.rest_positions.copy()
    guess[node] += depth * DOWN
    eq = solver.solve(guess, model.params)
    it = solver._evaluate(eq.x, model.params, True, None, None)
    data = tangent_data(model, pat, eq.x, it.tension, model.params, True, None)
    data[solver._zero_slots] = 0.0
    data[solver._diag_slots] = 1.0
    return pat, data


def dense(pat, data) -> np.ndarray:
    return sp.csc_matrix((data, pat.indices, pat.indptr), shape=(pat.n_dofs,) * 2).toarray()


def rel(x, ref) -> float:
    return float(np.abs(x - ref).max() / np.abs(ref).max())


def rhs_layouts(n: int, rng):
    """Right-hand sides as the callers pass them: (n,), (n, r) C- and Fortran-ordered, the
    transpose of a C-ordered (r, n) (the adjoint pass), one column, none."""
    c = rng.standard_normal((n, 31))
    return [c[:, 0].copy(), c, np.asfortranarray(c), rng.standard_normal((5, n)).T, c[:, :1],
            c[:, ::3], np.zeros((n, 0))]


@pytest.mark.parametrize("kv", [None, 3000.0])
def test_solves_equal_superlu_on_real_tangents(kv):
    pat, data = real_tangent(kv)
    rng = np.random.default_rng(0)
    lu, ref = ldl_factor(pat, data), superlu(pat, data)
    assert isinstance(lu, sparse_ldl.Factor)
    assert (lu.d > 0).all()  # the tangent of a stable equilibrium
    for b in rhs_layouts(pat.n_dofs, rng):
        x, x_ref = lu.solve(b), ref.solve(b)
        assert x.shape == x_ref.shape == b.shape
        if b.ndim == 2:
            assert x.flags.f_contiguous  # as SuperLU: solve(B.T).T of C-ordered B is C-ordered
        if b.size:
            assert rel(x, x_ref) < 1e-10
    b = rng.standard_normal(pat.n_dofs)
    np.testing.assert_allclose(dense(pat, data) @ lu.solve(b), b, rtol=0, atol=1e-10)


def test_a_solve_of_many_right_hand_sides_gives_each_the_bits_of_fewer():
    """A column's solution does not depend on the columns solved with it: the adjoint pass
    solves at each step only for the outputs that step carries, so its derivatives must be
    the same bits whatever the others. Every count from 2 to 13 (lane widths with and
    without padding) against the same columns solved 13 at once, bit for bit, and all of
    them within round-off of SuperLU's."""
    pat, data = real_tangent(3000.0)
    lu, ref = ldl_factor(pat, data), superlu(pat, data)
    b = np.random.default_rng(1).standard_normal((pat.n_dofs, 13))
    every = lu.solve(b)
    assert rel(every, ref.solve(b)) < 1e-10
    for r in range(2, 13):
        np.testing.assert_array_equal(lu.solve(b[:, :r]), every[:, :r])
        np.testing.assert_array_equal(lu.solve(np.ascontiguousarray(b[:, 13 - r:])),
                                      every[:, 13 - r:])


def test_restricted_solve_is_the_full_solve_scattered_and_gathered():
    """``solve_restricted`` (the Newton step's solve) equals ``solve`` of the right-hand side
    scattered on the dofs and gathered back, to the last bit (the same sweeps); bad dofs are
    refused with a clear error, not read out of bounds."""
    pat, data = real_tangent(3000.0)
    lu = ldl_factor(pat, data)
    rng = np.random.default_rng(3)
    dofs = rng.permutation(pat.n_dofs)[:pat.n_dofs - 7].astype(np.int64)
    values = rng.standard_normal(len(dofs))
    full = np.zeros(pat.n_dofs)
    full[dofs] = values
    np.testing.assert_array_equal(lu.solve_restricted(dofs, values), lu.solve(full)[dofs])
    with pytest.raises(ValueError, match="outside"):
        lu.solve_restricted(np.array([0, pat.n_dofs], dtype=np.int64), np.ones(2))
    with pytest.raises(ValueError, match="one length"):
        lu.solve_restricted(dofs, values[:-1])


def factor_dense(lu: sparse_ldl.Factor) -> tuple[np.ndarray, np.ndarray]:
    """(L (n, n) unit lower triangular, D (n,)) in the permuted order, from the supernodes."""
    s = lu.symbolic
    L = np.zeros((s.n, s.n))
    for k in range(len(s.sup_ptr) - 1):
        f, nc = s.sup_ptr[k], s.sup_ptr[k + 1] - s.sup_ptr[k]
        rows = s.rows[s.row_ptr[k]:s.row_ptr[k + 1]]
        block = lu.x[s.x_ptr[k]:s.x_ptr[k + 1]].reshape(nc, len(rows)).T
        for c in range(nc):
            L[rows[c:], f + c] = block[c:, c]
    return L, lu.d


def test_factors_reproduce_the_matrix_with_superlus_fill():
    pat, data = real_tangent(3000.0)
    lu = ldl_factor(pat, data)
    L, d = factor_dense(lu)
    np.testing.assert_array_equal(np.diag(L), 1.0)
    A = dense(pat, data)
    P = lu.symbolic.perm
    np.testing.assert_allclose((L * d) @ L.T, A[np.ix_(P, P)], rtol=0,
                               atol=1e-13 * np.abs(A).max())
    # the ordering is SuperLU's MMD_AT_PLUS_A: the same fill on a matrix with no zero entry
    # (SuperLU drops stored zeros, so it sees less than the pattern on constrained tangents)
    cols = np.repeat(np.arange(pat.n_dofs), np.diff(pat.indptr))
    full = np.where(pat.indices == cols, 100.0, -1.0)
    assert pat.ldl.nnz == superlu(pat, full).L.nnz - pat.n_dofs


def test_indefinite_matrices_solve_without_pivoting():
    """A tangent shifted to have negative eigenvalues (as a softening spring's can): no
    pivoting is needed as long as no pivot vanishes, like SuperLU's diag_pivot_thresh=0."""
    pat, data = real_tangent(None)
    lam = np.linalg.eigvalsh(dense(pat, data))
    k = len(lam) // 3
    shifted = data.copy()
    shifted[pat.diagonal] -= 0.5 * (lam[k] + lam[k + 1])  # mid-gap: well away from singular
    lu = ldl_factor(pat, shifted)
    assert (lu.d < 0).sum() > 0
    rng = np.random.default_rng(1)
    b = rng.standard_normal((pat.n_dofs, 4))
    assert rel(lu.solve(b), superlu(pat, shifted).solve(b)) < 1e-10
    assert rel(lu.solve(b), np.linalg.solve(dense(pat, shifted), b)) < 1e-10


def random_symmetric(n: int, density: float, spd: bool, rng) -> sp.csc_matrix:
    a = sp.random(n, n, density, random_state=rng, format="csc")
    a = a + a.T + sp.diags(rng.uniform(0.5, 1.0, n) * (1 if spd else rng.choice([-1, 1], n)))
    if spd:
        a = a + sp.diags(np.abs(a).sum(axis=1).A1)
    a = a.tocsc()
    a.sort_indices()
    return a


@pytest.mark.parametrize("n, density", [(1, 1.0), (2, 0.0), (7, 0.4), (40, 0.08), (120, 0.03)])
@pytest.mark.parametrize("spd", [True, False])
def test_random_patterns_match_dense_solves(n, density, spd):
    """Patterns without the tangent's 3 x 3 blocks: supernodes of any width (the kernels'
    three-column passes with 1 or 2 columns left over)."""
    rng = np.random.default_rng(n)
    a = random_symmetric(n, density, spd, rng)
    sym = sparse_ldl.analyse(a.indptr, a.indices)
    lu = sparse_ldl.factorize(sym, a.data)
    b = rng.standard_normal((n, 17))
    ref = np.linalg.solve(a.toarray(), b)
    tol = 1e-13 * np.linalg.cond(a.toarray())
    assert rel(lu.solve(b), ref) < tol
    assert rel(lu.solve(b[:, 3]), ref[:, 3]) < tol


def test_zero_pivot_raises_and_the_solver_shifts_the_diagonal(caplog):
    pat, data = real_tangent(None)
    dof = pat.n_dofs // 2
    cols = np.repeat(np.arange(pat.n_dofs), np.diff(pat.indptr))
    singular = np.where((pat.indices == dof) | (cols == dof), 0.0, data)
    with pytest.raises(RuntimeError, match="exactly singular"):
        ldl_factor(pat, singular)
    with pytest.raises(RuntimeError, match="exactly singular"):
        superlu(pat, singular)  # the reference agrees
    nan = data.copy()
    nan[0] = np.nan
    with pytest.raises(RuntimeError, match="non-finite"):
        ldl_factor(pat, nan)
    caplog.set_level(logging.DEBUG, logger="particle.statics")
    lu = factorize(pat, singular, np.zeros(0, np.int64))  # shifted: now regular
    assert "exactly singular; factorising it with its diagonal shifted" in caplog.text
    assert np.isfinite(lu.solve(np.ones(pat.n_dofs))).all()
    with pytest.raises(ConvergenceError, match="singular"):
        factorize(pat, np.zeros_like(data), np.zeros(0, np.int64))


def test_analysis_is_cached_on_the_pattern_and_pickles():
    pat, data = real_tangent(None)
    assert pat.ldl is pat.ldl
    b = np.arange(pat.n_dofs, dtype=np.float64)
    again = pickle.loads(pickle.dumps(pat))
    np.testing.assert_array_equal(ldl_factor(again, data).solve(b), ldl_factor(pat, data).solve(b))
    with pytest.raises(ValueError, match="right-hand side"):
        ldl_factor(pat, data).solve(np.ones(pat.n_dofs + 1))
