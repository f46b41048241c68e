"""The README's Python API tour, runnable: load a network, compile it for JAX or PyTorch, simulate the
case study's data, train the linear heat pipe (M2), save/load the model, evaluate on held-out data.

    python examples/quickstart.py [--out out/quickstart] [--backend jax|torch] [--hours 4] [--epochs 300]

The data come from the package's case-study generator (shared/spec/case-study.md); `--hours` shortens the
training set (the validation set is half as long).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import tnn_dsl

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/quickstart")
    ap.add_argument("--backend", default="jax", choices=("jax", "torch"))
    ap.add_argument("--hours", type=float, default=4.0)
    ap.add_argument("--epochs", type=int, default=300)
    ap.add_argument("--lbfgs-iters", type=int, default=300)
    args = ap.parse_args(argv)
    out = Path(args.out)

    # 1. the network: a validated IR; net.graph() is its networkx view
    net = tnn_dsl.load(ROOT / "networks/peltier_heatpipe/m2.thn")
    print(f"{net.name}: {len(net.nodes)} nodes, {len(net.links)} links, learned: "
          f"{[t.name for fn in net.learned for t in fn.targets]}")

    # 2. data: the case-study generator writes ordinary CSV files
    sets = tnn_dsl.generate_case_study(out / "data", widen=(), n_ood=0,
                                       durations=(3600 * args.hours, 1800 * args.hours, 0.0))
    train, val = tnn_dsl.read_data(net, [sets["train"], sets["val"]])

    # 3. compile and simulate the untrained model (it starts exactly at the nominal network)
    model = tnn_dsl.compile(net, backend=args.backend)
    params = model.init_params()
    conv = model.from_numpy
    arrays = conv({"u": train.inputs, "u0": train.inputs[0]})
    T0 = model.steady_state(params, arrays["u0"])
    states, outputs = model.rollout(params, T0, arrays["u"], train.dt)
    y = model.to_numpy({"y": outputs})["y"]
    mae0 = float(np.nanmean(np.abs(y - train.outputs)))
    print(f"untrained (nominal) model, training data: MAE {mae0:.4f} K")

    # 4. train (Adam, then L-BFGS) and save a model directory (no pickle)
    fitted = tnn_dsl.train(net, [train], val=[val], backend=args.backend, epochs=args.epochs,
                           lbfgs_iters=args.lbfgs_iters, out=out / "m2")

    # 5. load it back and evaluate on the held-out set (free run, thesis eq. 4.9)
    metrics = tnn_dsl.load_model(out / "m2").evaluate([val])
    print("validation:", {k: v for k, v in metrics.items() if k in ("mae", "max")})
    return {"untrained_mae": mae0, "metrics": metrics, "fitted": fitted}


if __name__ == "__main__":
    main()
