"""Never read outside the project, never blow up on a file (issue 13): includes confined to the main file's
directory tree (and ``--include-path``), regular files only, size caps, each included file read once (an
include bomb costs linear work), long strings and huge learned functions refused before anything is
allocated, long source lines shown as a window around the caret."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import tnn_dsl.lang.sources as sources
from tnn_dsl.cli import main
from tnn_dsl.compiler import learned as learned_arrays
from tnn_dsl.core.errors import TnnError
from tnn_dsl.lang import include_path_scope, load, loads

SECRET = "SECRET_LINE_THAT_MUST_NEVER_BE_PRINTED"
BODY = "node a C = 1 J/K\nboundary amb = 20 degC\nR a -- amb = 1 K/W as Ra\n"


def _project(tmp_path: Path) -> Path:
    """``tmp/outside/secret.thn`` (content that a message would print if it were read) and ``tmp/proj``."""
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret.thn").write_text(f"{SECRET}\n{SECRET} again\n")
    (outside / "shared.thn").write_text("param p_shared = 2 W\n")
    proj = tmp_path / "proj"
    (proj / "parts").mkdir(parents=True)
    (proj / "parts" / "loads.thn").write_text("param p_load = 1 W\n")
    return proj


def _main(proj: Path, include: str, extra: str = "") -> Path:
    p = proj / "main.thn"
    p.write_text(f'network m "t"\ninclude "{include}"\n{BODY}{extra}')
    return p


def _error_text(path: Path, **kw) -> str:
    with pytest.raises(TnnError) as e:
        load(path, **kw)
    return e.value.format()


@pytest.mark.parametrize("include", ["../outside/secret.thn", "../../outside/secret.thn", "{abs}",
                                     "parts/../../outside/secret.thn", "/etc/passwd"])
def test_include_outside_the_project_is_refused_unread(tmp_path, include):
    proj = _project(tmp_path)
    include = include.replace("{abs}", str(tmp_path / "outside" / "secret.thn"))
    if include.startswith("../../"):
        (proj / "sub").mkdir()
        path = proj / "sub" / "main.thn"
        path.write_text(f'network m "t"\ninclude "{include}"\n{BODY}')
    else:
        path = _main(proj, include)
    text = _error_text(path)
    assert "is outside the network's directory" in text and "--include-path" in text
    assert SECRET not in text and "root:" not in text


def test_symbolic_link_out_of_the_project_is_refused(tmp_path):
    proj = _project(tmp_path)
    (proj / "link.thn").symlink_to(tmp_path / "outside" / "secret.thn")
    text = _error_text(_main(proj, "link.thn"))
    assert "outside the network's directory" in text and SECRET not in text


def test_include_inside_the_tree_and_through_include_path(tmp_path, monkeypatch, capsys):
    proj = _project(tmp_path)
    assert "p_load" in {p.name for p in load(_main(proj, "parts/loads.thn", "source a = p_load\n")).params}
    path = _main(proj, "../outside/shared.thn", "source a = p_shared\n")
    assert "outside" in _error_text(path)
    outside = tmp_path / "outside"
    assert "p_shared" in {p.name for p in load(path, include_path=[outside]).params}
    with include_path_scope([outside]):
        load(path)
    monkeypatch.setenv("TNN_INCLUDE_PATH", str(outside))
    load(path)
    monkeypatch.delenv("TNN_INCLUDE_PATH")
    assert main(["check", "-q", str(path)]) == 1
    assert main(["check", "-q", str(path), "--include-path", str(outside)]) == 0
    capsys.readouterr()


def test_text_without_a_file_includes_from_the_working_directory(tmp_path, monkeypatch):
    proj = _project(tmp_path)
    monkeypatch.chdir(proj)
    loads(f'network m "t"\ninclude "parts/loads.thn"\n{BODY}')
    with pytest.raises(TnnError, match="outside"):
        loads(f'network m "t"\ninclude "../outside/secret.thn"\n{BODY}')


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs named pipes")
def test_fifo_and_devices_are_refused_without_blocking(tmp_path):
    proj = _project(tmp_path)
    os.mkfifo(proj / "pipe.thn")
    code = (f"import sys; from tnn_dsl.cli import main; "
            f"sys.exit(main(['check', {str(proj / 'pipe.thn')!r}, {str(_main(proj, 'pipe.thn'))!r}, '/dev/zero']))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 1, r.stderr
    assert "pipe.thn`: it is a named pipe (FIFO), not a regular file" in r.stderr
    assert "cannot read the included file `pipe.thn`: it is a named pipe" in r.stderr
    assert "`/dev/zero`: it is a device, not a regular file" in r.stderr
    assert "Traceback" not in r.stderr


def test_directory_is_refused(tmp_path):
    with pytest.raises(TnnError, match="it is a directory"):
        load(tmp_path)


def test_size_caps(tmp_path, monkeypatch):
    monkeypatch.setattr(sources, "MAX_FILE_BYTES", 2000)
    import tnn_dsl.lang.builder as builder
    import tnn_dsl.lang.parser as parser

    monkeypatch.setattr(builder, "MAX_FILE_BYTES", 2000)
    monkeypatch.setattr(parser, "MAX_FILE_BYTES", 2000)
    big = tmp_path / "big.thn"
    big.write_text(f'network m "t"\n{BODY}' + "# padding\n" * 300)
    with pytest.raises(TnnError, match=r"more than the 2,000 a network file may have"):
        load(big)
    (tmp_path / "part.thn").write_text("# padding\n" * 300)
    text = _error_text(_main(tmp_path, "part.thn"))
    assert "cannot read the included file `part.thn`: it is 3,000 bytes, more than the 2,000" in text
    with pytest.raises(TnnError, match="more than the 2,000"):
        loads("#" * 2001)
    # the files of one network together
    monkeypatch.setattr(builder, "MAX_TOTAL_BYTES", 2500)
    (tmp_path / "p1.thn").write_text("# x\n" * 400)
    (tmp_path / "p2.thn").write_text("# y\n" * 400)
    main_file = tmp_path / "two.thn"
    main_file.write_text(f'network m "t"\ninclude "p1.thn"\ninclude "p2.thn"\n{BODY}')
    assert "together are more than 2,500 bytes" in _error_text(main_file)


def _bomb(tmp_path: Path, depth: int) -> Path:
    """Each file includes the next twice: 2**depth inclusions if each were read every time."""
    for i in range(depth):
        (tmp_path / f"f{i}.thn").write_text(f'include "f{i + 1}.thn"\ninclude "f{i + 1}.thn"\nparam p{i} = 1 W\n')
    (tmp_path / f"f{depth}.thn").write_text(f"param p{depth} = 1 W\n")
    m = tmp_path / "main.thn"
    m.write_text(f'network bomb "b"\ninclude "f0.thn"\n{BODY}source a = p0 + p{depth}\n')
    return m


def test_include_bomb_reads_each_file_once(tmp_path, monkeypatch):
    import tnn_dsl.lang.builder as builder

    calls: list[str] = []
    real = builder._statements

    def counting(text, filename, srcs):
        calls.append(os.path.basename(filename))
        return real(text, filename, srcs)

    monkeypatch.setattr(builder, "_statements", counting)
    net = load(_bomb(tmp_path, 24))
    assert sorted(calls) == sorted(f"f{i}.thn" for i in range(25))  # 25 reads, not 2**25
    assert {f"p{i}" for i in range(25)} <= {p.name for p in net.params}


def test_diamond_include_declares_once(tmp_path):
    (tmp_path / "common.thn").write_text("param k = 3 W\n")
    (tmp_path / "left.thn").write_text('include "common.thn"\nparam l = 1 W\n')
    (tmp_path / "right.thn").write_text('include "common.thn"\nparam r = 1 W\n')
    m = tmp_path / "main.thn"
    m.write_text(f'network d "t"\ninclude "left.thn"\ninclude "right.thn"\n{BODY}source a = k + l + r\n')
    assert [p.name for p in load(m).params].count("k") == 1


def test_include_cycle_still_an_error(tmp_path):
    (tmp_path / "a.thn").write_text('include "b.thn"\n')
    (tmp_path / "b.thn").write_text('include "a.thn"\n')
    assert "include cycle" in _error_text(_main(tmp_path, "a.thn"))


def test_long_string_refused_and_long_lines_shown_as_a_window(tmp_path):
    p = tmp_path / "label.thn"
    p.write_text('network m "' + "x" * 100_000 + f'"\n{BODY}')
    text = _error_text(p)
    assert "label.thn:1:11: error: a quoted string longer than 1000 characters" in text
    assert max(len(line) for line in text.splitlines()) < 200
    q = tmp_path / "wide.thn"
    q.write_text(f'network m "t"\n{BODY}' + "source a = " + " " * 500 + "bogus bogus\n")
    lines = _error_text(q).splitlines()
    assert lines[0].startswith(f"{q}:5:")
    shown, caret = lines[1], lines[2]
    assert len(shown) < 200 and "…" in shown
    assert shown[caret.index("^"):].startswith("bogus")


@pytest.mark.parametrize("clause, message", [
    ("mlp(a; hidden=[100000, 100000])", "would have 10,000,400,001 weights (about 320 GB while training)"),
    ("mlp(a; hidden=[4, 4, 4, 4, 4, 4, 4, 4, 4, 4, 4, 4, 4, 4, 4, 4, 4])", "17 hidden layers, more than 16"),
    ("poly(a; degree=100000)", "degree 100000 is above 8"),
])
def test_learned_function_size_caps_before_allocation(clause, message):
    with pytest.raises(TnnError) as e:
        loads(f'network m "t"\n{BODY}learn Ra as {clause}\n')
    assert message in e.value.format() and "<string>:5:1" in e.value.format()


@settings(max_examples=60, deadline=None)
@given(kind=st.sampled_from(["const", "linear", "poly", "mlp", "table"]), n_in=st.integers(1, 4),
       n_out=st.integers(1, 3), degree=st.integers(1, 4), hidden=st.lists(st.integers(1, 9), min_size=1, max_size=3),
       knots=st.integers(2, 6))
def test_weight_count_equals_the_compiled_arrays(kind, n_in, n_out, degree, hidden, knots):
    from tnn_dsl.ir.network import LearnFunction, LearnInput, LearnTarget

    n_in = 1 if kind == "table" else n_in
    fn = LearnFunction(name="f", kind=kind, targets=[LearnTarget(name=f"t{i}", kind="param") for i in range(n_out)],
                       inputs=[LearnInput(name=f"x{i}", kind="input") for i in range(0 if kind == "const" else n_in)],
                       hidden=hidden if kind == "mlp" else [], degree=degree if kind == "poly" else None,
                       knots=[float(k) for k in range(knots)] if kind == "table" else [])
    shapes = learned_arrays.array_shapes(fn, len(fn.inputs), n_out)
    assert fn.weight_count() == sum(math.prod(s) for s, k in shapes.values() if k == "weights")


def test_init_from_outside_the_project_is_refused(tmp_path):
    proj = _project(tmp_path)
    p = proj / "m.thn"
    p.write_text(f'network m "t"\n{BODY}learn Ra as const(; frozen, init_from = "../outside")\n')
    text = _error_text(p)
    assert "`init_from` names `../outside`, outside the network's directory" in text


_SEGMENTS = st.sampled_from(["..", ".", "parts", "loads.thn", "secret.thn", "outside", "link.thn", "proj", ""])


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(segments=st.lists(_SEGMENTS, min_size=1, max_size=6), absolute=st.booleans())
def test_no_include_path_reads_outside_the_tree(tmp_path, segments, absolute):
    """Whatever the include path, a file outside the project is never read: its content never reaches a
    message, and the only errors are `outside`, `no such file`, `a directory` or the included file's own."""
    proj = tmp_path / "proj"
    if not proj.exists():
        _project(tmp_path)
        (proj / "link.thn").symlink_to(tmp_path / "outside" / "secret.thn")
    inc = "/".join(segments)
    if absolute:
        inc = str(tmp_path) + "/" + inc
    path = _main(proj, inc.replace('"', ""))
    try:
        load(path)
        return
    except TnnError as e:
        text = e.format()
    assert SECRET not in text


