"""Model predictive control of the case-study cooler (thesis §6.4.3), made real.

The plant is the true system (``networks/peltier_heatpipe/truth.thn``: the hidden, temperature- and
u1-dependent heat pipe); the controller plans with the engineer's nominal model
(``networks/peltier_heatpipe/nominal.thn``, constant heat pipe) or, with ``--model DIR``, a trained model
directory (e.g. M2 from ``examples/thesis_case_study.py``). The controller manipulates the Peltier
current I ∈ [0, 3] A every 10 s over a 300-s horizon to track a set-point on T_out; the heat-pipe input u1
steps from 0.5 to 0.8 at 60 min as an unmeasured disturbance. Gradients of the tracking cost come from
automatic differentiation through the model's rollout; the bounds are enforced by projection (L-BFGS-B).

    .venv/bin/python examples/mpc_case_study.py [--backend jax|torch] [--plot docs/img/mpc_case_study.png]

Checks (exit 1 if violated): in the 5 minutes before the controller's horizon first reaches a set-point
change, before the disturbance and before the end (the settled windows), |T_out − r| < 0.1 K; the applied
current never leaves [0, 3] A.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import tnn_dsl  # noqa: E402
from tnn_dsl.control.mpc import MPC, closed_loop  # noqa: E402

C0 = 273.15


def scenario(minutes: float = 100.0):
    """Inputs (N, 5) SI in the order I, u1, Ta, Tf1, Tf2 and the set-point (N,) K, 1-s grid."""
    N = int(minutes * 60)
    t = np.arange(N)
    U = np.tile([0.0, 0.5, C0 + 22.0, C0 + 25.0, C0 + 25.0], (N, 1))
    U[t >= 60 * 60, 1] = 0.8                       # unmeasured disturbance: heat-pipe input steps
    r = np.full(N, C0 + 24.3)
    r[t >= 25 * 60] = C0 + 23.8
    r[t >= 75 * 60] = C0 + 24.2
    # settled windows end where the controller first sees a set-point change (its horizon previews
    # it), where the disturbance hits, and at the end; (end, previewed?)
    changes = [(25 * 60, True), (60 * 60, False), (75 * 60, True), (N, False)]
    return U, r, changes


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backend", choices=("jax", "torch"), default="jax")
    ap.add_argument("--model", default=None, help="controller model directory (default: nominal.thn untrained)")
    ap.add_argument("--minutes", type=float, default=100.0)
    ap.add_argument("--horizon", type=int, default=30, help="intervals of 10 s (default 30)")
    ap.add_argument("--plot", default=str(ROOT / "docs" / "img" / "mpc_case_study.png"))
    args = ap.parse_args(argv)

    plant = tnn_dsl.compile(tnn_dsl.load(str(ROOT / "networks/peltier_heatpipe/truth.thn")), "jax")
    pp = plant.init_params()
    if args.model:
        tm = tnn_dsl.load_model(args.model)
        ctrl, cp, label = tm.compiled(args.backend), tm.backend_params(args.backend), f"model {args.model}"
    else:
        ctrl = tnn_dsl.compile(tnn_dsl.load(str(ROOT / "networks/peltier_heatpipe/nominal.thn")), args.backend)
        cp, label = ctrl.init_params(), "nominal.thn"
    mpc = MPC(ctrl, cp, "T_out", {"I": (0.0, 3.0)}, horizon=args.horizon, dt=10.0, move_penalty=0.05)
    U, r, changes = scenario(args.minutes)
    t0 = time.perf_counter()
    last = [0]

    def progress(k, n, y, u):
        if k - last[0] >= 600 or k == n:
            last[0] = k
            print(f"  t = {k / 60:5.1f} min  T_out = {y - C0:6.3f} °C  I = {u[0]:.3f} A", flush=True)

    print(f"MPC ({label}, {args.backend}) on the true plant, {args.minutes:g} min")
    res = closed_loop(plant, pp, mpc, U, r, progress=progress)
    wall = time.perf_counter() - t0
    I = res.u[:, 0]
    ok_bounds = bool(np.all(I >= 0.0) and np.all(I <= 3.0))
    worst = []
    preview = int(mpc.H * mpc.dt)
    for end, previewed in changes:
        end = min(end, len(r)) - (preview if previewed else 0)
        w = slice(end - 300, end)
        worst.append(float(np.max(np.abs(res.y[w] - res.r[w]))))
    print(f"solves: {len(res.solve_s)}, {np.mean(res.solve_s) * 1e3:.0f} ms each (mean), "
          f"{np.mean(res.iterations):.1f} L-BFGS-B iterations; wall {wall:.0f} s")
    print("max |T_out − r| over the 5 min before each set-point change is previewed, before the disturbance "
          "and before the end: "
          + ", ".join(f"{w * 1e3:.1f} mK" for w in worst))
    print(f"current within [0, 3] A: {ok_bounds} (min {I.min():.4f}, max {I.max():.4f} A)")
    if args.plot:
        plot(args.plot, res, label, changes)
        print(f"wrote {args.plot}")
    good = ok_bounds and max(worst) < 0.1
    print("PASS" if good else "FAIL")
    return 0 if good else 1


def plot(path, res, label, changes):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tm = res.t / 60
    fig, ax = plt.subplots(3, 1, figsize=(10, 7.5), sharex=True, gridspec_kw={"height_ratios": [2.2, 1.2, 1]})
    ax[0].plot(tm, res.r - C0, "k--", lw=1.1, label="set-point r")
    ax[0].plot(tm, res.y - C0, "C0", lw=1.3, label="T_out (true plant)")
    ax[0].set_ylabel("T_out [°C]")
    ax[0].legend(fontsize=8)
    ax[0].set_title(f"gradient-based MPC, controller model: {label}; plant: truth.thn", fontsize=9, loc="left")
    ax[1].step(tm, res.u[:, 0], where="post", color="C3", lw=1.1, label="I (applied)")
    ax[1].axhline(0, color="0.5", lw=0.8, ls=":")
    ax[1].axhline(3, color="0.5", lw=0.8, ls=":", label="bounds")
    ax[1].set_ylabel("I [A]")
    ax[1].legend(fontsize=8)
    ax[2].step(tm, res.u[:, 1], where="post", color="C2", lw=1.1,
               label="u1 (heat-pipe input; the nominal model ignores it)")
    ax[2].plot(tm, res.d * 1e3 / 100, color="C4", lw=0.9, label="output disturbance estimate d [×100 mK]")
    ax[2].set_ylabel("u1 [1]")
    ax[2].set_xlabel("time [min]")
    ax[2].legend(fontsize=8)
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
