"""The layering of docs/architecture.md holds, and the check that enforces it (import-linter, run by
``make lint``) would catch an upward import: a copy of the package with one module of ``ir`` importing the
compiler must break the contracts."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")

pytestmark = pytest.mark.skipif(not LINT_IMPORTS.exists(),
                                reason="import-linter is not installed (pip install -e .[dev])")


def _lint_imports(package_parent: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(package_parent))
    return subprocess.run([str(LINT_IMPORTS), "--config", str(ROOT / "pyproject.toml"), "--no-cache"],
                          cwd=package_parent, env=env, capture_output=True, text=True, timeout=300)


def _copy_package(tmp_path: Path) -> Path:
    shutil.copytree(ROOT / "tnn_dsl", tmp_path / "tnn_dsl", ignore=shutil.ignore_patterns("__pycache__"))
    return tmp_path / "tnn_dsl"


def test_the_package_keeps_its_layers(tmp_path):
    _copy_package(tmp_path)
    r = _lint_imports(tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 broken" in r.stdout


def test_an_upward_import_breaks_the_layers(tmp_path):
    pkg = _copy_package(tmp_path)
    (pkg / "ir" / "upward_probe.py").write_text("from tnn_dsl.compiler import compile  # noqa: F401\n")
    r = _lint_imports(tmp_path)
    assert r.returncode != 0
    assert "tnn_dsl.ir is not allowed to import tnn_dsl.compiler" in r.stdout
    assert "tnn_dsl.ir.upward_probe -> tnn_dsl.compiler" in r.stdout


def test_the_parser_may_not_import_the_compiler(tmp_path):
    pkg = _copy_package(tmp_path)
    (pkg / "lang" / "tensor_probe.py").write_text("import tnn_dsl.compiler.physics  # noqa: F401\n")
    r = _lint_imports(tmp_path)
    assert r.returncode != 0
    assert "the parser knows nothing of tensors, the compiler nothing of syntax BROKEN" in " ".join(r.stdout.split())
