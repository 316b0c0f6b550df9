"""The body-stiffness-gap study (studies/body_stiffness_gap.py): its closed forms (the sag a
uniform stiffness error predicts, the level that matches rest frequencies), the levelled
global set's modes, and the rows it reads from a report."""
import numpy as np

from calibration.parametrisation import GlobalParams
from forcecal.mesh import box_mesh
from particle.body import RestOperators, model_modes
from particle.model import ModelBuilder
from studies import body_stiffness_gap as gap


def test_a_uniform_softening_predicts_its_own_sag():
    """Every stiffness times ``s``: every frequency times ``sqrt(s)``, the static sag times
    ``1 / s``."""
    for s in (0.64, 1.0, 1.21):
        errors = np.full(3, np.sqrt(s) - 1.0)
        np.testing.assert_allclose(gap.predicted_sag_error(errors), 1.0 / s - 1.0, atol=1e-14)


def test_the_level_matches_proportional_frequencies_and_solves_the_normal_equation():
    """Ratios all ``rho``: the factor ``1 / rho^2`` puts every frequency on the FE's; uneven
    ratios: ``sqrt(c)`` zeroes the least-squares gradient ``sum r_i (r_i sqrt(c) - 1)``."""
    np.testing.assert_allclose(gap.rest_mode_level(np.full(6, 0.9)), 1 / 0.81, rtol=1e-14)
    r = np.array([0.8, 0.95, 1.1, 0.9, 0.85, 1.02])
    root = np.sqrt(gap.rest_mode_level(r))
    assert abs(np.sum(r * (r * root - 1.0))) < 1e-14


def test_levelling_scales_every_stiffness_and_every_frequency_by_its_root():
    """A clamped 3 x 2 x 2-cell box with a global set (springs, arms, relaxing volume term):
    the levelled set's rest eigenvalues at both moduli are the factor times the global
    set's (shapes, ratios and times kept)."""
    mesh = box_mesh((3, 2, 2), (0.06, 0.04, 0.04))
    glob = GlobalParams(K0=50.0, alpha=-0.3, beta=2.0, k1=30.0, tau1=0.5, k2=20.0, tau2=10.0,
                        kv=4000.0, kv1=2000.0, kv2=1000.0)
    factor = 1.3
    scaled = gap.levelled(glob, factor)
    assert (scaled.alpha, scaled.beta, scaled.tau1, scaled.tau2) == (
        glob.alpha, glob.beta, glob.tau1, glob.tau2)
    values = {}
    for name, params in (("global", glob), ("levelled", scaled)):
        builder = ModelBuilder()
        builder.add_particles(mesh.vertices, mesh.lumped_masses(1060.0),
                              mesh.vertices[:, 2] < 1e-9)
        builder.add_connectors(mesh.edges)
        model = builder.finalize(params.connector_params(len(mesh.edges)), mesh.tets)
        ops = RestOperators.of(model)
        values[name] = [model_modes(model, ops, m, 4)[0] for m in gap.MODULI]
    for before, after in zip(values["global"], values["levelled"]):
        np.testing.assert_allclose(after, factor * before, rtol=1e-9)


def test_the_rows_read_a_reports_modes_and_sags():
    modes = {m: {"frequency_errors": [-0.1, -0.05, 0.0, 0.2]} for m in gap.MODULI}
    report = {"body": {"variants": {v: modes for v in gap.VARIANTS}},
              "gravity": {"fe_max_static_sag_m": 0.01, "global_max_static_sag_m": None,
                          "calibrated_max_static_sag_m": 0.012,
                          "baseline_max_static_sag_m": 0.009}}
    rows = gap.report_rows(report)
    assert rows["global"]["static_sag_error"] is None
    np.testing.assert_allclose(rows["calibrated"]["static_sag_error"], 0.2, rtol=1e-12)
    np.testing.assert_allclose(rows["baseline"]["static_sag_error"], -0.1, rtol=1e-12)
    # the lowest three modes only
    expected = np.mean(np.array([0.9, 0.95, 1.0]) ** -2) - 1.0
    np.testing.assert_allclose(rows["baseline"]["predicted_sag_error"], expected, rtol=1e-14)
