"""The corpus runner (pipelines/corpus.py) on a fake pipeline, and the corpus's scenes.

The runner is tested with a stand-in for ``python -m pipelines demo`` that prints the
pipeline's log lines and writes what it writes (report.json, cache records), so every
outcome the runner must record -- a report with and without the verdict keys, a scene
that ends in an ``error:`` line, an up-to-date scene, an interrupted one -- happens in
well under a second. The corpus's own scene files are checked without any FE work.
"""
import importlib.util
import json
import sys
import textwrap
import tomllib

import pytest

from pipelines import corpus
from tests.conftest import ROOT, SCENES

# a stand-in for `python -m pipelines demo --scene S --out O`: what it does is chosen by the
# scene file's stem; like the pipeline, it reruns nothing when its outputs are up to date
FAKE_PIPELINE = textwrap.dedent('''
    import json, sys
    from pathlib import Path
    scene, out = Path(sys.argv[1]), Path(sys.argv[2])
    kind = scene.stem.split("_", 1)[1]
    stages = ("reference", "calibrate", "gravity", "report")
    seconds = {"reference": 60.0, "calibrate": 30.0, "gravity": 6.0, "report": 3.0}
    out.mkdir(parents=True, exist_ok=True)
    log = Path(sys.argv[3])
    with open(log, "a") as fh:
        fh.write(scene.stem + "\\n")
    if kind == "ok" and (out / "report.json").is_file():
        for s in stages:
            print(f"INFO pipelines.stages: {s:<9} up to date, skipped (inputs and outputs "
                  f"match {out}/cache/{s}.json)", file=sys.stderr)
        sys.exit(0)
    if kind == "refused":
        print(f"error: {scene.parent / 'missing.vtu'}: mesh file does not exist [stage "
              "reference; kept: nothing]", file=sys.stderr)
        sys.exit(2)
    if kind == "slow":  # an FE reference with two of its work items finished, then quiet
        (out / "reference.h5.parts").mkdir()
        for item in ("indentation-0000", "relaxation-0000"):
            (out / "reference.h5.parts" / f"{item}.npz").write_bytes(b"")
        print("INFO pipelines.stages: reference running: no cache record", file=sys.stderr,
              flush=True)
        import time
        time.sleep(2.0)
        sys.exit(0)
    if kind == "interrupted":
        print("INFO pipelines.stages: reference running: no cache record", file=sys.stderr)
        print("interrupted; rerun the same command to resume", file=sys.stderr)
        sys.exit(130)
    for s in stages:
        print(f"INFO pipelines.stages: {s:<9} running: no cache record", file=sys.stderr)
        if kind == "broken" and s == "calibrate":
            print("error: indentation of particle 50 0.0047 -> 0.0047 failed | Newton did not "
                  "converge [stage calibrate; kept: reference.h5; rerun the same command to "
                  "resume]", file=sys.stderr)
            sys.exit(2)
        (out / "cache").mkdir(exist_ok=True)
        (out / "cache" / f"{s}.json").write_text(json.dumps({"version": 3,
                                                             "elapsed_s": seconds[s]}))
        print(f"INFO pipelines.stages: {s:<9} done in {seconds[s]:.1f} s: x", file=sys.stderr)
    report = {"scene": scene.stem}
    if kind == "ok":
        report["verdict"] = {"passed": False, "require_no_worse_than_baseline": True,
            "checks": {
                "held_out_indentation": {"calibrated": 0.034, "baseline": 0.052, "goal": 0.1,
                                         "status": "passed", "passed": True, "reason": None},
                "static_sag": {"calibrated": 0.196, "baseline": 0.138, "goal": 0.15,
                               "status": "failed", "passed": False,
                               "reason": "worse than the baseline"},
                "release_rms": {"calibrated": None, "baseline": None, "goal": 0.3,
                                "status": "not_run", "passed": None,
                                "reason": "FE release failed"}}}
        report["realtime"] = {"substeps_per_ms": 3, "step_p99_us": 412.5}
    (out / "report.json").write_text(json.dumps(report))
    print("reference  ran  60.0 s", flush=True)
''')


@pytest.fixture()
def fake_corpus(tmp_path):
    """A corpus folder of copies of scenes/tiny.toml named for what the fake pipeline does
    (the meshes are the tiny generated liver), and the command running the fake on them."""
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    for stem in ("a_broken", "b_ok", "c_noverdict"):
        (scenes / f"{stem}.toml").write_text((SCENES / "tiny.toml").read_text()
                                             .replace('name = "tiny"', f'name = "{stem}"'))
    fake = tmp_path / "fake_pipeline.py"
    fake.write_text(FAKE_PIPELINE)
    calls = tmp_path / "calls.txt"

    def command(scene, out):
        return [sys.executable, str(fake), str(scene), str(out), str(calls)]
    return scenes, tmp_path / "runs", command, calls


