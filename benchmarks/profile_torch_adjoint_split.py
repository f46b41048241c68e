"""Where compiled torch's batched forward + gradient goes (issue 18): the case study M3 (RK4, float64) on
``bench_rollout.py``'s batch of windows (256 × 390 samples by default), timed as a forward rollout without
gradients, and a rollout with gradients split into its forward (the compiled forward scan) and its
``loss.backward()`` (the compiled adjoint scan), each in µs per window-step; the first calls (compiling both
scans) are printed apart.

    TORCHINDUCTOR_CACHE_DIR=$(mktemp -d) python benchmarks/profile_torch_adjoint_split.py
    TORCHINDUCTOR_CACHE_DIR=$(mktemp -d) python benchmarks/profile_torch_adjoint_split.py --vectorize

``--vectorize`` turns on inductor's SIMD kernels for both scans (``compiler.model.TORCH_VECTORIZE``, off by
default). Compare settings one after the other, each in a fresh cache directory (the host's speed drifts). A
profiling tool, not part of ``make bench`` (it writes no section of BENCHMARKS.md).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def _option(text: str) -> tuple[str, object]:
    """``KEY=VALUE`` of ``--inductor-option`` as ``(key, value)``."""
    key, sep, raw = text.partition("=")
    if not sep or not key:
        raise SystemExit(f"error: --inductor-option wants KEY=VALUE, got {text!r}")
    low = raw.strip().lower()
    if low in ("true", "false"):
        return key.strip(), low == "true"
    for kind in (int, float):
        try:
            return key.strip(), kind(raw)
        except ValueError:
            pass
    return key.strip(), raw


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--vectorize", action="store_true", help="inductor's SIMD kernels on (TORCH_VECTORIZE)")
    ap.add_argument("--inductor-option", action="append", default=[], metavar="KEY=VALUE",
                    help="an extra inductor option for both scans (repeatable; VALUE read as int, float, "
                         "true/false or text), e.g. cpp.simdlen=256")
    ap.add_argument("--batch", type=int, default=256, help="windows (default 256)")
    ap.add_argument("--steps", type=int, default=100000, help="samples the windows are cut from (default 100000)")
    ap.add_argument("--repeats", type=int, default=3, help="timed calls after the first (default 3)")
    args = ap.parse_args(argv)

    import bench_rollout as br
    import torch

    import tnn_dsl
    import tnn_dsl.compiler.model as compiled_model

    compiled_model.TORCH_VECTORIZE = bool(args.vectorize)
    extra = dict(_option(o) for o in args.inductor_option)
    if extra:
        base = compiled_model.inductor_options
        compiled_model.inductor_options = lambda: {**base(), **extra}
    torch.set_num_threads(1)
    case = br.Case(br.parse(["--steps", str(args.steps), "--batch", str(args.batch)]))
    model = tnn_dsl.compile(case.net, "torch", torch_compile=True)
    T0, U = torch.as_tensor(case.T0b), torch.as_tensor(case.Ub[:, :case.window])
    p = model.from_numpy(case.params)
    n = case.window * case.batch

    def forward():
        with torch.no_grad():
            model.rollout(p, T0, U, case.dt, case.integrator)

    def with_gradient():
        pg = dict(p)
        for k in case.trainable:
            pg[k] = p[k].detach().clone().requires_grad_(True)
        t0 = time.perf_counter()
        _, y = model.rollout(pg, T0, U, case.dt, case.integrator)
        loss = torch.mean((y - case.y_ref) ** 2)
        t1 = time.perf_counter()
        loss.backward()
        return t1 - t0, time.perf_counter() - t1

    t = time.perf_counter()
    forward()
    print(f"first forward (compiling the forward scan): {time.perf_counter() - t:.1f} s")
    t = time.perf_counter()
    with_gradient()
    print(f"first forward + gradient (compiling the adjoint scan): {time.perf_counter() - t:.1f} s")
    print(f"M3, {case.batch} windows × {case.window} samples, vectorised kernels {'on' if args.vectorize else 'off'}"
          f"{'; ' + ', '.join(args.inductor_option) if args.inductor_option else ''}; µs per window-step:")
    for _ in range(args.repeats):
        t = time.perf_counter()
        forward()
        tf = time.perf_counter() - t
        gf, gb = with_gradient()
        print(f"  forward {tf / n * 1e6:.3f}   with gradient: forward {gf / n * 1e6:.3f}, backward {gb / n * 1e6:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
