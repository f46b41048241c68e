"""The README's API tour (examples/quickstart.py) runs and training improves on the nominal model."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


# the torch variant (104 s on 2 cores in CI) is slow; the JAX variant (23 s) stays in CI
@pytest.mark.parametrize("backend", ["jax", pytest.param("torch", marks=pytest.mark.slow)])
def test_quickstart_runs_and_training_helps(tmp_path, backend):
    spec = importlib.util.spec_from_file_location("quickstart", ROOT / "examples" / "quickstart.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    res = mod.main(["--out", str(tmp_path), "--backend", backend, "--hours", "0.25", "--epochs", "8",
                    "--lbfgs-iters", "5"])
    assert res["metrics"]["mae"] < 0.75 * res["untrained_mae"]
    assert (tmp_path / "m2" / "params.safetensors").is_file()