def run(scenes, out, command, **kw):
    lines = []
    data = corpus.run_corpus(scenes, out, command=command, docs=out / "corpus.md",
                             echo=lines.append, **kw)
    return data, lines


def by_name(data):
    return {e["name"]: e for e in data["scenes"]}


def test_every_scene_runs_and_corpus_json_records_each_outcome(fake_corpus):
    scenes, out, command, calls = fake_corpus
    data, lines = run(scenes, out, command)
    assert data == json.loads((out / "corpus.json").read_text())
    assert {"kind", "version", "date", "git_commit", "cpus", "loadavg_start", "loadavg_end",
            "wall_time_s", "scenes_time_s", "passed", "scenes"} <= set(data)
    assert data["kind"] == corpus.KIND and len(data["loadavg_start"]) == 3
    assert len(data["loadavg_end"]) == 3 and data["wall_time_s"] > 0
    # the scene that fails first does not stop the others
    assert calls.read_text().split() == ["a_broken", "b_ok", "c_noverdict"]
    scene = by_name(data)
    for e in scene.values():  # the tiny liver's mesh, read in-process
        assert (e["vertices"], e["tets"]) == (78, 186)
        assert 0 < e["edge_min_m"] < e["edge_mean_m"] < 0.04

    broken = scene["a_broken"]
    assert broken["exit_status"] == 2
    assert broken["error"] == ("indentation of particle 50 0.0047 -> 0.0047 failed | Newton did "
                               "not converge [stage calibrate; kept: reference.h5; rerun the "
                               "same command to resume]")
    assert broken["stages"] == {"reference": {"status": "ran", "seconds": 60.0},
                                "calibrate": {"status": "failed", "seconds": None}}
    assert broken["fe_time_s"] == 60.0 and broken["calibration_time_s"] is None
    assert broken["total_time_s"] == broken["run_wall_time_s"]
    assert broken["verdict"] is None and broken["passed"] is None and broken["report"] is None

    ok = scene["b_ok"]
    assert ok["exit_status"] == 0 and ok["error"] is None and ok["missing"] == []
    assert (ok["fe_time_s"], ok["calibration_time_s"]) == (60.0, 30.0)
    assert ok["total_time_s"] == ok["run_wall_time_s"] < 60
    assert ok["haptic_p99_us"] == 412.5 and ok["passed"] is False
    assert ok["verdict"]["checks"]["static_sag"] == {
        "status": "failed", "calibrated": 0.196, "baseline": 0.138, "goal": 0.15,
        "reason": "worse than the baseline"}
    assert ok["verdict"]["checks"]["release_rms"]["status"] == "not_run"

    bare = scene["c_noverdict"]  # a report from before the verdict keys existed
    assert bare["exit_status"] == 0 and bare["missing"] == ["verdict", "realtime"]
    assert bare["verdict"] is None and bare["passed"] is None and bare["haptic_p99_us"] is None
    assert data["passed"] is False
    assert any("a_broken: error: indentation of particle 50" in line for line in lines)


def test_a_second_run_reruns_no_stage_of_an_up_to_date_scene(fake_corpus):
    scenes, out, command, calls = fake_corpus
    run(scenes, out, command, only=("b_ok",))
    report = out / "b_ok" / "report.json"
    written = report.stat().st_mtime_ns
    data, lines = run(scenes, out, command, only=("b_ok",))
    ok = by_name(data)["b_ok"]
    assert report.stat().st_mtime_ns == written
    assert {s: e["status"] for s, e in ok["stages"].items()} == dict.fromkeys(
        corpus.STAGE_NAMES, "up_to_date")
    # the times are those recorded with the outputs, not this run's fraction of a second
    assert (ok["fe_time_s"], ok["calibration_time_s"]) == (60.0, 30.0)
    assert ok["total_time_s"] == pytest.approx(99.0 + ok["run_wall_time_s"])
    assert ok["passed"] is False and ok["haptic_p99_us"] == 412.5
    assert not any("running" in line for line in lines)


