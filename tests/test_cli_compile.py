"""`tnnc compile FILE --emit equations|ir-json|graph [-o OUT]`."""

from __future__ import annotations

import json
import os

import pytest
from test_emit import case_study, tclab_lag

from tnn_dsl import Network
from tnn_dsl.cli import main
from tnn_dsl.ir import emit as _emit

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
M2 = os.path.join(ROOT, "networks", "peltier_heatpipe", "m2.thn")
TCLAB = os.path.join(ROOT, "networks", "tclab", "tclab.thn")


@pytest.fixture
def m2_json(tmp_path):
    path = tmp_path / "m2.ir.json"
    path.write_text(_emit.ir_json(case_study("linear")), encoding="utf-8")
    return str(path)


def test_equations_to_stdout_from_ir_json(m2_json, capsys):
    assert main(["compile", m2_json]) == 0
    out = capsys.readouterr().out
    assert "C_hx2·dT_hx2/dt = (T_hp − T_hx2)/R_hp2(hx1, hp, hx2, u1)" in out
    assert out == _emit.equations(case_study("linear"))


def test_equations_ascii_to_file(m2_json, tmp_path, capsys):
    out = tmp_path / "eq.txt"
    assert main(["compile", m2_json, "--emit", "equations", "--ascii", "-o", str(out)]) == 0
    assert capsys.readouterr().out == ""
    text = out.read_text(encoding="utf-8")
    assert text.isascii() and "C_hx2*dT_hx2/dt" in text


def test_ir_json_round_trip_through_the_cli(m2_json, tmp_path):
    first = tmp_path / "a.json"
    second = tmp_path / "b.json"
    assert main(["compile", m2_json, "--emit", "ir-json", "-o", str(first)]) == 0
    assert main(["compile", str(first), "--emit", "ir-json", "-o", str(second)]) == 0
    assert first.read_bytes() == second.read_bytes()
    assert Network.from_json(first.read_text()) == case_study("linear")
    assert json.loads(first.read_text())["name"] == "peltier_heatpipe"


def test_graph_dot_to_stdout_and_file(m2_json, tmp_path, capsys):
    assert main(["compile", m2_json, "--emit", "graph"]) == 0
    out = capsys.readouterr().out
    assert out.startswith('digraph "peltier_heatpipe" {') and '"hx1" -> "hp"' in out
    dot_file = tmp_path / "net.dot"
    assert main(["compile", m2_json, "--emit", "graph", "-o", str(dot_file)]) == 0
    assert dot_file.read_text() == out


def test_graph_png(tmp_path, capsys, monkeypatch):
    import tnn_dsl.plots.drawing as drawing

    monkeypatch.setattr(drawing.shutil, "which", lambda name: None)  # as on a machine without graphviz
    src = tmp_path / "t.json"
    src.write_text(_emit.ir_json(tclab_lag()))
    png = tmp_path / "net.png"
    assert main(["compile", str(src), "--emit", "graph", "-o", str(png)]) == 0
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert "Graphviz `dot` is not installed" in capsys.readouterr().err


def test_graph_svg_without_graphviz_is_a_clear_error(m2_json, tmp_path, capsys, monkeypatch):
    import tnn_dsl.cli._compile as comp

    monkeypatch.setattr(comp.shutil, "which", lambda name: None)
    assert main(["compile", m2_json, "--emit", "graph", "-o", str(tmp_path / "x.svg")]) == 1
    err = capsys.readouterr().err
    assert "needs Graphviz's `dot` program" in err and "hint: install graphviz" in err


def test_unknown_picture_format(m2_json, tmp_path, capsys):
    assert main(["compile", m2_json, "--emit", "graph", "-o", str(tmp_path / "x.jpeg")]) == 1
    err = capsys.readouterr().err
    assert "unknown picture format '.jpeg'" in err and "hint:" in err


def test_missing_file_and_bad_json(tmp_path, capsys):
    assert main(["compile", str(tmp_path / "nope.json")]) == 1
    assert "no such file" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text('{"name": "x", "nodes": [{"name": 1}]}')
    assert main(["compile", str(bad)]) == 1
    err = capsys.readouterr().err
    assert "not a tnn_dsl IR file" in err and "Traceback" not in err


def test_unwritable_output(m2_json, tmp_path, capsys):
    (tmp_path / "afile").write_text("x")  # missing directories are created; a path below a file cannot be
    assert main(["compile", m2_json, "-o", str(tmp_path / "afile" / "such" / "dir" / "eq.txt")]) == 1
    assert "cannot write" in capsys.readouterr().err
    assert main(["compile", m2_json, "-o", str(tmp_path / "no" / "such" / "dir" / "eq.txt")]) == 0
    assert (tmp_path / "no" / "such" / "dir" / "eq.txt").read_text().strip()


def test_bad_emit_choice(m2_json, capsys):
    with pytest.raises(SystemExit) as ex:
        main(["compile", m2_json, "--emit", "pdf"])
    assert ex.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


# -- through the parser ---------------------------------------------------------------------


def test_compile_thn_equations(capsys):
    assert main(["compile", M2]) == 0
    out = capsys.readouterr().out
    assert "C_hx2·dT_hx2/dt = (T_hp − T_hx2)/R_hp2(hx1, hp, hx2, u1) + f2.mdot·f2.cp·(1 − a_f2)·(Tf2 − T_hx2)" in out


def test_compile_thn_ir_json_is_stable(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    assert main(["compile", TCLAB, "--emit", "ir-json", "-o", str(a)]) == 0
    assert main(["compile", str(a), "--emit", "ir-json", "-o", str(b)]) == 0
    assert a.read_bytes() == b.read_bytes()


def test_compile_thn_with_an_error_reports_position(tmp_path, capsys):
    bad = tmp_path / "bad.thn"
    bad.write_text('network bad\nnode a C = 4 J/K\nR a -- b = 0.08 W/K\n')
    assert main(["compile", str(bad)]) == 1
    err = capsys.readouterr().err
    assert f"{bad}:3:" in err and "error:" in err and "Traceback" not in err


def test_compile_emit_thn_prints_the_network_back(tmp_path, capsys):
    """--emit thn: the flat .thn printed from the IR reads back to the same IR (JSON equal but for the file
    names and positions); from an IR JSON file too; never over its input."""
    out, js = tmp_path / "m2_flat.thn", tmp_path / "m2.json"
    assert main(["compile", M2, "--emit", "thn", "-o", str(out)]) == 0
    assert main(["compile", M2, "--emit", "ir-json", "-o", str(js)]) == 0

    def strip_spans(text):
        d = json.loads(text)

        def walk(x):
            if isinstance(x, dict):
                return {k: walk(v) for k, v in x.items() if k != "span"}
            if isinstance(x, list):
                return [walk(v) for v in x]
            return x
        d.pop("source_files", None)
        return walk(d)

    from tnn_dsl import load

    assert strip_spans(load(str(out)).to_json()) == strip_spans(load(M2).to_json())
    capsys.readouterr()
    assert main(["compile", str(js), "--emit", "thn"]) == 0
    assert capsys.readouterr().out == out.read_text()
    assert main(["compile", M2, "--emit", "thn", "-o", M2]) == 1
    assert "also an input" in capsys.readouterr().err
