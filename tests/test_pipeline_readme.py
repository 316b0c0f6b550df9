"""The README and the docs state what the code and the committed runs say: the commands,
results, figures, file schemas and the particle model's example."""
import re
from pathlib import Path

import calibration.results
import pipelines.gravity
from pipelines.figures import FIGURES
from pipelines.report import read_report, results_markdown
from tests.conftest import ROOT

README = (ROOT / "README.md").read_text()
DOCS = ROOT / "docs"


def _table(module) -> list[str]:
    return [line for line in module.__doc__.splitlines() if line.startswith("|")]


def _images(page: Path) -> list[Path]:
    """The images a Markdown page shows, as paths (relative to the page's folder)."""
    return [(page.parent / p).resolve()
            for p in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", page.read_text())]


def test_the_readme_gives_the_two_commands_and_ci_runs_its_test_command():
    block = README.split("## The two commands", 1)[1].split("```bash\n", 1)[1].split("```")[0]
    commands = [line.split("#")[0].strip() for line in block.splitlines()]
    assert commands == ["make demo", "make test"]
    ci = [line for line in (ROOT / ".ci" / "run").read_text().splitlines()
          if line and not line.startswith(("#", "set ", "cd "))]
    assert ci == ["make test"]


def test_results_page_shows_the_committed_report():
    # the numbers are generated from runs/liver/report.json, never typed in
    report = read_report(ROOT / "runs" / "liver" / "report.json")
    assert results_markdown(report) in (DOCS / "results.md").read_text()
    assert report["scene"] == "liver"


def test_every_figure_of_the_default_liver_is_shown_and_every_image_exists():
    for page in [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]:
        for image in _images(page):
            assert image.is_file(), f"{page.name} shows a missing image {image}"
    shown = set(_images(DOCS / "results.md"))
    assert {(ROOT / "runs/liver/figures" / name).resolve() for name in FIGURES} <= shown
    assert _images(ROOT / "README.md"), "the README shows what forcecal does in one picture"


def test_data_files_page_has_the_schemas_of_the_code():
    page = (DOCS / "data-files.md").read_text()
    for module in (calibration.results, pipelines.gravity):
        for line in _table(module):
            assert line in page, f"docs/data-files.md lacks {module.__name__} schema row {line}"


def test_particle_model_example_runs(monkeypatch):
    text = (DOCS / "particle-model.md").read_text()
    code = text.split("```python\n", 1)[1].split("```", 1)[0]
    monkeypatch.chdir(ROOT)
    namespace: dict = {}
    exec(compile(code, "docs/particle-model.md", "exec"), namespace)
    # what the comments say the objects are
    problem = namespace["problem"]
    assert namespace["sag"].shape == (problem.mesh.n_vertices, 3)
    assert namespace["forces"].shape == (len(problem.test_points), 10)
    assert namespace["stiffer"].shape == (2, len(problem.test_points), 10)
    assert (namespace["stiffer"][1] > namespace["stiffer"][0]).all()  # stiffer springs push harder
    assert namespace["force"].shape == (3,)


def test_the_own_mesh_recipe_is_a_valid_scene_with_the_whole_body_method(tmp_path):
    """The README's scene for a user's own mesh loads (on the user organ's mesh) and asks for
    the whole-body method: the FE's whole-body data fitted by the gradient method, the
    second held-out body test, the discretisation floor, the relaxing volume term."""
    from forcecal.scene import load_scene

    section = README.split("## Running your own mesh", 1)[1]
    recipe = section.split("```toml\n", 1)[1].split("```")[0]
    mesh = (ROOT / "scenes" / "meshes" / "user_organ.vtu").as_posix()
    (tmp_path / "my_organ.toml").write_text(recipe.replace('"meshes/my_organ.vtu"',
                                                           f'"{mesh}"'))
    scene = load_scene(tmp_path / "my_organ.toml")
    assert {"body", "second_support", "floor"} <= set(scene.experiments)
    assert scene.calibration.method == "gradient" and scene.calibration.body_data != "none"
    assert scene.particle.volume == "viscoelastic"
