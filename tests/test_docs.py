"""Generated documentation (``python -m pipelines docs``): every committed table is what the
command writes from the committed results, and the docs carry no development history."""
import copy
import json
import re

import pytest

from forcecal.errors import DataFileError
from pipelines.docs import NO_VERDICT, Sources, regenerate, report_verdict, stale, summary_table
from tests.conftest import ROOT

PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def test_every_generated_block_is_what_the_docs_command_writes():
    assert stale(ROOT) == [], "run `python -m pipelines docs` and commit the pages"


def test_the_readme_shows_every_shipped_scene_at_a_glance():
    src = Sources(ROOT)
    readme = (ROOT / "README.md").read_text()
    assert "<!-- generated: results -->" in readme
    assert src.scenes()[0] == "liver"
    for name in src.scenes():
        assert f"**`{name}`**" in readme


def test_a_scratch_run_under_runs_is_no_shipped_scene(tmp_path):
    import shutil
    (tmp_path / "scenes").mkdir()
    shutil.copy(ROOT / "scenes" / "liver.toml", tmp_path / "scenes" / "liver.toml")
    for folder in ("liver", "tmp-liver-check", "bench"):  # the scratch run is of scene liver
        (tmp_path / "runs" / folder).mkdir(parents=True)
        shutil.copy(ROOT / "runs" / "liver" / "report.json",
                    tmp_path / "runs" / folder / "report.json")
    assert Sources(tmp_path).scenes() == ["liver"]


def test_a_block_is_rewritten_and_the_text_around_it_kept():
    text = "before\n<!-- generated: scene keys -->\nstale table\n<!-- end generated -->\nafter\n"
    out = regenerate(text, Sources(ROOT))
    assert out.startswith("before\n<!-- generated: scene keys -->\n| key |")
    assert out.endswith("\n<!-- end generated -->\nafter\n")
    assert "stale table" not in out
    assert regenerate(out, Sources(ROOT)) == out


def test_an_unknown_block_is_refused_by_name():
    with pytest.raises(DataFileError, match="unknown generated block 'results of mars'"):
        regenerate("<!-- generated: results of mars -->\n<!-- end generated -->\n",
                   Sources(ROOT))


def test_the_summary_says_when_a_report_predates_the_verdict_and_shows_its_status_otherwise():
    report = json.loads((ROOT / "runs" / "liver" / "report.json").read_text())
    report.pop("verdict", None)
    assert summary_table(report).endswith(f"Verdict: {NO_VERDICT}.")
    judged = copy.deepcopy(report)
    judged["verdict"], judged_now = report_verdict(report)
    assert judged_now
    table = summary_table(judged)
    checks = judged["verdict"]["checks"]
    status_row = next(line for line in table.splitlines() if line.startswith("| status |"))
    assert status_row.count("**") == 2 * 6  # one status per column
    assert f"**{checks['held_out_indentation']['status']}**" in status_row
    assert table.splitlines()[-1].startswith("Verdict: ")
    assert NO_VERDICT not in table
    assert report_verdict(judged) == (judged["verdict"], False)


# development history belongs in git log, not in the docs or the docstrings
HISTORY = re.compile(r"\bissues? \d+|\bissue #?\d+|#\d{2,}\b|\b20\d\d-\d\d-\d\d\b"
                     r"|\b(?:commit|at) `?[0-9a-f]{7,40}\b")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_the_docs_cite_no_issue_numbers_dates_or_commits(page):
    # the corpus pages are generated records of runs: their dates and commits
    if page.name in ("corpus.md", "corpus_recipe.md"):
        return
    found = HISTORY.findall(page.read_text())
    assert not found, f"{page.name}: {found}"


def test_the_code_cites_no_issue_numbers():
    packages = ("forcecal", "particle", "calibration", "reference_fe", "pipelines", "studies",
                "tests", "examples")
    hits = [f"{path.relative_to(ROOT)}:{n}" for package in packages
            for path in sorted((ROOT / package).rglob("*.py"))
            for n, line in enumerate(path.read_text().splitlines(), 1)
            if re.search(r"\bissues? \d+\b|\(issue \d", line)]
    assert not hits, hits


def test_the_docs_command_rewrites_stale_blocks_and_check_says_so(tmp_path, capsys):
    from pipelines.cli import main
    readme = tmp_path / "README.md"
    readme.write_text("# x\n<!-- generated: scene keys -->\nSTALE\n<!-- end generated -->\n")
    assert main(["docs", "--root", str(tmp_path), "--check"]) == 1
    assert f"stale: {readme}" in capsys.readouterr().out
    assert "STALE" in readme.read_text()
    assert main(["docs", "--root", str(tmp_path)]) == 0
    assert "STALE" not in readme.read_text() and "`calibration.method`" in readme.read_text()
    assert main(["docs", "--root", str(tmp_path), "--check"]) == 0


def test_the_corpus_page_is_written_from_corpus_json_when_there_is_one(tmp_path):
    from pipelines import corpus
    from pipelines.docs import generated
    assert tmp_path / corpus.DOCS not in generated(tmp_path)  # no corpus run: no page
    data = {"kind": corpus.KIND, "version": corpus.VERSION, "scenes": [], "date": "d",
            "git_commit": "c", "cpus": 2, "loadavg_start": [0.1, 0.1, 0.1], "loadavg_end": [],
            "wall_time_s": 60.0, "scenes_time_s": 0.0, "passed": False}
    corpus.write_corpus(tmp_path / "runs" / "corpus" / "corpus.json", data)
    assert generated(tmp_path)[tmp_path / corpus.DOCS] == corpus.corpus_markdown(data)
    assert tmp_path / corpus.RECIPE_DOCS not in generated(tmp_path)
    recipe = {**data, "recipe": True}  # the recipe corpus: its own page, its own title
    corpus.write_corpus(tmp_path / corpus.RECIPE_OUT / "corpus.json", recipe)
    page = generated(tmp_path)[tmp_path / corpus.RECIPE_DOCS]
    assert page == corpus.corpus_markdown(recipe) and "own-mesh recipe" in page.splitlines()[0]
