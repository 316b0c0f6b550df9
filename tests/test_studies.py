"""The studies package: its layer (nothing of forcecal imports it), its command lines and its
docs page (``docs/studies.md``, generated from the committed results)."""
import ast
import importlib
import json
import pkgutil
import re

import pytest

import studies
from studies.catalogue import STUDIES, main as catalogue_main, page
from tests.conftest import ROOT

PRODUCT = ("forcecal", "particle", "calibration", "reference_fe", "pipelines", "examples")
MODULES = sorted(m.name for m in pkgutil.iter_modules(studies.__path__)
                 if not m.name.startswith("_") and m.name != "catalogue")


def imported_modules(path):
    """Every module ``path`` imports, and every string naming one for a dynamic import
    (``"studies.x"``, ``"studies.x:function"``; not a bare word)."""
    names = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append(node.module)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and re.fullmatch(
                r"\w+(\.\w+)+(:\w+)?|\w+:\w+", node.value):
            # a dotted path or "module:function" (a bare word such as the runs/ folder name
            # "studies" names no module to import)
            names.append(node.value.split(":")[0])
    return names


def is_study(name):
    return name == "studies" or name.startswith("studies.")


def test_nothing_of_forcecal_imports_a_study():
    offenders = [f"{path.relative_to(ROOT)}: {name}" for package in PRODUCT
                 for path in sorted((ROOT / package).rglob("*.py"))
                 for name in imported_modules(path) if is_study(name)]
    assert offenders == []


def test_only_the_studies_own_tests_import_them():
    """A test of forcecal's product never reads a study; a study's tests are named after it."""
    own = {f"test_study_{m}.py" for m in MODULES} | {"test_studies.py"}
    importing = {path.name for path in (ROOT / "tests").glob("*.py")
                 if any(is_study(n) for n in imported_modules(path))}
    assert importing <= own, importing - own


def test_every_study_is_on_the_docs_page_with_its_results():
    assert sorted(s.module for s in STUDIES) == MODULES
    for study in STUDIES:
        assert list(ROOT.glob(study.results)), f"{study.module}: no committed result"
        assert f"## {study.module}\n" in page()


def test_the_docs_page_is_what_the_catalogue_writes(capsys):
    assert (ROOT / "docs" / "studies.md").read_text() == page()
    assert catalogue_main(["--check"]) == 0


def test_the_page_rebuilds_each_command_from_its_result():
    """fold_cv: --variants only when they are not the default ones; the result's own scene
    and output path."""
    from studies.catalogue import fold_cv_answer, fold_cv_command

    result = json.loads((ROOT / "runs/studies/fold_cv_prior.json").read_text())
    command = fold_cv_command("runs/studies/x.json", result)
    assert command.startswith("python -m studies.fold_cv --scene scenes/liver_punch.toml "
                              "--variants '")
    variants = json.loads(command.split("--variants '")[1].split("'")[0])
    assert variants == {label: v["changes"] for label, v in result["variants"].items()}
    assert command.endswith("--out runs/studies/x.json")
    assert fold_cv_answer(result).endswith(f"**{result['chosen']}**")
    default = json.loads((ROOT / "runs/studies/fold_cv.json").read_text())
    assert "--variants" not in fold_cv_command("f.json", default)


@pytest.mark.parametrize("module", MODULES)
def test_each_study_has_one_command_line(module, capsys):
    """``python -m studies.<name> --help`` prints its usage; an unknown option is refused
    before anything runs."""
    main = importlib.import_module(f"studies.{module}").main
    with pytest.raises(SystemExit) as done:
        main(["--help"])
    assert done.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: python -m studies.{module}")
    with pytest.raises(SystemExit) as done:
        main(["--no-such-option"])
    assert done.value.code == 2


@pytest.mark.parametrize("module, argv, expected", [
    ("fold_cv", ["--scene", "s.toml", "--variants", '{"a": {"local": false}}', "--run", "r"],
     (("s.toml", "r", {"a": {"local": False}}, None), {})),
    ("sag_split", ["--scene", "s.toml"], (("s.toml", None), {})),
    ("sag_tradeoff", ["--scene", "s.toml", "--regions", "24", "--iterations", "3"],
     (("s.toml", None, 24, 3), {})),
    ("release_levers", ["--scene", "s.toml", "--run", "r"], (("s.toml", "r"), {})),
])
def test_the_finished_run_studies_pass_their_arguments_on(module, argv, expected,
                                                          monkeypatch):
    """The studies of a finished run take its scene (required) and folder (default: the
    scene's ``runs/<name>``, resolved by the study) and their own options, typed."""
    target = importlib.import_module(f"studies.{module}")
    calls = []

    class Stop(Exception):
        pass

    def study(*args, **kwargs):
        calls.append((args, kwargs))
        raise Stop

    monkeypatch.setattr(target, "study", study)
    with pytest.raises(Stop):
        target.main(argv)
    assert calls == [expected]
    with pytest.raises(SystemExit) as done:
        target.main([])  # --scene is required
    assert done.value.code == 2


@pytest.mark.parametrize("module, committed", [
    ("fold_cv", "fold_cv_force_vector_user_organ.json"),
    ("sag_split", "sag_split_force_vector.json"),
    ("sag_tradeoff", "sag_tradeoff_liver_punch.json"),
    ("release_levers", "release_levers_force_vector.json"),
])
def test_a_finished_run_study_writes_its_result_under_runs_studies(module, committed,
                                                                   monkeypatch, tmp_path):
    """Without ``--out`` the result goes to ``runs/studies/<study>_<scene>.json`` (relative
    to where the command runs), with it where told; the study's own result, as JSON."""
    result = json.loads((ROOT / "runs" / "studies" / committed).read_text())
    target = importlib.import_module(f"studies.{module}")
    monkeypatch.setattr(target, "study", lambda *args: result)
    monkeypatch.chdir(tmp_path)
    target.main(["--scene", "s.toml"])
    written = tmp_path / "runs" / "studies" / f"{module}_{result['scene']}.json"
    assert json.loads(written.read_text()) == result
    target.main(["--scene", "s.toml", "--out", "elsewhere/result.json"])
    assert json.loads((tmp_path / "elsewhere" / "result.json").read_text()) == result