def test_only_keeps_the_other_scenes_entries(fake_corpus):
    scenes, out, command, calls = fake_corpus
    first, _ = run(scenes, out, command)
    data, _ = run(scenes, out, command, only=("c_noverdict",))
    assert [e["name"] for e in data["scenes"]] == ["a_broken", "b_ok", "c_noverdict"]
    assert by_name(data)["a_broken"] == by_name(first)["a_broken"]
    assert {"date", "git_commit"} <= set(by_name(data)["a_broken"])
    (scenes / "a_broken.toml").unlink()  # a full run forgets a scene that is gone
    data, _ = run(scenes, out, command)
    assert [e["name"] for e in data["scenes"]] == ["b_ok", "c_noverdict"]
    assert calls.read_text().split()[:4] == ["a_broken", "b_ok", "c_noverdict",
                                             "c_noverdict"]
    with pytest.raises(corpus.DataFileError, match="no scene nope"):
        run(scenes, out, command, only=("nope",))


def test_an_interrupted_scene_stops_the_corpus_and_keeps_what_finished(fake_corpus):
    scenes, out, command, calls = fake_corpus
    (scenes / "d_interrupted.toml").write_text((scenes / "b_ok.toml").read_text()
                                               .replace('"b_ok"', '"d_interrupted"'))
    (scenes / "e_ok.toml").write_text((scenes / "b_ok.toml").read_text()
                                      .replace('"b_ok"', '"e_ok"'))
    with pytest.raises(KeyboardInterrupt):
        run(scenes, out, command)
    assert calls.read_text().split() == ["a_broken", "b_ok", "c_noverdict", "d_interrupted"]
    data = corpus.read_corpus(out / "corpus.json")
    assert by_name(data)["d_interrupted"]["exit_status"] == 130
    assert "e_ok" not in by_name(data)


def test_a_scene_whose_mesh_is_refused_is_recorded_with_the_refusal(fake_corpus):
    scenes, out, command, calls = fake_corpus
    (scenes / "f_refused.toml").write_text((scenes / "b_ok.toml").read_text().replace(
        'source = "generate"', 'source = "missing.vtu"').replace('"b_ok"', '"f_refused"'))
    data, lines = run(scenes, out, command)
    entry = by_name(data)["f_refused"]
    assert entry["exit_status"] == 2 and "missing.vtu: mesh file does not exist" in entry["error"]
    assert "vertices" not in entry and entry["verdict"] is None
    assert data["scenes"][0] is entry  # refused at load: run first
    assert "[1/4] f_refused (its mesh is refused)" in lines


def test_a_long_quiet_stage_is_reported_with_the_fe_items_it_finished(fake_corpus):
    scenes, out, command, calls = fake_corpus
    scene = scenes / "g_slow.toml"
    lines = []
    run = corpus.run_scene(command(scene, out / "g_slow"), out / "g_slow.log", lines.append,
                           lambda: corpus.fe_items_done(out / "g_slow"), heartbeat_s=0.3)
    assert run["exit_status"] == 0
    assert "reference running: no cache record" in lines
    # heartbeats before the first line (a slow start) say "starting"; after it, the stage
    heartbeats = lines[lines.index("reference running: no cache record") + 1:]
    assert "reference running, 0 min so far, 2 FE work items finished" in heartbeats
    assert set(lines) - set(heartbeats) <= {"reference running: no cache record",
                                            "starting, 0 min so far"}
    assert "reference running: no cache record" in (out / "g_slow.log").read_text()


def test_the_table_shows_each_check_in_its_own_unit_and_which_scenes_a_run_ran():
    weight = {"calibrated": 0.62, "baseline": 1.0, "goal": 1.0, "status": "failed"}
    assert corpus._check_cell(weight, "carries_its_weight") == "**fail** 0.62 / 1.00 (≥ 1.00) g"
    sag = {"calibrated": 0.034, "baseline": 0.052, "goal": 0.15, "status": "passed"}
    assert corpus._check_cell(sag, "static_sag") == "pass 3.4 / 5.2 (≤ 15.0) %"
    data = {"date": "2026-01-02T00:00:00+00:00", "wall_time_s": 120.0, "scenes_time_s": 600.0,
            "scenes": [{"scene": "scenes/corpus/a.toml", "date": "2026-01-02T00:00:05+00:00"},
                       {"scene": "scenes/corpus/b.toml", "date": "2026-01-01T00:00:00+00:00"}]}
    assert corpus._wall_time(data).startswith("this run ran a in 2.0 min, the other scenes'")
    data["scenes"][1]["date"] = "2026-01-02T00:10:00+00:00"
    assert corpus._wall_time(data) == ("corpus wall time 2.0 min (the scenes' pipeline times "
                                       "add up to 10.0 min)")


