"""The README states what the code and the committed run say: results, figures, file schemas."""
import re

import calibration.results
import pipelines.gravity
from pipelines.figures import FIGURES
from pipelines.report import read_report, results_markdown
from tests.conftest import ROOT

README = (ROOT / "README.md").read_text()


def _table(module) -> list[str]:
    return [line for line in module.__doc__.splitlines() if line.startswith("|")]


def test_readme_results_are_the_committed_report():
    # the README's numbers are generated from runs/liver/report.json, never typed in
    report = read_report(ROOT / "runs" / "liver" / "report.json")
    assert results_markdown(report) in README
    assert report["scene"] == "liver"


def test_readme_figures_exist_and_every_figure_is_shown():
    shown = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", README)
    assert shown
    for path in shown:
        assert (ROOT / path).is_file(), path
    assert {f"runs/liver/figures/{name}" for name in FIGURES} <= set(shown)


def test_readme_file_schemas_match_the_code():
    for module in (calibration.results, pipelines.gravity):
        for line in _table(module):
            assert line in README, f"README lacks {module.__name__} schema row {line}"
