"""``tnnc estimate NET DATA --use SENSOR... -o states.csv``: virtual sensing with an extended Kalman filter.

Estimates every node temperature (and so every sensor, including those left out) from the sensors named
with ``--use`` and the data file's inputs (thesis §6.4.2). ``NET`` is a model directory from ``tnnc train``
(its fitted parameters) or a ``.thn`` file (parameters as written). Missing readings (empty cells) are
dropouts: the filter predicts through them; ``--drop START:END`` blanks the used sensors over a time
span (s) to see how the estimate holds up without them.

Noise: ``--process-noise`` is the random-walk intensity q per state in K/√s (one number, or
``NODE=VALUE`` pairs), ``--meas-noise`` the σ of each used sensor in K. ``--tune`` picks one q for all
states by maximising the innovation likelihood on this file (tune on training data, then pass the value
found with ``--process-noise`` on other files). ``--estimate-param NAME`` also estimates a constant
parameter (e.g. an unlogged ambient temperature) as a random walk.

``states.csv`` holds ``time_s``, ``T_<node>`` (estimated, in the network's temperature unit), ``<sensor>``
(estimated readings, every sensor), ``<sensor>_open`` (the open-loop model's prediction from the same
initial state) and ``T_<node>_std_K`` (the estimate's standard deviation, kelvin). The summary compares,
for every sensor the file measures, the estimate and the open-loop prediction with the measurement.
"""

from __future__ import annotations

import os
import sys

import numpy as np

from .. import plots
from ..core import CSV, IMAGE, Diagnostic, TnnError, save_figure
from ._common import add_backend, add_command, add_force_flag, add_integration, add_time_columns, check_outputs


def register(subparsers) -> None:
    p = add_command(
        subparsers, "estimate",
        "estimate all node temperatures from some sensors (extended Kalman filter, virtual sensing)", __doc__)
    p.add_argument("net", metavar="MODEL_OR_NET", help="a model directory from `tnnc train`, or a .thn network file")
    p.add_argument("data", metavar="DATA", help="data file (CSV or Parquet) with the inputs and the used sensors")
    p.add_argument("--use", nargs="+", required=True, metavar="SENSOR", help="the sensors the filter reads")
    p.add_argument("-o", "--output", required=True, metavar="STATES.csv", help="where to write the estimates")
    p.add_argument("--plot", default=None, metavar="PNG", help="plot estimate, open loop and measurement per sensor")
    add_backend(p)
    add_integration(p, default=None, default_help="the model's training integrator, else rk4")
    p.add_argument("--process-noise", nargs="+", default=None, metavar="Q|STATE=Q",
                   help="process-noise intensity in K/√s (default 0.01), one value or per state")
    p.add_argument("--meas-noise", nargs="+", default=None, metavar="S|SENSOR=S",
                   help="measurement-noise σ in K (default 0.1), one value or per sensor")
    p.add_argument("--init-std", type=float, default=None, metavar="K", help="initial-state σ in K (default 1)")
    p.add_argument("--tune", action="store_true", help="choose the process noise by maximum likelihood on this file")
    p.add_argument("--estimate-param", nargs="+", default=(), metavar="PARAM",
                   help="constant parameters estimated jointly (random walk), e.g. an unlogged ambient")
    p.add_argument("--drop", nargs="+", default=(), metavar="START:END",
                   help="blank the used sensors between START and END seconds (a simulated dropout)")
    add_time_columns(p)
    p.add_argument("--seed", type=int, default=0, help="seed for learned functions of a .thn (default 0)")
    add_force_flag(p)
    p.set_defaults(func=run)


def _noise_arg(values, flag: str, unit: str):
    """``["0.02"]`` → 0.02; ``["h1=0.05", "0.01"]`` → ``{"h1": 0.05, "*": 0.01}``."""
    if values is None:
        return None
    out: dict[str, float] = {}
    for v in values:
        name, _, num = v.rpartition("=")
        try:
            x = float(num)
        except ValueError:
            raise TnnError(Diagnostic(f"{flag}: {v!r} is not a number",
                                      hint=f"write a value in {unit} (e.g. 0.02) or NAME=VALUE")) from None
        out[name or "*"] = x
    if list(out) == ["*"]:
        return out["*"]
    return out


def _drops(spans, t: np.ndarray) -> np.ndarray:
    mask = np.zeros(t.shape, dtype=bool)
    for s in spans:
        a, sep, b = s.partition(":")
        try:
            lo, hi = float(a), float(b)
        except ValueError:
            raise TnnError(Diagnostic(f"--drop: {s!r} is not START:END in seconds",
                                      hint="e.g. --drop 2000:3000")) from None
        if not sep or hi <= lo:
            raise TnnError(Diagnostic(f"--drop: {s!r} needs START < END", hint="e.g. --drop 2000:3000"))
        mask |= (t >= lo) & (t < hi)
    return mask


