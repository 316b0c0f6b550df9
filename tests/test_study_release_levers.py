"""The release study (studies/release_levers.py): its integrator and its consistent mass."""
import dataclasses

import numpy as np

from particle.experiments import gravity_dynamic
from tests.particle_models import box_model
from studies.release_levers import Lever, consistent_mass, release

GRAVITY = np.array([0.0, 0.0, -9.81])
DENSITY = 1000.0


def volume_box():
    """A clamped viscoelastic box with the volume term (kv = 2 kPa on every tet)."""
    model = box_model((3, 3, 2), density=DENSITY, K0=20.0, a=5.0, b=10.0)
    return model.with_params(dataclasses.replace(model.params, kv=np.full(model.n_tets, 2e3)))


def test_the_unchanged_model_repeats_the_gravity_stage_release():
    """Lumped mass, elastic kv, arms x1: the compiled integrator's release (the gravity
    stage's), at the same samples, to round-off."""
    model = volume_box()
    times = np.arange(1, 41) * 2e-3
    dt = 0.5e-3
    stage = gravity_dynamic(model, GRAVITY, float(times[-1]), dt, times)
    p = model.params
    ours = release(model, DENSITY, GRAVITY, times, dt, Lever("model"),
                   (20.0, float(p.k1[0]), float(p.tau1[0]), float(p.k2[0]), float(p.tau2[0])))
    scale = np.abs(stage).max()
    assert scale > 1e-4  # the box sags visibly in 80 ms
    assert np.abs(ours - stage).max() <= 1e-12 * scale


def test_the_consistent_mass_lumps_to_the_model_masses_within_the_step_bound():
    """Row sums = the lumped masses (rho V/4 per tet); symmetric; the lumped-to-consistent
    eigenvalues lie in [1/5, 1], the bound behind the study's shorter step."""
    model = volume_box()
    m = consistent_mass(model, DENSITY)
    assert np.allclose(np.asarray(m.sum(axis=1)).ravel(), model.masses, rtol=1e-13, atol=0)
    dense = m.toarray()
    assert np.allclose(dense, dense.T, rtol=1e-14, atol=0)
    lumped = np.diag(1.0 / np.sqrt(model.masses))
    ratio = np.linalg.eigvalsh(lumped @ dense @ lumped)
    assert ratio.min() >= 0.2 - 1e-12 and ratio.max() <= 1.0 + 1e-12
