"""Stored models are validated on load (issue 13): shapes, finite values, physical values, the stored network
through the validation pass, each a ``file: error:`` message (exit 1, never a traceback); ``tnnc inspect``
shows values in the units the network file wrote them in."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tnn_dsl.cli import main
from tnn_dsl.core.errors import ModelFileError
from tnn_dsl.fit.model_files import load_model, save_model
from tnn_dsl.lang import load, loads

ROOT = Path(__file__).resolve().parents[1]
LEARNED = ('network tiny\nunits temperature = degC\ninput P : [%] column "P"\nparam gain = 0.02 W/%\n'
           'node a C = 4 kJ/K free\nboundary amb = 21 degC\nG a -- amb = 0.05 W/K free as Ua\n'
           'source a = gain * P\nsensor T1 = a column "T1"\nlearn Ua as linear(a)\n')


def _model(tmp_path: Path, **changes) -> Path:
    net = loads(LEARNED)
    params = {"C_a": np.array(4000.0), "T_amb": np.array(294.15), "Ua": np.array(0.05), "gain": np.array(2.0),
              "fn_Ua.W": np.zeros((1, 1)), "fn_Ua.b": np.zeros(1), "fn_Ua.x_mean": np.array([298.15]),
              "fn_Ua.x_scale": np.array([10.0]), "fn_Ua.y_scale": np.array([0.05])}
    for k, v in changes.items():
        k = k.replace("__", ".")
        if v is None:
            params.pop(k)
        else:
            params[k] = np.asarray(v, dtype=float)
    return save_model(tmp_path / "m", net, params, {"backend": "jax"}, force=True)


def _cli_error(capsys, path) -> str:
    assert main(["inspect", str(path)]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and "internal error" not in err
    return err


def test_a_valid_model_loads(tmp_path):
    tm = load_model(_model(tmp_path))
    assert tm.params["C_a"] == 4000.0


@pytest.mark.parametrize("changes, message", [
    ({"C_a": -3.0}, "`C_a`: a capacitance must be positive, got -3 (SI)"),
    ({"Ua": 0.0}, "`Ua`: a conductance must be positive, got 0 (SI)"),
    ({"T_amb": -5.0}, "`T_amb`: a temperature must be above absolute zero, got -5 K"),
    ({"C_a": [4000.0, 1.0]}, "`C_a` has shape (2,), expected one number"),
    ({"Ua": None}, "`Ua` is missing"),
    ({"fn_Ua__W": np.zeros((3, 1))}, "`fn_Ua.W` has shape (3, 1), expected (1, 1)"),
    ({"fn_Ua__b": None}, "`fn_Ua.b` is missing"),
    ({"fn_Ua__x_scale": [0.0]}, "`fn_Ua.x_scale` must be positive"),
])
def test_hand_edited_parameters_are_refused_on_load(tmp_path, capsys, changes, message):
    d = _model(tmp_path, **changes)
    with pytest.raises(ModelFileError) as e:
        load_model(d)
    text = e.value.format()
    assert f"{d / 'params.safetensors'}: {message}" in text and "hint:" in text
    assert message in _cli_error(capsys, d)
    assert main(["simulate", str(d), "--data", str(tmp_path / "none.csv"), "-o", str(tmp_path / "o.csv")]) == 1


def test_a_hand_edited_network_is_validated_on_load(tmp_path, capsys):
    d = _model(tmp_path)
    j = json.loads((d / "network.json").read_text())
    for p in j["params"]:
        if p["name"] == "C_a":
            p["expr"]["value"] = -3000.0
    j["links"][0]["b"] = "nowhere"
    (d / "network.json").write_text(json.dumps(j))
    err = _cli_error(capsys, d)
    assert f"{d / 'network.json'}: the stored network is not valid" in err
    assert "must be positive" in err and "nowhere" in err


def test_inspect_shows_the_files_units(tmp_path, capsys):
    d = _model(tmp_path, C_a=4500.0, T_amb=296.35)
    assert load_model(d).network.temperature_unit == "degC"
    assert main(["inspect", str(d), "--all", "--json", str(tmp_path / "t.json")]) == 0
    out = capsys.readouterr().out
    rows = {line.split()[0]: line for line in out.splitlines() if line.split() and line.split()[0] in
            ("C_a", "T_amb", "gain", "Ua")}
    assert "4 kJ/K" in rows["C_a"] and "4.5 kJ/K" in rows["C_a"] and "+12.5 %" in rows["C_a"]
    assert "21 degC" in rows["T_amb"] and "23.2 degC" in rows["T_amb"] and "+2.2 K" in rows["T_amb"]
    assert "0.02 W/%" in rows["gain"] and "296" not in rows["T_amb"]
    table = {r["name"]: r for r in json.loads((tmp_path / "t.json").read_text())["parameters"]}
    assert table["T_amb"]["fitted"] == pytest.approx(296.35) and table["T_amb"]["fitted_shown"] == pytest.approx(23.2)
    assert table["gain"]["nominal"] == pytest.approx(2.0) and table["gain"]["nominal_shown"] == pytest.approx(0.02)
    assert table["C_a"]["unit"] == "kJ/K"


def test_inspect_of_a_real_network_model(tmp_path, capsys):
    """The TCLab network (degC, W/% gains): nothing in SI under the file's units."""
    net = load(ROOT / "networks" / "tclab" / "tclab.thn")
    params = {p.name: np.asarray(float(p.value)) for p in net.params if p.is_constant}
    save_model(tmp_path / "m", net, params, {"backend": "jax"})
    assert main(["inspect", str(tmp_path / "m")]) == 0
    out = capsys.readouterr().out
    assert "23 degC" in out and "0.01 W/%" in out and "296.15" not in out


def test_an_edited_ir_file_is_validated(tmp_path, capsys):
    ir = tmp_path / "t.json"
    assert main(["compile", str(ROOT / "networks" / "tclab" / "tclab.thn"), "--emit", "ir-json", "-o", str(ir)]) == 0
    j = json.loads(ir.read_text())
    for p in j["params"]:
        if p["name"] == "C_h1":
            p["expr"]["value"] = -4.0
    ir.write_text(json.dumps(j))
    capsys.readouterr()
    assert main(["compile", str(ir)]) == 1
    err = capsys.readouterr().err
    assert f"{ir}: the IR is not a valid network" in err
    assert "the capacity of node `h1` must be positive, got -4" in err and "Traceback" not in err