@pytest.mark.parametrize("line, message", [
    ("G a -- b = 1e308 W/K", "`G_a_b` is a conductance of 1e+308 W/K, above the 1e-09 … 1e+06 W/K"),
    ("R a -- b = 2e-7 K/W", "`R_a_b` is a resistance of 2e-07 K/W, below the 1e-06 … 1e+09 K/W"),
])
def test_absurd_magnitudes_are_warned_about_and_still_valid(tmp_path, capsys, line, message):
    """Legal values orders of magnitude off (found by the mutation run): a warning with a caret from `check`
    (also with -q) and from `simulate`; exit 0."""
    p = tmp_path / "n.thn"
    p.write_text(f'network m "t"\n{BODY}node b C = 1 J/K\n{line}\n')
    assert main(["check", "-q", str(p)]) == 0
    err = capsys.readouterr().err
    assert f"{p}:6:12: warning: " + message in err and "^" in err
    from tnn_dsl.lang import magnitude_warnings

    assert magnitude_warnings(load(ROOT_NETS / "tclab" / "tclab.thn")) == []


ROOT_NETS = Path(__file__).resolve().parents[1] / "networks"


def test_no_shipped_network_is_warned_about():
    from tnn_dsl.lang import magnitude_warnings

    for p in sorted(ROOT_NETS.rglob("*.thn")):
        if "parts" not in p.parts:
            assert magnitude_warnings(load(p)) == [], p
