"""Test-session settings shared by every test file."""

from __future__ import annotations


def pytest_configure(config):
    # The networks are small: torch's intra-op threads only add synchronisation (measured 47× slower per
    # batched step with 2 threads than with 1 on the 2-core CI machine, benchmarks/bench_rollout.py
    # --torch-threads), and pytest-xdist already runs one worker per core.
    try:
        import torch
    except ImportError:  # pragma: no cover
        return
    torch.set_num_threads(1)
