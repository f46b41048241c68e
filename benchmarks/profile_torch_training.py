"""Where a compiled-torch training run spends its time (issue 18): each graph torch compiles (name and seconds),
and every rollout of a short training timed call by call, grouped by input shape and by whether it carries
gradients, with the backward passes apart. Case study (4 h train / 2 h validation, the cache of
``bench_train.py``), a fixed schedule (Adam ``--epochs``, validation every 10, no L-BFGS), seed 0.

    python benchmarks/profile_torch_training.py m2 --epochs 30
    python benchmarks/profile_torch_training.py m3 --epochs 20 --backend jax   # the same schedule on JAX

The README's training paragraph of 2026-11-27 (Intel Xeon) quoted it; it is kept in docs/measurement-log.md.
"""

from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model", choices=("m2", "m3"))
    ap.add_argument("--epochs", type=int, default=20)
    ap.add_argument("--backend", choices=("torch", "jax"), default="torch")
    ap.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "tnn_bench_train_cs"))
    args = ap.parse_args(argv)

    import tnn_dsl
    from tnn_dsl.compiler import model as compiled_model
    from tnn_dsl.studies.casestudy import generate_case_study

    t0 = time.perf_counter()
    calls: dict = collections.defaultdict(list)
    backward: list = []
    if args.backend == "torch":
        import torch
        import torch._dynamo.convert_frame as convert_frame

        compile_inner = convert_frame._compile

        def timed_compile(code, *a, **k):
            t = time.perf_counter()
            out = compile_inner(code, *a, **k)
            print(f"[{t - t0:6.1f} s] compiled {code.co_name} in {time.perf_counter() - t:.1f} s", flush=True)
            return out
        convert_frame._compile = timed_compile

        rollout = compiled_model.Model.rollout

        def timed_rollout(self, params, T0, inputs, *a, **k):
            t = time.perf_counter()
            out = rollout(self, params, T0, inputs, *a, **k)
            grad = torch.is_grad_enabled() and any(getattr(v, "requires_grad", False) for v in params.values())
            calls[(tuple(inputs.shape), grad)].append(time.perf_counter() - t)
            return out
        compiled_model.Model.rollout = timed_rollout
        grad_fn = torch.autograd.grad

        def timed_grad(*a, **k):
            t = time.perf_counter()
            out = grad_fn(*a, **k)
            backward.append(time.perf_counter() - t)
            return out
        torch.autograd.grad = timed_grad

    cs = generate_case_study(args.cache, n_ood=0, widen=(), durations=None)

    def progress(info):
        if info.get("val_mae") is not None and info.get("epoch") in (0, 1, args.epochs):
            print(f"[{time.perf_counter() - t0:6.1f} s] epoch {info.get('epoch')}", flush=True)

    t_train = time.perf_counter()
    tnn_dsl.train(ROOT / "networks" / "peltier_heatpipe" / f"{args.model}.thn", cs["train"], cs["val"],
                  backend=args.backend, torch_compile=args.backend == "torch", seed=0, callback=progress,
                  epochs=args.epochs, val_every=10, lbfgs_iters=0, patience=0)
    print(f"training: {time.perf_counter() - t_train:.1f} s")
    for (shape, grad), ts in sorted(calls.items(), key=lambda kv: -sum(kv[1])):
        print(f"rollout {shape} {'with' if grad else 'without'} gradients: {len(ts)} calls, median "
              f"{np.median(ts):.4f} s, total {sum(ts):.2f} s")
    if backward:
        print(f"backward passes (torch.autograd.grad): {len(backward)}, median {np.median(backward):.4f} s, "
              f"max {max(backward):.1f} s (with compilation)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
