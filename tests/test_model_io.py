"""Model directories: atomic write, round trip, clear errors for damaged directories, cross-backend
predictions (the part that needs the compiler is skipped until it is importable)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tnn_dsl.core.errors import ModelFileError
from tnn_dsl.fit.model_files import load_model, save_model
from tnn_dsl.ir.network import Network
from tnn_dsl.lang import loads


def _net() -> Network:
    """One node, free capacity and conductance (as the parser builds it: stored models are validated on load)."""
    return loads('network tiny\nunits temperature = K\nnode a C = 4 J/K free\nboundary amb = 296.15 K\n'
                 'G a -- amb = 0.05 W/K free\nsensor T1 = a column "T1"\n')


def _params():
    return {"C_a": np.array(4.5), "G_a_amb": np.array(0.06), "T_amb": np.array(296.15),
            "f1.W": np.arange(6.0).reshape(2, 3)}


def test_round_trip(tmp_path):
    d = save_model(tmp_path / "m", _net(), _params(), {"backend": "torch", "metrics": {"mae": 0.1, "x": float("nan")}})
    assert sorted(p.name for p in d.iterdir()) == ["meta.json", "network.json", "params.safetensors"]
    tm = load_model(d)
    assert tm.network == _net()
    assert tm.backend == "torch"
    for k, v in _params().items():
        np.testing.assert_array_equal(tm.params[k], v)
        assert tm.params[k].dtype == np.float64
    assert tm.meta["metrics"]["mae"] == 0.1 and tm.meta["metrics"]["x"] is None  # NaN -> null, valid JSON
    assert tm.meta["format"] == "tnn_dsl-model"


def test_source_copied(tmp_path):
    src = tmp_path / "net.thn"
    src.write_text("network tiny\n# source as written\n")
    net = _net().model_copy(update={"source_files": [str(src)]})
    d = save_model(tmp_path / "m", net, _params(), {})
    assert (d / "network.thn").read_text() == src.read_text()


def test_a_network_printed_from_the_ir_is_written_as_given_not_its_files_copy(tmp_path):
    """The doctor's extension is parsed under the user's file name (no ``-o``): its source file is the user's, which
    must not be copied as the model's ``network.thn``; ``source_text`` is written instead, and nothing is included."""
    src = tmp_path / "net.thn"
    src.write_text("network tiny\n# the user's file, not the extension\n")
    net = _net().model_copy(update={"source_files": [str(src), str(tmp_path / "part.thn")]})
    d = save_model(tmp_path / "m", net, _params(), {}, source_text="network tiny\n# the extension\n")
    assert (d / "network.thn").read_text() == "network tiny\n# the extension\n"
    assert not (d / "include").exists() and src.read_text().endswith("not the extension\n")


def test_overwrite_is_atomic(tmp_path):
    d = save_model(tmp_path / "m", _net(), _params(), {"run": 1})
    with pytest.raises(Exception):
        save_model(tmp_path / "m", _net(), {"bad": object()}, {"run": 2})  # fails while writing
    assert load_model(d).meta["run"] == 1  # the old model is intact
    assert [p.name for p in tmp_path.iterdir()] == ["m"]  # no temporary directories left behind
    save_model(tmp_path / "m", _net(), _params(), {"run": 3})
    assert load_model(d).meta["run"] == 3
    assert [p.name for p in tmp_path.iterdir()] == ["m"]


def test_missing_directory(tmp_path):
    with pytest.raises(ModelFileError) as e:
        load_model(tmp_path / "nope")
    assert "does not exist" in str(e.value) and "hint:" in str(e.value)


def test_missing_file(tmp_path):
    d = save_model(tmp_path / "m", _net(), _params(), {})
    (d / "params.safetensors").unlink()
    with pytest.raises(ModelFileError) as e:
        load_model(d)
    assert "missing params.safetensors" in str(e.value)


def test_corrupted_meta_points_at_line(tmp_path):
    d = save_model(tmp_path / "m", _net(), _params(), {})
    text = (d / "meta.json").read_text().splitlines()
    text[3] = text[3] + " oops"
    (d / "meta.json").write_text("\n".join(text))
    with pytest.raises(ModelFileError) as e:
        load_model(d)
    msg = str(e.value)
    assert f"{d / 'meta.json'}:4:" in msg and "not valid JSON" in msg and "^" in msg


def test_not_a_model(tmp_path):
    d = save_model(tmp_path / "m", _net(), _params(), {})
    (d / "meta.json").write_text(json.dumps({"hello": 1}))
    with pytest.raises(ModelFileError, match="not a tnn_dsl model"):
        load_model(d)


def test_truncated_params(tmp_path):
    d = save_model(tmp_path / "m", _net(), _params(), {})
    raw = (d / "params.safetensors").read_bytes()
    (d / "params.safetensors").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ModelFileError, match="params.safetensors cannot be read"):
        load_model(d)


def test_non_finite_params(tmp_path):
    p = _params()
    p["C_a"] = np.array(np.nan)
    d = save_model(tmp_path / "m", _net(), p, {})
    with pytest.raises(ModelFileError, match="non-finite"):
        load_model(d)


def test_corrupted_network(tmp_path):
    d = save_model(tmp_path / "m", _net(), _params(), {})
    (d / "network.json").write_text('{"name": 3')
    with pytest.raises(ModelFileError, match="network.json cannot be read"):
        load_model(d)


def test_file_instead_of_directory(tmp_path):
    f = tmp_path / "m"
    f.write_text("x")
    with pytest.raises(ModelFileError, match="not a model directory"):
        load_model(f)
    with pytest.raises(ModelFileError, match="a file of that name exists"):
        save_model(f, _net(), _params(), {})


def test_scalars_stay_scalars(tmp_path):
    d = save_model(tmp_path / "m", _net(), _params(), {})
    tm = load_model(d)
    assert tm.params["C_a"].shape == () and tm.params["f1.W"].shape == (2, 3)
