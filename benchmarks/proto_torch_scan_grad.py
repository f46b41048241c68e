"""Prototype (not the model's code path): a differentiable compiled torch rollout as one ``scan``, the parameters
passed through the scan's ``xs`` (expanded over time) instead of its closure. torch 2.13's ``scan`` does not
support gradients with respect to closed-over tensors (the model's forward-only compiled scan reads the
parameters that way); this measures whether the supported form is worth it for training.

Prints the largest state difference and the largest relative gradient difference against the same rollout run
eager, and the wall time per window-step of a second (compiled, warm) forward+gradient call.

    python benchmarks/proto_torch_scan_grad.py --batch 256 --steps 391 --compare   # case study M3, 256 windows
    python benchmarks/proto_torch_scan_grad.py --batch 1 --steps 2001 --compare    # one sequence

Measured 2026-11-26 (AMD EPYC, BENCHMARKS.md "Rollout cost: reading and proposals"): gradients within 1.5e-10
(relative) of eager; forward+gradient 4.84 µs per window-step on 256 windows (the model's step-by-step compiled
path in the same process: 4.87) and 2894 µs/step on one sequence (model: 547), 26–33 s of compilation: no gain.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))


def _walk(o, fn):
    """``o`` (a prepared-values object, dicts, lists, tuples) with every tensor ``t`` replaced by ``fn(t)``."""
    import torch

    from tnn_dsl.compiler.assembly import _Prep

    if isinstance(o, torch.Tensor):
        return fn(o)
    if isinstance(o, _Prep):
        n = _Prep()
        for s in _Prep.__slots__:
            if hasattr(o, s):
                setattr(n, s, _walk(getattr(o, s), fn))
        return n
    if type(o) is dict:
        return {k: _walk(v, fn) for k, v in o.items()}
    if type(o) in (list, tuple):
        return type(o)(_walk(v, fn) for v in o)
    if isinstance(o, dict):
        raise TypeError(f"cannot walk a {type(o).__name__}")
    return o


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--steps", type=int, default=391)
    ap.add_argument("--net", default=str(ROOT / "networks" / "peltier_heatpipe" / "m3.thn"))
    ap.add_argument("--compare", action="store_true", help="also time the model's own compiled rollout with gradients")
    args = ap.parse_args(argv)

    import nets
    import torch
    from torch._higher_order_ops import scan

    import tnn_dsl

    torch.set_num_threads(1)
    net = tnn_dsl.load(args.net)
    m = tnn_dsl.compile(net, "torch")
    p_np = nets.random_params(tnn_dsl.compile(net, "numpy"), 5)
    B, N = args.batch, args.steps
    rng = np.random.default_rng(0)
    ni = len(m.input_names)
    U = np.stack([np.stack([rng.uniform(0, 3, N), rng.uniform(0, 1, N)]
                           + [np.full(N, 295.15 + 3 * i) for i in range(ni - 2)], -1) for _ in range(B)])
    T0 = 298.15 + np.linspace(-2, 2, len(m.state_names)) + np.zeros((B, 1))

    def run(compiled):
        p = {k: v.requires_grad_(True) for k, v in m.from_numpy(p_np).items()}
        prep = m._prepare(p)
        leaves = []
        _walk(prep, lambda t: leaves.append(t) if t.requires_grad else None)
        M = N - 1
        Um = torch.movedim(torch.as_tensor(U)[:, :M], -2, 0).contiguous()

        def roll(prep, T0, Um, leaves):
            xs = dict(m._core.rhs_u(prep, Um))
            xs["p"] = [leaf.expand(M, *leaf.shape) for leaf in leaves]

            def body(T, c):
                it = iter(c["p"])
                pr = _walk(prep, lambda t: next(it) if t.requires_grad else t)
                Tn = m._stepper(pr, 1.0, "rk4", 1)(T, {"s": c["s"], "v": c["v"], "u": c["u"]})
                return Tn, Tn.clone()
            return scan(body, T0, xs)[1]

        f = torch.compile(roll, fullgraph=True) if compiled else roll
        t = time.perf_counter()
        ys = f(prep, torch.as_tensor(T0), Um, leaves)
        y = ys[..., 0]
        (y * torch.linspace(-1, 1, y.numel(), dtype=y.dtype).reshape(y.shape)).sum().backward()
        el = time.perf_counter() - t
        grads = {k: (np.zeros(v.shape) if v.grad is None else v.grad.numpy().copy()) for k, v in p.items()}
        return grads, ys.detach().numpy(), el

    mc = tnn_dsl.compile(net, "torch", torch_compile=True)

    def model_path():  # the model's own torch_compile=True rollout with gradients (step by step), same loss
        p = {k: v.requires_grad_(True) for k, v in mc.from_numpy(p_np).items()}
        t = time.perf_counter()
        states, _ = mc.rollout(p, torch.as_tensor(T0), torch.as_tensor(U), 1.0)
        y = states[:, 1:, 0]
        (y * torch.linspace(-1, 1, y.numel(), dtype=y.dtype).reshape(y.shape)).sum().backward()
        return time.perf_counter() - t

    ge, se, _ = run(False)
    gc, sc, t_first = run(True)
    _, _, t_warm = run(True)
    scale = max(float(np.abs(g).max()) for g in ge.values() if g.size)
    rel = max(float(np.abs(ge[k] - gc[k]).max()) / max(float(np.abs(ge[k]).max()), 1e-8 * scale)
              for k in ge if ge[k].size)
    print(f"max |states - eager| {np.abs(se - sc).max():.3g} K; max relative gradient difference {rel:.3g}")
    print(f"first call {t_first:.1f} s (compilation), warm call {t_warm:.3f} s = "
          f"{t_warm / (B * (N - 1)) * 1e6:.2f} µs per window-step (forward+gradient)")
    if args.compare:
        first = model_path()
        warm = model_path()
        print(f"the model's step-by-step compiled path, same process: first call {first:.1f} s, warm call "
              f"{warm:.3f} s = {warm / (B * (N - 1)) * 1e6:.2f} µs per window-step")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