def test_the_docs_table_is_generated_from_corpus_json_alone(fake_corpus, tmp_path):
    scenes, out, command, calls = fake_corpus
    data, _ = run(scenes, out, command)
    table = (out / "corpus.md").read_text()
    assert table == corpus.corpus_markdown(corpus.read_corpus(out / "corpus.json"))
    rows = {line.split(" | ")[0].lstrip("| "): line for line in table.splitlines()
            if line.startswith("| ") and not line.startswith("| scene")}
    assert set(rows) == {"a_broken", "b_ok", "c_noverdict"}
    assert "pass 3.4 / 5.2 (≤ 10.0) %" in rows["b_ok"]
    assert "**fail** 19.6 / 13.8 (≤ 15.0) %" in rows["b_ok"] and "| 412 |" in rows["b_ok"]
    assert "Newton did not converge" in rows["a_broken"]
    assert "\\|" in rows["a_broken"]  # the error's "|" does not break the table
    assert "report without verdict, realtime" in rows["c_noverdict"]
    # the command that rewrites it from corpus.json
    from pipelines.cli import main
    docs = tmp_path / "again.md"
    assert main(["corpus", "--out", str(out), "--table", "--docs", str(docs)]) == 0
    assert docs.read_text() == table


def test_the_committed_corpus_table_is_what_the_command_writes():
    data_path, docs = ROOT / "runs/corpus/corpus.json", ROOT / corpus.DOCS
    if not data_path.is_file() and not docs.is_file():
        pytest.skip("no corpus run committed yet (make corpus writes both)")
    assert docs.read_text() == corpus.corpus_markdown(corpus.read_corpus(data_path))


CORPUS_SCENES = sorted((SCENES / "corpus").glob("*.toml"))


def test_the_corpus_has_its_meshes_sources_and_licences():
    sources = (SCENES / "corpus" / "SOURCES.md").read_text()
    spec = importlib.util.spec_from_file_location("corpus_convert",
                                                  SCENES / "corpus" / "convert.py")
    convert = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = convert  # its dataclasses look their module up there
    spec.loader.exec_module(convert)
    SOURCES = convert.SOURCES
    assert len(CORPUS_SCENES) >= 6
    assert {p.stem for p in CORPUS_SCENES} == {s.name for s in SOURCES}
    assert len({s.repo for s in SOURCES}) >= 2
    assert not any("sofa" in s.repo.lower() for s in SOURCES)
    for s in SOURCES:
        assert s.commit in sources and s.path in sources and s.licence in sources


@pytest.mark.parametrize("path", CORPUS_SCENES, ids=lambda p: p.stem)
def test_each_corpus_scene_loads_and_its_mesh_passes_the_checks(path):
    """Scene keys, mesh checks, fixed nodes, test points, depths and the cost check: all
    that is refused before any FE work. The scene sets only what a user must."""
    from forcecal.cost import check_cost
    from forcecal.problem import build_problem
    from forcecal.scene import load_scene
    scene = load_scene(path)
    if not scene.mesh_source_path().is_file():
        pytest.skip(f"{scene.mesh_source_path()} not converted (scenes/corpus/convert.py)")
    keys = tomllib.loads(path.read_text())
    assert set(keys) <= {"name", "description", "mesh", "fixed", "gravity", "indentation",
                         "relaxation", "material"}
    assert set(keys.get("indentation", {})) <= {"depth"}
    assert set(keys.get("relaxation", {})) <= {"depth"}
    problem = build_problem(scene)
    n = problem.mesh.n_vertices
    assert 150 <= n <= 3000
    assert 3 <= len(problem.fixed) <= 0.4 * n
    check_cost(scene, n, len(problem.mesh.edges))
    # the calibration's refusal of a depth that collapses connectors (the pipeline makes it
    # before the FE reference)
    from calibration.reach import check_experiment_depths
    check_experiment_depths(scene, problem)


def test_the_recipe_is_the_readmes_own_mesh_recipe_less_the_meshs_own_keys():
    """``--recipe`` gives each corpus scene what the README's "Running your own mesh" block
    sets, except what only that mesh can say (name, mesh, supports, gravity, punch radius:
    the rule of :func:`pipelines.corpus.recipe_scene`)."""
    readme = (ROOT / "README.md").read_text()
    block = readme.split("## Running your own mesh", 1)[1].split("```toml\n", 1)[1]
    recipe = tomllib.loads(block.split("```", 1)[0])
    own = {"name", "mesh", "fixed", "second_support", "gravity"}
    assert recipe.pop("experiments") == corpus.RECIPE["experiments"]
    recipe["indentation"].pop("radius")
    assert {k: v for k, v in recipe.items() if k not in own} == {
        k: v for k, v in corpus.RECIPE.items() if k != "experiments"}
    assert "1.5 x your mesh's mean surface edge length" in block
    assert corpus.RECIPE_RADIUS_EDGES == 1.5


