"""``python -m pipelines export``: the calibrated model as VTU (ParaView) and JSON (another
engine), read back with meshio and json; the model rebuilt from the JSON is the model."""
import json
import math

import meshio
import numpy as np
import pytest

import forcecal
from forcecal.errors import DataFileError
from particle.reference_numpy import forces_numpy
from particle.stability import critical_time_step
from pipelines.cli import main as pipelines_main
from pipelines.export import EXPORT_FORMAT, model_from_document, read_model_json
from pipelines.realtime import session_strain_range
from tests.test_load_model import calibrated_box


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    base = tmp_path_factory.mktemp("export")
    _, params = calibrated_box(base)
    out = base / "export"
    assert pipelines_main(["export", "--params", str(params), "--out", str(out)]) == 0
    return params, out


def test_the_vtu_files_carry_every_connector_and_tet_parameter(exported):
    params, out = exported
    model = forcecal.load_model(params)
    p = model.params
    lines = meshio.read(out / "connectors.vtu")
    np.testing.assert_array_equal(lines.points, model.rest_positions)
    assert [c.type for c in lines.cells] == ["line"]
    np.testing.assert_array_equal(lines.cells[0].data, model.edges)
    want = {"K0_N_per_m": p.K0, "a_N_per_m": p.a, "b_N_per_m": p.b, "k1_N_per_m": p.k1,
            "tau1_s": p.b1 / p.k1, "k2_N_per_m": p.k2, "tau2_s": p.b2 / p.k2,
            "rest_length_m": model.rest_lengths}
    assert set(lines.cell_data) == set(want)
    for name, values in want.items():
        np.testing.assert_array_equal(lines.cell_data[name][0], values, err_msg=name)
    np.testing.assert_array_equal(lines.point_data["mass_kg"], model.masses)
    np.testing.assert_array_equal(lines.point_data["fixed"].astype(bool), model.fixed)
    tets = meshio.read(out / "tets.vtu")
    np.testing.assert_array_equal(tets.cells[0].data, model.tets)
    want = {"rest_volume_m3": model.rest_volumes, "kv_Pa": p.kv, "kv1_Pa": p.kv1,
            "tau_v1_s": p.bv1 / p.kv1, "kv2_Pa": p.kv2, "tau_v2_s": p.bv2 / p.kv2}
    assert set(tets.cell_data) == set(want)
    for name, values in want.items():
        np.testing.assert_array_equal(tets.cell_data[name][0], values, err_msg=name)


def test_the_json_model_gives_the_loaded_model_s_forces(exported):
    """On a perturbed state (every free particle moved by up to 10 % of the shortest
    connector, the arms and the volume arms loaded by earlier steps) the model rebuilt from
    ``model.json`` gives the loaded model's forces: JSON keeps every float64, so exactly."""
    params, out = exported
    model = forcecal.load_model(params)
    rebuilt = read_model_json(out / "model.json")
    rng = np.random.default_rng(3)
    dt = 1e-4
    states = [m.state() for m in (model, rebuilt)]
    gravity = np.array([0.0, 0.0, -9.81])
    for _ in range(3):  # three steps of random motion: arms and volume arms carry forces
        move = np.zeros_like(model.rest_positions)
        move[~model.fixed] = rng.uniform(-0.1, 0.1, (int((~model.fixed).sum()), 3))
        move *= model.rest_lengths.min()
        forces = []
        for m, state in zip((model, rebuilt), states):
            state.x_prev[:] = state.x
            state.x[:] = m.rest_positions + move
            forces.append(forces_numpy(m, state, dt, gravity=gravity))
        np.testing.assert_array_equal(forces[1], forces[0])
    want = forces[0]
    assert np.abs(want[~model.fixed]).max() > 0
    assert np.abs(states[0].volume_arm).max() > 0 and np.abs(states[0].arm_force).max() > 0


def test_the_json_document_says_what_an_engine_needs(exported):
    params, out = exported
    calibrated = forcecal.load_calibrated(params)
    model = calibrated.model
    doc = json.loads((out / "model.json").read_text())
    assert doc["format"] == EXPORT_FORMAT and doc["schema_version"] == 1
    assert (doc["n_particles"], doc["n_connectors"], doc["n_tets"]) == (
        model.n_particles, model.n_connectors, model.n_tets)
    assert doc["fixed"] == np.nonzero(model.fixed)[0].tolist()
    assert doc["volume"]["kv"] == model.params.kv.tolist()
    assert doc["valid_strain"] == dict(zip(("low", "high"), calibrated.strain_range))
    assert doc["units"]["K0"] == "N/m" and doc["units"]["bv1"] == "Pa s"
    # the step: the rigorous limit over the haptic session's strain range, 0.9 of it
    step = doc["time_step"]
    lo, hi = session_strain_range(model.params)
    assert step["strain_low"] == lo.tolist() and step["strain_high"] == hi.tolist()
    assert step["critical_dt"] == critical_time_step(model, strain_range=(lo, hi))
    assert step["dt"] == pytest.approx(0.9 * step["critical_dt"], rel=1e-15)
    assert step["substeps_per_period"] == math.ceil(1e-3 / step["dt"])


def test_a_json_that_is_not_a_model_is_refused(exported, tmp_path):
    _, out = exported
    doc = json.loads((out / "model.json").read_text())
    with pytest.raises(DataFileError, match="is not a forcecal.particle_model file"):
        model_from_document({"format": "other"})
    with pytest.raises(DataFileError, match="schema version 7"):
        model_from_document({**doc, "schema_version": 7})
    with pytest.raises(DataFileError, match="'masses' is missing"):
        model_from_document({k: v for k, v in doc.items() if k != "masses"})
    with pytest.raises(DataFileError, match="edges name particles outside"):
        model_from_document({**doc, "edges": [[0, doc["n_particles"]]] + doc["edges"][1:]})
    with pytest.raises(DataFileError, match=r"rest_lengths has shape \(1,\)"):
        model_from_document({**doc, "rest_lengths": [1.0]})
    with pytest.raises(DataFileError, match="does not exist"):
        read_model_json(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(DataFileError, match="not readable JSON"):
        read_model_json(tmp_path / "bad.json")


def test_the_export_command_refuses_a_missing_params_file(tmp_path, capsys):
    assert pipelines_main(["export", "--params", str(tmp_path / "params.h5"),
                           "--out", str(tmp_path / "x")]) == 2
    assert capsys.readouterr().err.strip().endswith("params.h5 does not exist")
    assert not (tmp_path / "x").exists()