def run(args) -> int:
    from ..data import from_kelvin, read_data, warning_lines, write_csv
    from ..estimation import ekf, open_loop, tune_process_noise
    from ._simulate import _load

    if args.substeps is not None and args.substeps < 1:
        raise TnnError(Diagnostic(f"--substeps must be ≥ 1, got {args.substeps}"))
    check_outputs(args, [(args.output, CSV, "-o"), (args.plot, IMAGE, "--plot")], inputs=[args.net, args.data])
    net, model, params, label, _ = _load(args.net, args.backend, args.seed)
    integrator = args.integrator
    if integrator is None and os.path.isdir(args.net):
        from ..fit import load_model

        integrator = load_model(args.net).meta.get("config", {}).get("integrator")
    integrator = integrator or "rk4"
    sensors = [s.name for s in net.sensors]
    for s in args.use:
        if s not in sensors:
            raise TnnError(Diagnostic(f"--use: unknown sensor {s!r}",
                                      hint=f"the network's sensors are: {', '.join(sensors)}"))
    (exp,) = read_data(net, [args.data], time_col=args.time_col, dt=args.dt, time_unit=args.time_unit,
                       require_outputs=False, split_gaps=False)  # one filter over the file: a long gap is an error
    for n in exp.notes:
        print(f"note: {n}", file=sys.stderr)
    for w in warning_lines([exp]):
        print(w, file=sys.stderr)
    Y = np.array(exp.outputs, dtype=float)
    dropped = _drops(args.drop, exp.t)
    use_idx = [sensors.index(s) for s in args.use]
    for j in use_idx:
        Y[dropped, j] = np.nan
    opts = dict(meas_noise=_noise_arg(args.meas_noise, "--meas-noise", "K"), init_std=args.init_std,
                augment=list(args.estimate_param), integrator=integrator, substeps=args.substeps)
    q = _noise_arg(args.process_noise, "--process-noise", "K/√s")
    if args.tune:
        best, scores = tune_process_noise(model, params, exp.inputs, Y, exp.dt, args.use, **opts)
        print("process noise by likelihood: " + ", ".join(f"q={k:g}: {v:.1f}" for k, v in scores.items()))
        print(f"  chosen q = {best:g} K/√s")
        q = best
    res = ekf(model, params, exp.inputs, Y, exp.dt, args.use, process_noise=q, t=exp.t, **opts)
    _, y_open = open_loop(model, params, exp.inputs, exp.dt, res.states[0], integrator, args.substeps)

    cols: dict[str, np.ndarray] = {}
    kelvin = []
    for k, name in enumerate(res.state_names):
        key = f"T_{name}" if name in net.node_names else name.replace(".", "_")
        cols[key] = res.states[:, k]
        kelvin.append(key)
    for k, s in enumerate(sensors):
        cols[s] = res.outputs[:, k]
        cols[f"{s}_open"] = y_open[:, k]
        kelvin += [s, f"{s}_open"]
    for j, name in enumerate(res.param_names):
        cols[name] = res.params[:, j]
    for k, name in enumerate(res.state_names):
        key = f"T_{name}" if name in net.node_names else name.replace(".", "_")
        cols[f"{key}_std_K"] = res.std[:, k]
    write_csv(args.output, exp.t, cols, net.temperature_unit, kelvin=kelvin)

    print(f"estimated {label} on {exp.path}: {exp.n_steps} samples of {exp.dt:g} s, using {', '.join(args.use)} "
          f"({args.backend}, {integrator})")
    if dropped.any():
        print(f"  dropout: {int(dropped.sum())} samples without {', '.join(args.use)}")
    for s, v in res.nis.items():
        print(f"  {s}: normalised innovation² {v:.2f} (≈ 1 when the noise levels fit the data)")
    for j, name in enumerate(res.param_names):
        v = res.params[-1, j]
        shown = from_kelvin(np.asarray(v), net.temperature_unit) if net.param(name).role == "temperature" else v
        print(f"  {name}: final estimate {float(shown):.5g}")
    print(f"  {'sensor':<12} {'role':<10} {'EKF MAE':>9} {'open MAE':>9}")
    for k, s in enumerate(sensors):
        meas = exp.outputs[:, k]
        ok = np.isfinite(meas)
        if not ok.any():
            continue
        e1 = np.mean(np.abs(res.outputs[ok, k] - meas[ok]))
        e0 = np.mean(np.abs(y_open[ok, k] - meas[ok]))
        role = "used" if s in args.use else "estimated"
        print(f"  {s:<12} {role:<10} {e1:8.3f}K {e0:8.3f}K")
    print(f"wrote {args.output}")
    if args.plot:
        save_figure(plots.filter_estimate(net, exp, res, y_open, dropped, label), args.plot, dpi=110)
        print(f"wrote {args.plot}")
    return 0
