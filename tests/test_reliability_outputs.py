"""Never lose a file (issue 13, data-loss items): outputs are checked before any work, never overwrite an
input or a file of another kind, and model directories are written so that the path always holds a
complete model — across failures, SIGKILL and concurrent writers."""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tnn_dsl.cli import main
from tnn_dsl.core.errors import ModelFileError, TnnError
from tnn_dsl.core.files import CSV, JSON, THN, atomic_path, check_output
from tnn_dsl.fit.model_files import is_model_dir, load_model, save_model

sys.path.insert(0, str(Path(__file__).parent))
from test_cli_simulate import RC, rc_data  # noqa: E402
from test_model_io import _net, _params  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def rc_net(tmp_path: Path) -> str:
    """The one-node RC network of test_cli_simulate with its conductance free (so that it trains)."""
    p = tmp_path / "rc.thn"
    p.write_text(RC.replace("G n -- amb = 2 W/K", "G n -- amb = 2 W/K  free"))
    return str(p)


def _digest(path: Path) -> dict[str, str]:
    """Relative path -> SHA-256 of every file below ``path`` (the state that must survive)."""
    return {str(p.relative_to(path)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(path.rglob("*")) if p.is_file()}


def _user_dir(tmp_path: Path, data: str) -> Path:
    """A directory of the user's: notes, a sub-directory, and the training CSV itself."""
    d = tmp_path / "work"
    (d / "sub").mkdir(parents=True)
    (d / "notes.txt").write_text("my notes\n")
    (d / "sub" / "thesis.tex").write_text("\\documentclass{article}\n")
    (d / "train.csv").write_bytes(Path(data).read_bytes())
    return d


@pytest.fixture
def no_training(monkeypatch):
    """Any attempt to train fails the test: refusals must come before any work."""
    import tnn_dsl.fit.training as T

    def boom(*a, **k):
        raise AssertionError("training started although the output should have been refused first")

    monkeypatch.setattr(T, "_Trainer", boom)


# ---------------------------------------------------------------------------------------------
# tnnc train -o: an existing directory that is not a model
# ---------------------------------------------------------------------------------------------


def test_train_refuses_a_directory_that_is_not_a_model_and_deletes_nothing(tmp_path, capsys, no_training):
    net, data = rc_net(tmp_path), rc_data(tmp_path)
    d = _user_dir(tmp_path, data)
    before = _digest(d)
    # the case: the directory holds the training CSV itself
    assert main(["train", net, str(d / "train.csv"), "-o", str(d), "--epochs", "2"]) == 1
    err = capsys.readouterr().err
    assert "the input" in err and "lies inside this output directory" in err and "Traceback" not in err
    # and a directory of other files only
    assert main(["train", net, data, "-o", str(d), "--epochs", "2"]) == 1
    err = capsys.readouterr().err
    assert "is not a model directory written by tnnc" in err and "--force" in err and "Traceback" not in err
    assert _digest(d) == before


def test_train_force_writes_into_the_directory_and_keeps_its_files(tmp_path, capsys):
    net, data = rc_net(tmp_path), rc_data(tmp_path)
    d = _user_dir(tmp_path, data)
    before = _digest(d)
    rc = main(["train", net, data, "-o", str(d), "--force", "--epochs", "3", "--lbfgs-iters", "0", "-q"])
    assert rc == 0, capsys.readouterr().err
    after = _digest(d)
    assert all(after[k] == v for k, v in before.items())  # every file of the user's is still there, unchanged
    assert load_model(d).network.name == "rc"
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_train_replaces_an_existing_model_without_force(tmp_path, capsys):
    net, data = rc_net(tmp_path), rc_data(tmp_path)
    out = tmp_path / "model"
    args = ["train", net, data, "-o", str(out), "--epochs", "2", "--lbfgs-iters", "0", "-q"]
    assert main(args) == 0
    first = load_model(out).meta["write_id"]
    assert main(args) == 0, capsys.readouterr().err
    assert load_model(out).meta["write_id"] != first
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model", "rc.csv", "rc.thn"]


def test_retraining_into_a_model_directory_keeps_the_users_files_in_it(tmp_path, capsys):
    """A model directory the user has put notes and plots into is not theirs to lose: training into it again
    (no --force needed: it is a model) replaces the model's files and keeps the rest."""
    net, data = rc_net(tmp_path), rc_data(tmp_path)
    out = tmp_path / "model"
    args = ["train", net, data, "-o", str(out), "--epochs", "2", "--lbfgs-iters", "0", "-q"]
    assert main(args) == 0
    first = load_model(out).meta["write_id"]
    (out / "notes.txt").write_text("what I tried")
    (out / "plots").mkdir()
    (out / "plots" / "fit.png").write_bytes(b"png")
    assert main(args) == 0, capsys.readouterr().err
    assert load_model(out).meta["write_id"] != first
    assert (out / "notes.txt").read_text() == "what I tried" and (out / "plots" / "fit.png").read_bytes() == b"png"
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


@pytest.mark.parametrize("what", ["file", "below-a-file", "input-csv", "input-thn"])
def test_train_refuses_a_bad_output_before_training(tmp_path, capsys, no_training, what):
    net, data = rc_net(tmp_path), rc_data(tmp_path)
    (tmp_path / "afile").write_text("keep me")
    out = {"file": tmp_path / "afile", "below-a-file": tmp_path / "afile" / "model",
           "input-csv": Path(data), "input-thn": Path(net)}[what]
    before = _digest(tmp_path)
    for extra in ([], ["--force"]):  # --force never deletes a file to make room for a directory
        assert main(["train", net, data, "-o", str(out), *extra]) == 1
        err = capsys.readouterr().err
        assert "error:" in err and "Traceback" not in err
        assert _digest(tmp_path) == before


def test_train_api_checks_out_before_training(tmp_path, no_training):
    import tnn_dsl

    net, data = rc_net(tmp_path), rc_data(tmp_path)
    d = _user_dir(tmp_path, data)
    with pytest.raises(TnnError, match="not a model directory"):
        tnn_dsl.train(net, [data], out=d, epochs=2)


# ---------------------------------------------------------------------------------------------
# output = input, and outputs of another kind
# ---------------------------------------------------------------------------------------------


def test_simulate_refuses_to_overwrite_its_measurement_file(tmp_path, capsys):
    net, data = rc_net(tmp_path), rc_data(tmp_path)
    before = Path(data).read_bytes()
    for extra in ([], ["--force"]):
        assert main(["simulate", net, "--data", data, "-o", data, *extra]) == 1
        assert "also an input" in capsys.readouterr().err
        assert Path(data).read_bytes() == before
    # the same file through another spelling of its path
    alias = tmp_path / "sub" / ".." / Path(data).name
    (tmp_path / "sub").mkdir()
    assert main(["simulate", net, "--data", data, "-o", str(alias)]) == 1
    link = tmp_path / "link.csv"
    link.symlink_to(data)
    assert main(["simulate", net, "--data", data, "-o", str(link)]) == 1
    assert Path(data).read_bytes() == before


def test_simulate_output_a_directory_is_refused_and_leaves_nothing(tmp_path, capsys):
    net, data = rc_net(tmp_path), rc_data(tmp_path)
    outdir = tmp_path / "outdir"
    outdir.mkdir()
    assert main(["simulate", net, "--data", data, "-o", str(outdir)]) == 1
    err = capsys.readouterr().err
    assert "is a directory" in err and "internal error" not in err
    assert list(outdir.iterdir()) == [] and sorted(p.name for p in tmp_path.iterdir()) == ["outdir", "rc.csv", "rc.thn"]


def test_simulate_overwrites_an_earlier_csv_but_not_a_file_of_another_kind(tmp_path, capsys):
    net, data = rc_net(tmp_path), rc_data(tmp_path)
    out = tmp_path / "sim.csv"
    assert main(["simulate", net, "--data", data, "-o", str(out)]) == 0
    assert main(["simulate", net, "--data", data, "-o", str(out)]) == 0  # an earlier result: replaced
    other = tmp_path / "report.docx"
    other.write_bytes(b"precious")
    assert main(["simulate", net, "--data", data, "-o", str(other)]) == 1
    assert "--force" in capsys.readouterr().err and other.read_bytes() == b"precious"
    assert main(["simulate", net, "--data", data, "-o", str(other), "--force"]) == 0
    assert other.read_text().startswith("time_s")


def test_compile_refuses_to_overwrite_its_source(tmp_path, capsys):
    net = Path(rc_net(tmp_path))
    before = net.read_bytes()
    for emit in ("equations", "ir-json", "graph"):
        assert main(["compile", str(net), "--emit", emit, "-o", str(net)]) == 1
        assert "also an input" in capsys.readouterr().err
    assert net.read_bytes() == before


def test_compile_refuses_an_included_file(tmp_path, capsys):
    (tmp_path / "part.thn").write_text("param Ta = 20 degC\n")
    main_thn = tmp_path / "main.thn"
    main_thn.write_text(Path(rc_net(tmp_path)).read_text().replace("param Ta = 20 degC\n", 'include "part.thn"\n'))
    before = (tmp_path / "part.thn").read_bytes()
    assert main(["compile", str(main_thn), "-o", str(tmp_path / "part.thn"), "--force"]) == 1
    assert (tmp_path / "part.thn").read_bytes() == before


def test_diagnose_refuses_to_overwrite_its_network_before_any_work(tmp_path, capsys, monkeypatch):
    import tnn_dsl.doctor.session as D
    from tnn_dsl.doctor import diagnose

    net, data = rc_net(tmp_path), rc_data(tmp_path)
    before = Path(net).read_bytes()
    monkeypatch.setattr(D, "_unused_columns", lambda *a: (_ for _ in ()).throw(AssertionError("work started")))
    assert main(["diagnose", net, data, "-o", net, "--quiet"]) == 1
    assert "also an input" in capsys.readouterr().err
    with pytest.raises(TnnError, match="also an input"):
        diagnose(net, [data], output=net)
    assert Path(net).read_bytes() == before


def test_evaluate_json_inside_the_model_directory_is_refused(tmp_path, capsys):
    net, data = rc_net(tmp_path), rc_data(tmp_path)
    out = tmp_path / "model"
    assert main(["train", net, data, "-o", str(out), "--epochs", "2", "--lbfgs-iters", "0", "-q"]) == 0
    before = _digest(out)
    assert main(["evaluate", str(out), data, "--json", str(out / "meta.json")]) == 1
    assert "inside the input directory" in capsys.readouterr().err
    assert main(["estimate", str(out), data, "--use", "Tn", "-o", data]) == 1
    assert _digest(out) == before


def test_report_directory_and_generate_directory(tmp_path, capsys):
    from tnn_dsl.doctor.report import REPORT_DIR
    from tnn_dsl.studies.casestudy import DATA_DIR

    d = tmp_path / "site"
    d.mkdir()
    (d / "index.html").write_text("<html>my web site</html>")
    with pytest.raises(TnnError, match="not a report directory"):
        check_output(d, REPORT_DIR)
    assert check_output(d, REPORT_DIR, force=True) == d
    home = tmp_path / "home"
    home.mkdir()
    (home / "train.csv").write_text("mine")
    with pytest.raises(TnnError, match="not a case-study data directory"):
        check_output(home, DATA_DIR)
    assert main(["generate", "case-study", "-o", str(home)]) == 1
    assert (home / "train.csv").read_text() == "mine"


def test_check_output_kind_rules(tmp_path):
    assert check_output("-", JSON) == Path("-")
    (tmp_path / "x.thn").write_text("network x")
    (tmp_path / "x.csv").write_text("a")
    assert check_output(tmp_path / "x.thn", THN) == tmp_path / "x.thn"
    with pytest.raises(TnnError, match="not a .thn network file"):
        check_output(tmp_path / "x.csv", THN)
    with pytest.raises(TnnError, match="is a directory"):
        check_output(tmp_path, CSV)
    assert check_output(tmp_path / "new" / "deeper" / "y.csv", CSV)


# ---------------------------------------------------------------------------------------------
# model writes: failures, SIGKILL, concurrency
# ---------------------------------------------------------------------------------------------


def test_failed_swap_keeps_the_old_model_and_leaves_no_stray_files(tmp_path, monkeypatch):
    import tnn_dsl.fit.model_files as M

    d = save_model(tmp_path / "m", _net(), _params(), {"run": 1})

    def interrupted(tmp, path):
        raise KeyboardInterrupt

    monkeypatch.setattr(M, "_install", interrupted)
    with pytest.raises(KeyboardInterrupt):
        save_model(d, _net(), _params(), {"run": 2})
    assert load_model(d).meta["run"] == 1
    assert [p.name for p in tmp_path.iterdir()] == ["m"]


def test_a_writer_killed_at_any_moment_leaves_a_complete_model(tmp_path):
    """SIGKILL a process that rewrites the model in a loop, at several moments: the path always loads
    (the old or a new model), and the next write removes the dead writer's temporary directory."""
    d = tmp_path / "m"
    save_model(d, _net(), _params(), {"run": -1})
    script = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_model_io import _net, _params
        from tnn_dsl.fit.model_files import save_model
        net, params = _net(), _params()
        print("ready", flush=True)
        for k in range(100000):
            save_model({str(d)!r}, net, params, {{"run": k}})
    """)
    for delay in (0.02, 0.05, 0.09, 0.13, 0.2, 0.31, 0.45, 0.57):
        proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=str(ROOT))
        try:
            assert proc.stdout.readline().strip() == "ready"
            time.sleep(delay)
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert isinstance(load_model(d).meta["run"], int)
    save_model(d, _net(), _params(), {"run": "final"})
    assert load_model(d).meta["run"] == "final"
    assert [p.name for p in tmp_path.iterdir()] == ["m"]


def test_concurrent_writers_and_a_reader_never_see_the_path_empty(tmp_path):
    """Two processes save 60 times each to one path while a third loads it: no error anywhere."""
    d = tmp_path / "m"
    save_model(d, _net(), _params(), {"run": 0})
    writer = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_model_io import _net, _params
        from tnn_dsl.fit.model_files import save_model
        net, params = _net(), _params()
        for k in range(60):
            save_model({str(d)!r}, net, params, {{"run": k, "who": sys.argv[1]}})
    """)
    reader = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from tnn_dsl.fit.model_files import load_model
        for k in range(150):
            tm = load_model({str(d)!r})
            assert tm.params["C_a"].shape == ()
    """)
    procs = [subprocess.Popen([sys.executable, "-c", writer, w], stderr=subprocess.PIPE, text=True, cwd=str(ROOT))
             for w in ("a", "b")]
    procs.append(subprocess.Popen([sys.executable, "-c", reader], stderr=subprocess.PIPE, text=True, cwd=str(ROOT)))
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
    assert load_model(d).meta["run"] == 59
    assert [p.name for p in tmp_path.iterdir()] == ["m"]


_NAMES = st.one_of(
    st.sampled_from(["meta.json", "network.json", "params.safetensors", "network.thn", "notes.txt", "train.csv"]),
    st.text(alphabet="abcdefgh._-", min_size=1, max_size=8).filter(lambda s: s not in (".", "..")))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(files=st.dictionaries(_NAMES, st.binary(max_size=64), min_size=1, max_size=6), force=st.booleans())
def test_a_model_write_never_changes_another_file(tmp_path_factory, files, force):
    """Whatever a directory holds, writing a model there either is refused (nothing changed) or succeeds
    with every file that is not a model file unchanged."""
    d = tmp_path_factory.mktemp("any")
    for name, data in files.items():
        (d / name).write_bytes(data)
    before = _digest(d)
    try:
        save_model(d, _net(), _params(), {"run": 1}, force=force)
    except ModelFileError:
        assert _digest(d) == before
        assert not force or not d.is_dir()
        return
    after = _digest(d)
    model_files = {"network.json", "params.safetensors", "meta.json", "network.thn"}
    assert all(after.get(k) == v for k, v in before.items() if k not in model_files)
    assert is_model_dir(d)
    assert load_model(d).meta["run"] == 1
    assert [p.name for p in d.parent.iterdir() if p.name.startswith(f".{d.name}.")] == []


def test_atomic_path_leaves_nothing_on_error(tmp_path):
    dest = tmp_path / "out.csv"
    dest.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(dest) as tmp:
            tmp.write_text("half")
            raise RuntimeError("disk full")
    assert dest.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["out.csv"]


def test_model_files_are_flushed(tmp_path, monkeypatch):
    """Every file of a model and the directories holding them are fsync'ed (Linux: names from /proc)."""
    if not Path("/proc/self/fd").is_dir():
        pytest.skip("needs /proc to name the flushed files")
    synced: list[str] = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(os.readlink(f"/proc/self/fd/{fd}")), real(fd))[1])
    save_model(tmp_path / "m", _net(), _params(), {})
    names = {Path(s).name for s in synced}
    assert {"meta.json", "params.safetensors", "network.json"} <= names
    assert str(tmp_path) in synced  # the rename into place is flushed too


def test_a_directory_of_someones_sources_is_not_a_model(tmp_path):
    """network.thn and include/ are names a user's own sources have too: a directory holding only those is not
    a model, so it is never swapped away or deleted; with force the user's files stay byte for byte."""
    d = tmp_path / "proj"
    (d / "include").mkdir(parents=True)
    (d / "network.thn").write_text("network mine\n# my own file\n")
    (d / "include" / "parts.thn").write_text("param p = 1 W\n")
    before = _digest(d)
    assert not is_model_dir(d)
    with pytest.raises(ModelFileError):
        save_model(d, _net(), _params(), {})
    assert _digest(d) == before
    save_model(d, _net(), _params(), {}, force=True)
    after = _digest(d)
    assert {k: after[k] for k in before} == before
    assert load_model(d).params["C_a"] == 4.5
    empty = tmp_path / "empty"
    empty.mkdir()
    assert is_model_dir(save_model(empty, _net(), _params(), {}))
