"""Scale study: growth exponents recover power laws exactly; the table shows every size."""
import pytest

from pipelines.bench.scale import growth_exponent, scale_table


def test_growth_exponent_of_a_power_law_is_its_power():
    vertices = [300, 1000, 3000, 10000]
    assert growth_exponent(vertices, [2e-3 * v ** 1.5 for v in vertices]) == pytest.approx(
        1.5, rel=1e-12)
    # sizes without a value (None, e.g. the FE skipped) are left out of the fit
    assert growth_exponent(vertices, [7.0 * 300, None, 7.0 * 3000, None]) == pytest.approx(
        1.0, rel=1e-12)
    assert growth_exponent(vertices, [1.0, None, None, None]) is None


def test_scale_table_has_a_row_per_size_and_the_exponents():
    row = {"vertices": 282, "tets": 885, "connectors": 1400, "points_s": 0.05, "coverage": 0.87,
           "step_us": 20.0, "calibration_s": 30.0, "evaluations": 150, "fe_indentation_s": 4.0,
           "fe_relaxation_s": 12.0, "fe_gravity_static_s": 2.0, "fe_dynamic_step_s": 0.3,
           "fe_reference_s": 800.0, "peak_rss_mb": 450.0, "fe_estimated_items": []}
    big = {**row, "vertices": 4843, "fe_relaxation_s": 99.0,
           "fe_estimated_items": ["relaxation", "gravity_dynamic"]}
    table = scale_table({"scale": [row, big], "scale_study": {"exponents": {
        "points_s": 1.1, "step_us": 1.0, "calibration_s": 1.2, "fe_indentation_s": 1.4,
        "fe_reference_s": 1.3, "peak_rss_mb": 0.5}}}).splitlines()
    assert len(table) == 2 + 2 + 1
    assert table[2].startswith("| 282 | 885 | 1400 | 0.05 (87 %) | 20.0 | 30 (150) | 4.0 / 12.0 /")
    assert "99.0* /" in table[3]  # estimated items are starred
    assert table[4].startswith("| growth exponent | | | 1.10 | 1.00 | 1.20 | 1.40")


def test_a_child_reports_its_own_peak_memory_not_its_parents():
    """The parent holds ~400 MB when it starts the child; the child's peak stays far below
    (``ru_maxrss`` would report at least the parent's 400 MB there)."""
    import subprocess
    import sys

    import numpy as np

    from pipelines.bench.scale import peak_rss_mb

    held = np.ones(50_000_000)  # 400 MB, every page touched
    assert peak_rss_mb() >= held.nbytes / 2**20
    out = subprocess.run([sys.executable, "-c", "from pipelines.bench.scale import peak_rss_mb; "
                          "print(peak_rss_mb())"], capture_output=True, text=True, check=True)
    child = float(out.stdout)
    assert 1.0 < child < 0.5 * held.nbytes / 2**20
