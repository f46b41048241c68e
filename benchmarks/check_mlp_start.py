"""How closely an MLP started as a linear law computes it (``tnn_dsl.doctor.mlp_check.mlp_start``, the doctor's
nested linear-or-MLP check; issue 18): for 1–6 inputs and 1 or 3 outputs, five random laws each (weights ~ N(0, 0.4),
biases ~ N(0, 0.2)), the largest raw-output difference over the normalised inputs' box and the largest output weight.

    python benchmarks/check_mlp_start.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import tnn_dsl  # noqa: E402
from tnn_dsl.doctor.mlp_check import mlp_start, mlp_variant  # noqa: E402

INPUTS = ["u1", "u2", "u3", "u4", "u5", "u6"]


def main() -> int:
    print("| inputs | outputs | largest |Δz| (5 laws) | largest output weight |")
    print("|---|---|---|---|")
    for n_in in range(1, 7):
        for n_out in (1, 3):
            targets = ", ".join(f"G{j}" for j in range(n_out))
            text = ("network n\n" + "".join(f"input {u} : [1]\n" for u in INPUTS[:n_in])
                    + "boundary amb = 20 degC\n" + "".join(f"node {x}  C = 1 J/K\n" for x in "abcd")
                    + "G a -- amb = 1 W/K\n" + "".join(f"G {x} -- amb = 1 W/K\n" for x in "bcd")
                    + "".join(f"G a -- {x} = 1 W/K  as G{j}\n" for j, x in enumerate("bcd"[:n_out]))
                    + f"learn {targets} as linear({', '.join(INPUTS[:n_in])})\n")
            net = tnn_dsl.loads(text, "n.thn")
            net_mlp, _ = mlp_variant(net, {f"G{j}" for j in range(n_out)})
            name = net.learned[0].name
            worst, weight = 0.0, 0.0
            for seed in range(5):
                rng = np.random.default_rng(seed)
                start = {f"{name}.W": rng.normal(0, 0.4, (n_in, n_out)), f"{name}.b": rng.normal(0, 0.2, n_out),
                         f"{name}.x_mean": np.zeros(n_in), f"{name}.x_scale": np.ones(n_in),
                         f"{name}.y_scale": np.ones(n_out)}
                values, dz = mlp_start(net_mlp, start, seed=seed)
                worst = max(worst, dz)
                weight = max(weight, float(np.max(np.abs(values[f"{name}.W1"]))))
            print(f"| {n_in} | {n_out} | {worst:.1e} | {weight:.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
