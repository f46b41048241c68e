"""``tnnc simulate NET --data CSV -o OUT.csv``: a free-run simulation driven by a data file's inputs.

``NET`` is a ``.thn`` file (its parameters at their written values, learned functions untrained, i.e. at
their nominal values) or a model directory written by ``tnnc train`` (its fitted parameters).

The inputs are read from the data file's columns (the ``column "..."`` of each ``input``), on the
file's step or ``--dt``. The initial state follows one rule (``--init``, :mod:`tnn_dsl.fit.initial`): with
``estimate`` (the default) it is fitted to the sensor readings of a burn-in at the file's start (``--burn-in``
seconds, else a tenth of the file; its length is printed), or, for a file a model was trained on, it is the state
fitted in training, so the run continues exactly; ``filter`` runs an extended Kalman filter over the burn-in;
``steady`` is the steady state of the first inputs (thesis §4.5: what the case-study data starts from), with a
warning when a sensor starts more than 1 K away; ``measured`` moves every sensed node of that steady state (and its
lag state) to the first reading. A file without sensor columns starts at the steady state.

``OUT.csv`` holds ``time_s`` and one column per sensor (the sensor's name) in the network's temperature
unit; ``--states`` adds every state (``T_<node>``; ``<sensor>_lag`` for a lagged sensor). ``--plot`` draws
measured against simulated for each sensor that the data file measures, and the inputs.
"""

from __future__ import annotations

import os
import sys

import numpy as np

from .. import plots
from ..core import CSV, IMAGE, Diagnostic, TnnError, save_figure
from ._common import (
    add_backend,
    add_command,
    add_force_flag,
    add_init,
    add_integration,
    add_time_columns,
    check_outputs,
)


def register(subparsers) -> None:
    p = add_command(subparsers, "simulate", "simulate a network (or a trained model) on a data file's inputs", __doc__)
    p.add_argument("net", metavar="NET", help="a .thn network file, or a model directory from `tnnc train`")
    p.add_argument("--data", required=True, metavar="CSV", help="data file with the input columns (CSV or Parquet)")
    p.add_argument("-o", "--output", required=True, metavar="OUT.csv", help="where to write the simulated sensors")
    add_backend(p)
    p.add_argument("--torch-compile", action="store_true",
                   help="torch backend: compile the rollout with torch.compile (pays off on long runs)")
    add_integration(p)
    add_time_columns(p)
    add_init(p)
    p.add_argument("--states", action="store_true", help="also write every state (node temperatures)")
    p.add_argument("--plot", default=None, metavar="OUT.png", help="plot measured vs simulated")
    p.add_argument("--seed", type=int, default=0, help="seed for initialising learned functions of a .thn (default 0)")
    add_force_flag(p)
    p.set_defaults(func=run)


# ---------------------------------------------------------------------------------------------


def _load(net_arg: str, backend: str, seed: int):
    """→ (network, compiled model, backend params, label, what a trained model knows for a free run)."""
    if os.path.isdir(net_arg):
        from ..fit import load_model

        tm = load_model(net_arg)
        model = tm.compiled(backend)
        return tm.network, model, tm.backend_params(backend), f"model {net_arg}", tm.free_run_context()
    from ..compiler import compile as compile_network
    from ..lang import load

    net = load(net_arg)
    from ..lang import magnitude_warnings

    for w in magnitude_warnings(net):
        print(w.format(), file=sys.stderr)
    model = compile_network(net, backend=backend, dtype="float64")
    return net, model, model.init_params(seed=seed), net_arg, {}


def run(args) -> int:
    from ..data import read_data, warning_lines, write_csv
    from ..fit import free_run

    if args.substeps is not None and args.substeps < 1:
        raise TnnError(Diagnostic(f"--substeps must be ≥ 1, got {args.substeps}"))
    check_outputs(args, [(args.output, CSV, "-o"), (args.plot, IMAGE, "--plot")], inputs=[args.net, args.data])
    net, model, params, label, known = _load(args.net, args.backend, args.seed)
    if args.torch_compile:
        if args.backend != "torch":
            raise TnnError(Diagnostic("--torch-compile applies to the torch backend only",
                                      hint="add --backend torch (JAX rollouts are always compiled)"))
        model.torch_compile = True
    (exp,) = read_data(net, [args.data], time_col=args.time_col, dt=args.dt, time_unit=args.time_unit,
                       require_outputs=False, split_gaps=False)
    for n in exp.notes:
        print(f"note: {n}", file=sys.stderr)
    for w in warning_lines([exp]):
        print(w, file=sys.stderr)
    run = free_run(model, params, exp, args.init, integrator=args.integrator, substeps=args.substeps,
                   burn_in_s=args.burn_in, check=True, **known)
    states, y = run.states, run.y
    for n in run.init.notes:
        print(n, file=sys.stderr)

    cols: dict[str, np.ndarray] = {s.name: y[:, k] for k, s in enumerate(net.sensors)}
    if args.states:
        for k, name in enumerate(model.state_names):
            key = f"T_{name}" if name in net.node_names else name.replace(".", "_")
            if key in cols:
                key = f"state_{key}"
            cols[key] = states[:, k]
    write_csv(args.output, exp.t, cols, net.temperature_unit)

    unit = {"degC": "°C", "K": "K", "degF": "°F"}[net.temperature_unit]
    print(f"simulated {label} on {exp.path}: {exp.n_steps} steps of {exp.dt:g} s ({args.backend}, {args.integrator})")
    measured = np.isfinite(exp.outputs)
    measured[: run.burn_in] = False  # the burn-in the initial state was estimated on is not scored
    after = f", after the {run.burn_in}-sample burn-in" if run.burn_in else ""
    for k, s in enumerate(net.sensors):
        if measured[:, k].any():
            err = y[measured[:, k], k] - exp.outputs[measured[:, k], k]
            print(f"  {s.name}: MAE {np.mean(np.abs(err)):.3f} K, max {np.max(np.abs(err)):.3f} K "
                  f"(vs column {exp.output_columns[k]!r}{after})")
    print(f"wrote {args.output} (temperatures in {unit})")
    if args.plot:
        save_figure(plots.simulation(net, exp, y, label), args.plot, dpi=110)
        print(f"wrote {args.plot}")
    return 0
