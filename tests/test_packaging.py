"""The wheel ships the grammar and the networks: a wheel built from the repo parses files outside the
checkout (issue 2) and finds the case study's true network (the generator needs it)."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(out), str(ROOT)], check=True, capture_output=True)
    (whl,) = out.glob("tnn_dsl-*.whl")
    return whl


def test_wheel_contains_grammar_and_networks(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    assert "tnn_dsl/grammars/thn.lark" in names
    assert "tnn_dsl/networks/peltier_heatpipe/truth.thn" in names
    assert "tnn_dsl/networks/tclab/tclab.thn" in names


def test_installed_wheel_parses_a_file_outside_the_checkout(wheel, tmp_path):
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    work = tmp_path / "elsewhere"
    work.mkdir()
    (work / "board.thn").write_text(
        'network board\nunits temperature = degC\nparam Ta = 20 degC\nboundary amb = Ta\n'
        'node a C = 10 J/K\nR a -- amb = 2 K/W\nsensor Ta_meas = a column "T"\n')
    code = (
        "import tnn_dsl, sys\n"
        "assert 'site' in tnn_dsl.__file__, tnn_dsl.__file__\n"
        "net = tnn_dsl.load('board.thn')\n"
        "from tnn_dsl.studies.casestudy import truth_network_path\n"
        "p = truth_network_path()\n"
        "assert 'site' in str(p) and p.is_file(), p\n"
        "print(len(net.nodes), net.param('R_a_amb').value)\n"
    )
    env = dict(os.environ, PYTHONPATH=str(site))
    res = subprocess.run([sys.executable, "-c", code], cwd=work, env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["1", "2.0"]


def test_wheel_is_typed_and_the_version_comes_from_the_metadata(wheel):
    from importlib import metadata

    import tnn_dsl

    assert "tnn_dsl/py.typed" in set(zipfile.ZipFile(wheel).namelist())
    assert tnn_dsl.__version__ == metadata.version("tnn_dsl")
    assert wheel.name.startswith(f"tnn_dsl-{tnn_dsl.__version__}-")


def test_public_names_are_visible_and_lazy():
    code = ("import sys, tnn_dsl\n"
            "assert 'jax' not in sys.modules and 'torch' not in sys.modules\n"
            "missing = [n for n in tnn_dsl.__all__ if getattr(tnn_dsl, n, None) is None]\n"
            "assert not missing, missing\n"
            "assert sorted(dir(tnn_dsl)) == sorted(tnn_dsl.__all__)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr
