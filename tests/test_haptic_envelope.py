"""The haptic session's strain bands that follow the state (``HapticSession(envelope=...)``):
the stability bound of a band and its arms' history holds at the states inside them, and a
drag re-centres the bands, keeps fewer substeps than the fixed +-0.5 range and the same force."""
import dataclasses

import numpy as np
import pytest

from particle.haptics import HapticSession
from particle.params import connector_strain_bounds
from particle.stability import connector_strains, critical_time_step, step_bound
from particle.volume_bounds import volume_ratio_range
from tests.particle_models import box_model, top_centre
from tests.test_haptic_volume import jittered_box, mass_scaled_volume_tangent, strains_and_ratios


def relaxing(model, a=10.0, b=50.0):
    """``model`` with nonlinear springs (a, b [N/m]) and volume arms (kv1, kv2 [Pa])."""
    n = model.n_tets
    return model.with_params(dataclasses.replace(
        model.params, a=np.full(model.n_connectors, a), b=np.full(model.n_connectors, b),
        kv=np.full(n, 2e4), kv1=np.full(n, 1.2e4), bv1=np.full(n, 6e3), kv2=np.full(n, 8e3),
        bv2=np.full(n, 8e4)))


def mass_scaled_tangent(model, x, arm_forces, volume_arms):
    """M^{-1/2} K_t M^{-1/2} [1/s^2] (dense, free dofs) at ``x``: connectors with the arms'
    largest step coefficients k1 + k2 and forces ``arm_forces`` (E,) [N] in their tension,
    plus the volume term with ``volume_arms`` (:func:`mass_scaled_volume_tangent`)."""
    p = model.params
    d = x[model.edges[:, 1]] - x[model.edges[:, 0]]
    length = np.linalg.norm(d, axis=1)
    unit = d / length[:, None]
    eps = length / model.rest_lengths - 1.0
    axial = p.K0 + 2.0 * p.a * eps + 3.0 * p.b * eps ** 2 + p.k1 + p.k2
    tension = (p.K0 + p.a * eps + p.b * eps ** 2) * eps * model.rest_lengths + arm_forces
    geometric = tension / length
    blocks = ((axial - geometric)[:, None, None] * unit[:, :, None] * unit[:, None, :]
              + geometric[:, None, None] * np.eye(3))
    n = model.n_particles
    k = np.zeros((3 * n, 3 * n))
    for (i, j), blk in zip(model.edges, blocks):
        for r, c, sign in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
            k[3 * r:3 * r + 3, 3 * c:3 * c + 3] += sign * blk
    dof = np.repeat(~model.fixed, 3)
    scale = 1.0 / np.sqrt(np.repeat(model.masses, 3)[dof])
    return (scale[:, None] * k[np.ix_(dof, dof)] * scale
            + mass_scaled_volume_tangent(model, x, volume_arms))


@pytest.mark.parametrize("seed", [0, 1])
def test_the_band_bound_is_above_the_tangent_at_states_inside_the_bands(seed):
    """Rigour: bands of half-width 0.05 centred on a stretched state (strains up to ~0.1) with
    the history of a session that started at rest (bands +-0.05 there): at the centre and at
    random states around it whose strains lie in the bands, with arm forces ``(k1 + k2)(dx -
    m)`` and volume arm pressures ``(kv1 + kv2)(j - m)`` for random ``m`` in the history's
    hull (the convolution's convex combination), the largest eigenvalue of the assembled
    mass-scaled tangent stays below the band's bound. The bound is well below the fixed
    +-0.5 range's (what makes the session's step larger)."""
    model = relaxing(jittered_box(seed))
    p = model.params
    centre = model.rest_positions.copy()
    centre[:, 2] *= 1.1
    eps = connector_strains(model, centre - model.rest_positions)
    lo, hi = eps - 0.05, eps + 0.05
    history = (np.minimum(lo, -0.05), np.maximum(hi, 0.05))
    bound = step_bound(model, (lo, hi), history).omega2
    h_lo, h_hi = history
    j_lo, j_hi = volume_ratio_range(model, lo, hi)
    jh_lo, jh_hi = volume_ratio_range(model, h_lo, h_hi)
    rng = np.random.default_rng(seed)
    free = ~model.fixed
    samples = 0
    for amplitude in (0.0, 1e-4, 2e-4, 4e-4) * 4:
        x = centre.copy()
        x[free] += amplitude * rng.standard_normal((int(free.sum()), 3))
        strain, ratio = strains_and_ratios(model, x)
        inside = (np.all((lo <= strain) & (strain <= hi))
                  and np.all((j_lo < ratio) & (ratio <= j_hi)))
        if not inside:
            continue
        samples += 1
        for extreme in (0.0, 1.0):  # the arms' mean at a random point or at the history's floor
            mean = np.where(extreme > 0.0, h_lo, rng.uniform(h_lo, h_hi))
            arm_forces = (p.k1 + p.k2) * (strain - mean) * model.rest_lengths
            volume_mean = np.where(extreme > 0.0, jh_lo, rng.uniform(jh_lo, jh_hi))
            k = p.kv1 + p.kv2
            tangent = mass_scaled_tangent(model, x, arm_forces, (k, k * (ratio - volume_mean)))
            assert np.linalg.eigvalsh(tangent)[-1] <= bound
    assert samples >= 6
    assert bound < 0.5 * step_bound(model, (-0.5, 0.5)).omega2


def test_an_enveloped_session_drags_with_fewer_substeps_and_the_same_force():
    """A (6, 6, 3) box with relaxing volume dragged 3 mm down at its top centre: the session
    whose bands (half-width 0.05) follow the state re-centres them as the strains grow, stays
    stable, takes fewer substeps than the fixed +-0.5 range, and its tool force differs from
    that session's by the step's discretisation only: RMS below 1e-3 of the largest force,
    the drag error a faster haptic variant may cost (5 vs 2 substeps: 5.4e-4)."""
    model = relaxing(box_model((6, 6, 3), size=0.06), a=0.0, b=0.0)
    node = top_centre(model)
    fixed = HapticSession(model, 0.9 * critical_time_step(model))
    enveloped = HapticSession(model, 1e-3, envelope=0.05)
    start = model.rest_positions[node]
    forces = []
    for k in range(300):
        target = start + np.array([0.0, 0.0, -0.003 * min(1.0, k / 150)])
        forces.append((fixed.step(node, target), enveloped.step(node, target)))
    forces = np.array(forces)
    assert enveloped.recentred >= 1
    assert enveloped.substeps < fixed.substeps
    scale = np.max(np.linalg.norm(forces[:, 0], axis=1))
    error = np.linalg.norm(forces[:, 1] - forces[:, 0], axis=1)
    assert np.sqrt(np.mean(error ** 2)) < 1e-3 * scale
