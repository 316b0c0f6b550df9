"""The report's real-time check takes its step from the bound every session and integrator
takes (:func:`particle.stability.step_bound`), and says what sets it from that same bound.

The model: the tiny scene's mesh (78 vertices, 186 tets) with uniform viscoelastic springs and
the relaxing volume term (kv 20 kPa, arms kv/2 and kv/4), on the haptic session's strain range.
There the volume term's own bound, added to the springs', is the smaller one (the springs' part
is 7 % of it); the joint bound (volume edge weights added to the springs') is the smaller on a
regular box at rest, which the last test takes.
"""
import dataclasses

import numpy as np
import pytest

from forcecal.problem import build_problem
from forcecal.scene import load_scene
from particle.haptics import HapticSession
from particle.integrator import VerletIntegrator
from particle.model import build_model
from particle.params import connector_strain_bounds, viscoelastic_params
from particle.stability import (EIGENVALUE_MARGIN, connector_stiffness_bound, critical_time_step,
                                largest_eigenvalue, mass_scaled_laplacian, step_bound)
from particle.volume_bounds import (volume_edge_stiffness_bound, volume_scalar_matrix,
                                    volume_tet_energies)
from pipelines import realtime
from pipelines.realtime import realtime_block, session_strain_range, step_limiters
from tests.particle_models import box_model
from tests.conftest import SCENES

KV = 2e4  # [Pa]


@pytest.fixture(scope="module")
def tiny():
    scene = load_scene(SCENES / "tiny.toml")
    problem = build_problem(scene)
    n_tets = len(problem.mesh.tets)
    params = dataclasses.replace(
        viscoelastic_params(len(problem.mesh.edges)), kv=np.full(n_tets, KV),
        kv1=np.full(n_tets, KV / 2), bv1=np.full(n_tets, 0.2 * KV / 2),
        kv2=np.full(n_tets, KV / 4), bv2=np.full(n_tets, 1.0 * KV / 4))
    return scene, problem, build_model(problem, scene.material.density, params)


def test_the_real_time_check_runs_the_substeps_of_the_integrator_and_session(tiny, monkeypatch):
    """Same model, same strain range: the check's limit is the integrator's to the bit, and its
    substeps per 1 ms call are those of a session given the scene's step rule on that limit."""
    scene, problem, model = tiny
    monkeypatch.setattr(realtime, "CALLS", 200)  # a 50 ms push: the substeps do not depend on it
    block = realtime_block(scene, problem, model)
    assert block["status"] == "measured", block["reason"]
    strain_range = session_strain_range(model.params)
    critical = VerletIntegrator(strain_range=strain_range).critical_time_step(model)
    assert block["critical_dt_s"] == critical
    session = HapticSession(model, scene.particle.dt_safety * critical,
                            strain_range=strain_range)
    assert block["substeps_per_ms"] == session.substeps and block["dt_s"] == session.dt
    assert session.substeps > 1  # the volume term sets a step below the 1 ms period


def test_what_sets_the_step_is_read_off_the_bound_the_step_is_taken_from(tiny):
    """With the volume term's own bound added to the springs': the connectors' shares (the
    springs' Laplacian's fastest mode) sum to the springs' part of the bound, the tets' own
    volume shares (the scalar matrix's fastest mode, exact Rayleigh parts of its eigenvalue)
    to the volume term's part, and that bound is the limit's."""
    _, _, model = tiny
    strain_range = session_strain_range(model.params)
    bound = step_bound(model, strain_range)
    assert bound.volume_matrix is not None
    assert 2.0 / np.sqrt(bound.omega2) == critical_time_step(model, strain_range=strain_range)
    lo, hi = connector_strain_bounds(strain_range, model.n_connectors, model.edges)
    scalar = volume_scalar_matrix(model, lo, hi)
    eigenvalues, vectors = np.linalg.eigh(scalar.toarray())
    energies = volume_tet_energies(model, lo, hi, vectors[:, -1])
    assert energies.sum() == pytest.approx(eigenvalues[-1], rel=1e-12)
    assert bound.volume_part == pytest.approx(EIGENVALUE_MARGIN * eigenvalues[-1], rel=1e-12)
    springs = largest_eigenvalue(mass_scaled_laplacian(
        model, connector_stiffness_bound(model.params, lo, hi)))
    assert bound.laplacian_part == EIGENVALUE_MARGIN * springs

    limiters = step_limiters(model, strain_range, count=model.n_connectors)
    edge_share = np.zeros(model.n_connectors)
    for e in limiters["limiting_edges"]:
        edge_share[e["connector"]] = e["share"]
    assert edge_share.min() >= 0.0
    assert edge_share.sum() == pytest.approx(bound.laplacian_part / bound.omega2, rel=1e-9)
    tet_share = np.zeros(model.n_tets)
    for t in limiters["limiting_tets"]:
        tet_share[t["tet"]] = t["share"]
    own = tet_share - edge_share[model.tet_connectors].sum(axis=1)
    assert own.min() >= -1e-15
    assert own.sum() == pytest.approx(bound.volume_part / bound.omega2, rel=1e-9)
    assert np.argmax(own) == np.argmax(energies)


def test_with_the_joint_bound_the_volume_term_is_in_the_connectors_weights():
    """A regular box at rest (zero strain range), kv 1 kPa: the joint bound is the smaller, the
    Laplacian's weights are the springs' plus the volume term's edge weights, and the
    connectors' shares of its fastest mode sum to 1."""
    box = box_model((3, 3, 2))
    model = box.with_params(dataclasses.replace(box.params, kv=np.full(box.n_tets, 1e3)))
    zero = np.zeros(model.n_connectors)
    bound = step_bound(model, (zero, zero))
    assert bound.volume_matrix is None and bound.volume_part == 0.0
    np.testing.assert_array_equal(bound.kappa, connector_stiffness_bound(model.params, zero, zero)
                                  + volume_edge_stiffness_bound(model, zero, zero))
    assert 2.0 / np.sqrt(bound.omega2) == critical_time_step(model, strain_range=(zero, zero))
    limiters = step_limiters(model, (zero, zero), count=model.n_connectors)
    assert sum(e["share"] for e in limiters["limiting_edges"]) == pytest.approx(1.0, rel=1e-12)