def test_a_recipe_scene_is_the_corpus_scene_with_the_recipe(tmp_path):
    """On the user organ's mesh as a corpus scene (hung from its top, its own depth): the
    recipe scene keeps its keys, adds the recipe's, and its punch radius is the one
    scenes/user_organ_punch.toml gives the same mesh by the same rule (17.3 mm); written
    again, the file is untouched; a scene whose mesh is refused is written as it is."""
    from forcecal.scene import load_scene
    source = tmp_path / "corpus"
    source.mkdir()
    mesh = (SCENES / "meshes" / "user_organ.vtu").resolve()
    (source / "organ.toml").write_text(textwrap.dedent(f'''
        name = "organ"
        description = "a kidney-like organ hung from its top"
        [mesh]
        source = "{mesh}"
        scale = 0.001
        [fixed]
        axis = "y"
        side = "max"
        tolerance = 0.001
        [gravity]
        acceleration = [0.0, -9.81, 0.0]
        [indentation]
        depth = 0.004
    '''))
    folder = tmp_path / "out" / "scenes"
    path = corpus.recipe_scene(source / "organ.toml", folder)
    scene = load_scene(path)
    assert scene.name == "organ_recipe" and list(scene.experiments) == corpus.RECIPE["experiments"]
    assert scene.mesh_source_path().resolve() == mesh
    assert (scene.fixed.axis, scene.fixed.side, scene.fixed.tolerance) == ("y", "max", 0.001)
    assert (scene.second_support.axis, scene.second_support.side) == ("y", "min")
    assert scene.indentation.depth == 0.004 and scene.indentation.indenter == "punch"
    assert scene.indentation.radius == load_scene(SCENES / "user_organ_punch.toml").indentation.radius
    assert (scene.fe.element, scene.fe.local_refine, scene.particle.volume) == (
        "TH", 3, "viscoelastic")
    assert (scene.calibration.method, scene.calibration.body_data) == (
        "gradient", "modes+loaded_modes+free_modes")
    # a depth the mesh refuses: the largest 0.5 mm multiple below both limits, as the
    # refusals ask; the second support seats as many vertices as [fixed] holds
    from calibration.reach import accepted_depth
    from forcecal.point_selection import fixed_nodes
    from forcecal.problem import MAX_DEPTH_PER_EDGE, load_mesh
    (source / "deep.toml").write_text((source / "organ.toml").read_text().replace(
        "depth = 0.004", "depth = 0.05").replace('"organ"', '"deep"'))
    deep = load_scene(corpus.recipe_scene(source / "deep.toml", folder))
    organ = load_mesh(scene)
    limit = min(accepted_depth(deep), MAX_DEPTH_PER_EDGE * organ.edge_lengths.mean())
    assert deep.indentation.depth < limit and deep.relaxation.depth == 0.005  # accepted: kept
    assert limit - deep.indentation.depth <= 5e-4
    assert round(deep.indentation.depth / 5e-4, 9).is_integer()
    assert len(fixed_nodes(organ, "y", "min", scene.second_support.tolerance)) >= len(
        fixed_nodes(organ, "y", "max", 0.001))
    written = path.stat().st_mtime_ns
    assert corpus.recipe_scene(source / "organ.toml", folder) == path
    assert path.stat().st_mtime_ns == written
    (source / "gone.toml").write_text((source / "organ.toml").read_text().replace(
        str(mesh), str(tmp_path / "gone.vtu")).replace('"organ"', '"gone"'))
    gone = load_scene(corpus.recipe_scene(source / "gone.toml", folder))
    assert gone.name == "gone" and gone.experiments == load_scene(source / "gone.toml").experiments


def test_the_recipe_corpus_writes_its_scenes_and_records_that_it_ran_them(fake_corpus, tmp_path,
                                                                          monkeypatch):
    """``python -m pipelines corpus --recipe``: the recipe scenes under <out>/scenes/, run
    by the corpus runner, ``corpus.json`` saying so."""
    scenes, out, command, calls = fake_corpus
    ran = []

    def run_corpus(folder, where, **kw):
        ran.append((folder, where, kw["recipe"]))
        return {"scenes": [], "wall_time_s": 1.0, "passed": None}
    monkeypatch.setattr(corpus, "run_corpus", run_corpus)
    from pipelines.cli import main
    assert main(["corpus", "--recipe", "--scenes", str(scenes), "--out", str(out),
                 "--only", "b_ok"]) == 0
    assert ran == [(out / "scenes", out, True)]
    assert [p.name for p in (out / "scenes").glob("*.toml")] == ["b_ok.toml"]
