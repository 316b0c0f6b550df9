"""The independent check (studies/independent_check.py): what it records of a run's report,
its scene as the README's recipe, and its refusal of a mesh that is not the pinned one."""
import json
import subprocess

import pytest
import tomllib

from studies.independent_check import SCENE, summary, write_mesh
from tests.conftest import SCENES


def test_the_summary_is_the_reports_verdict_checks_and_body_record():
    report = json.loads((SCENES.parent / "runs" / "user_organ_punch" / "report.json").read_text())
    got = summary(report)
    assert got["passed"] == report["verdict"]["passed"]
    assert set(got["checks"]) == set(report["verdict"]["checks"])
    for name, check in got["checks"].items():
        want = report["verdict"]["checks"][name]
        assert check == {k: want[k] for k in ("status", "calibrated", "baseline", "goal",
                                              "reason")}
    assert got["body"]["kinds"] == report["body"]["kinds"]
    assert got["fe_failures"] == report["fe_failures"]


def test_the_scene_is_the_readmes_recipe_with_the_changes_its_comments_name():
    """Every key the README's recipe sets is set, to the recipe's value except those the
    scene's comments explain (mesh, support tolerances and sides, punch radius, depths)."""
    readme = (SCENES.parent / "README.md").read_text()
    recipe = tomllib.loads(readme.split('```toml\n', 1)[1].split("```", 1)[0])
    scene = tomllib.loads(SCENE.read_text())
    changed = {("mesh", "source"), ("mesh", "scale"), ("fixed", "tolerance"),
               ("second_support", "axis"), ("second_support", "side"),
               ("second_support", "tolerance"), ("indentation", "radius")}
    for section, keys in recipe.items():
        if not isinstance(keys, dict):
            continue
        for key, value in keys.items():
            assert key in scene[section], (section, key)
            if (section, key) not in changed:
                assert scene[section][key] == value, (section, key)
    assert scene["experiments"] == recipe["experiments"]
    assert scene["indentation"]["depth"] == scene["relaxation"]["depth"] == 0.004


def test_a_repository_without_the_pinned_commit_is_refused(tmp_path):
    git = ["git", "-C", str(tmp_path)]
    subprocess.run(git + ["init", "-q"], check=True)
    with pytest.raises(SystemExit, match="cannot read share/mesh/liver.msh"):
        write_mesh(tmp_path / ".git")
