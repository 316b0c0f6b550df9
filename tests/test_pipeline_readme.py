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


def test_readme_particle_model_example_runs(monkeypatch):
    block = README.split("## The particle model", 1)[1].split("```python\n", 1)[1]
    code = block.split("```", 1)[0]
    monkeypatch.chdir(ROOT)
    namespace: dict = {}
    exec(compile(code, "README.md: The particle model", "exec"), namespace)
    # what the comments say the objects are
    problem = namespace["problem"]
    assert namespace["sag"].shape == (problem.mesh.n_vertices, 3)
    assert namespace["forces"].shape == (len(problem.test_points), 10)
    assert namespace["stiffer"].shape == (2, len(problem.test_points), 10)
    assert (namespace["stiffer"][1] > namespace["stiffer"][0]).all()  # stiffer springs push harder
    assert namespace["force"].shape == (3,)
