"""Calls from Python into the compiled kernels stay on numba's fast dispatch: every argument
fits numba 0.56's 40-byte type fingerprint (:mod:`particle.dispatch`), so calls after the
first never type their arguments in Python, and the groups joined in compiled code give the
kernels' results bit for bit."""
import dataclasses

import numpy as np
import pytest

from particle import dispatch, kernels, statics, step_kernels
from particle.experiments import relaxation_dynamic
from particle.integrator import VerletIntegrator, recording
from particle.stability import critical_time_step
from particle.volume import add_volume_forces, add_volume_forces_grouped, node_volume_force
from tests.particle_models import box_model, top_centre


def relaxing_box():
    """A box with nonlinear viscoelastic connectors and a relaxing volume term: every
    optional group of the kernels filled."""
    model = box_model(a=10.0, b=50.0)
    n = model.n_tets
    return model.with_params(dataclasses.replace(
        model.params, kv=np.full(n, 2e4), kv1=np.full(n, 1.2e4), bv1=np.full(n, 6e3),
        kv2=np.full(n, 8e3), bv2=np.full(n, 8e4)))


def test_four_arrays_fit_numbas_fingerprint_and_five_do_not():
    """The limit the groups are sized for: an array takes 8 bytes, a tuple 2 more."""
    a = np.zeros(3)
    assert dispatch.fits((a,) * 4 + (None, 1, 2.0, True))
    assert not dispatch.fits((a,) * 5)


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("volume", [False, True])
def test_every_argument_a_run_passes_to_the_kernels_fits_the_fingerprint(volume, threads):
    """The compiled loop's groups (with a prescribed particle, a recording and a probe: every
    group filled) and :meth:`Run.force_on`'s volume arms."""
    model = relaxing_box() if volume else box_model(a=10.0, b=50.0)
    node = top_centre(model)
    run = VerletIntegrator().prepare(model, 0.5 * critical_time_step(model),
                                     prescribed_nodes=[node], threads=threads)
    state = model.state()
    keyframes = (np.zeros(2), np.zeros((2, 1, 3)))
    probe = (node, *run._incident(node)[:1], np.empty(3), run._incident(node)[1])
    args = run.arguments(state, 1, keyframes, 1.0, recording(model, [node], [0, 1], 1), probe)
    assert len(args) == step_kernels.run_verlet.py_func.__code__.co_argcount
    assert [k for k, a in enumerate(args) if not dispatch.fits(a)] == []
    assert dispatch.fits(run.volume_arms(state)) and dispatch.fits(run._volume)


def count_typings(monkeypatch, *dispatchers) -> list:
    """The values numba's dispatch types in Python from now on (its fingerprint cache
    missed) in calls of ``dispatchers``."""
    typed = []
    for d in dispatchers:
        def typeof_pyval(val, original=d.typeof_pyval):
            typed.append(val)
            return original(val)
        monkeypatch.setattr(d, "typeof_pyval", typeof_pyval)
    return typed


def test_a_relaxation_with_a_new_run_per_sample_types_no_argument_after_its_first(
        monkeypatch):
    """relaxation_dynamic prepares a run per sample and calls it and force_on once each: after
    a first relaxation (compiling or loading the kernels), a second one's calls all find
    their types in numba's cache, and give the same forces."""
    model = relaxing_box()
    node = top_centre(model)
    times = np.linspace(0.002, 0.02, 10)
    depths = 1e-3 * np.minimum(times / 0.01, 1.0)
    dt = 0.5 * critical_time_step(model)
    first = relaxation_dynamic(model, node, np.array([0.0, 0.0, -1.0]), times, depths, dt,
                               progress=False)
    typed = count_typings(monkeypatch, step_kernels.run_verlet, node_volume_force)
    again = relaxation_dynamic(model, node, np.array([0.0, 0.0, -1.0]), times, depths, dt,
                               progress=False)
    assert typed == []
    np.testing.assert_array_equal(again, first)
    assert np.all(first[:, 2] < 0.0)  # the indenter's force pushes the particle down, in


def test_threaded_runs_type_no_argument_after_their_first(monkeypatch):
    """A new two-thread run per call (its work split in a group of three arrays)."""
    model = relaxing_box()
    dt = 0.5 * critical_time_step(model)
    integrator = VerletIntegrator()
    integrator.simulate(model, model.state(), dt, 2, threads=2)
    typed = count_typings(monkeypatch, step_kernels.run_verlet)
    for _ in range(5):
        integrator.simulate(model, model.state(), dt, 2, threads=2,
                            gravity=np.array([0.0, 0.0, -9.81]))
    assert typed == []


def test_the_static_volume_arms_call_types_no_argument_after_its_first_and_matches_the_kernel(
        monkeypatch):
    """The Newton path's volume forces with an arm step (:func:`statics.net_forces`) through
    :func:`add_volume_forces_grouped`: no typing after the first call, and bit for bit
    :func:`add_volume_forces` with the arms in one tuple."""
    model = relaxing_box()
    p = model.params
    rng = np.random.default_rng(3)
    r, c = p.volume_arm_recursion(1e-3, exact=True)
    step = statics.VolumeArmStep(r, c, rng.uniform(-50.0, 50.0, (model.n_tets, 2)),
                                 rng.uniform(-0.01, 0.01, model.n_tets))
    ar, ac = p.arm_recursion(1e-3)
    arms = statics.ArmStep(ar, ac, np.zeros((model.n_connectors, 2)),
                           np.zeros(model.n_connectors), volume=step)
    limits = (np.zeros(model.n_tets), np.full(model.n_tets, np.inf))
    x = model.rest_positions + 1e-4 * rng.standard_normal((model.n_particles, 3))
    first = statics.net_forces(model, x, p, True, arms, None, limits)
    typed = count_typings(monkeypatch, add_volume_forces_grouped)
    for _ in range(5):
        again = statics.net_forces(model, x, p, True, arms, None, limits)
    assert typed == []
    for got, expected in zip((*again[:4], *again[4]), (*first[:4], *first[4])):
        np.testing.assert_array_equal(got, expected)

    tets = kernels.index_view(model.tets)
    grouped, whole = np.zeros_like(x), np.zeros_like(x)
    outputs = [(np.zeros((model.n_tets, 2)), np.zeros(model.n_tets)) for _ in range(2)]
    add_volume_forces_grouped(x, tets, model.rest_volumes, p.kv, *limits, grouped,
                              (r, c, step.pressure_prev, step.strain_prev), outputs[0],
                              np.empty(model.n_tets))
    add_volume_forces(x, tets, model.rest_volumes, p.kv, *limits, whole,
                      (r, c, step.pressure_prev, step.strain_prev, *outputs[1]),
                      np.empty(model.n_tets))
    np.testing.assert_array_equal(grouped, whole)
    np.testing.assert_array_equal(outputs[0][0], outputs[1][0])
    np.testing.assert_array_equal(outputs[0][1], outputs[1][1])
    assert np.any(grouped != 0.0) and np.any(outputs[0][0] != 0.0)
