"""``tnnc inspect MODEL [--plot DIR] [--json FILE]``: what a trained model learned.

Prints the fitted value of every free parameter next to its nominal (as written) value, the training
summary (data, metrics, why training stopped), the estimates with their standard errors (the coefficient table
of the fit's objective: estimate, std. error, t, p, dF/dPar, in SI and the file's units; log-likelihood, AIC,
BIC) and, for each learned function, its inputs with the range
they covered in training. ``--plot DIR`` writes one PNG per learned function: each target plotted
against each input over the range that input saw in training, the other inputs held at the middle of
their ranges (for a positive parameter target: its value; for a flow or heat load: the learned
correction in W, or the flow itself for ``replace``).
"""

from __future__ import annotations

import json
import math
import os
import sys

import numpy as np

from ._common import add_command, add_force_flag, check_outputs, write_json


def register(subparsers) -> None:
    p = add_command(
        subparsers, "inspect",
        "fitted vs nominal parameters and the learned functions of a trained model", __doc__)
    p.add_argument("model", metavar="MODEL", help="a model directory written by `tnnc train`")
    p.add_argument("--plot", default=None, metavar="DIR", help="write one plot per learned function into DIR")
    p.add_argument("--json", default=None, metavar="FILE", help="write the parameter table as JSON ('-' for stdout)")
    p.add_argument("--all", action="store_true", help="list every constant parameter, not only the free ones")
    add_force_flag(p)
    p.set_defaults(func=run)


def parameter_table(tm, all_params: bool = False) -> list[dict]:
    """Rows ``{name, role, nominal, fitted, change_pct, free}`` (SI; temperatures in K) and ``unit``,
    ``nominal_shown``, ``fitted_shown`` (the file's units): see :meth:`tnn_dsl.fit.TrainedModel.parameter_table`."""
    return tm.parameter_table(all_params)


def learned_summary(tm) -> list[dict]:
    """Per learned function: kind, targets, inputs and the training range of each input."""
    out = []
    norm = tm.meta.get("normalisation", {})
    for fn in tm.network.learned:
        xm = np.asarray(tm.params.get(f"{fn.name}.x_mean", np.zeros(len(fn.inputs))), dtype=float)
        xs = np.asarray(tm.params.get(f"{fn.name}.x_scale", np.ones(len(fn.inputs))), dtype=float)
        info = norm.get(fn.name, {})
        lo = np.asarray(info.get("x_min", (xm - xs).tolist()), dtype=float)
        hi = np.asarray(info.get("x_max", (xm + xs).tolist()), dtype=float)
        out.append({"name": fn.name, "kind": fn.kind, "targets": [t.name for t in fn.targets],
                    "target_kinds": [t.kind for t in fn.targets], "inputs": [a.name for a in fn.inputs],
                    "input_kinds": [a.kind for a in fn.inputs], "x_min": lo.tolist(), "x_max": hi.tolist(),
                    "frozen": fn.frozen, "replace": fn.replace})
    return out


def learned_values(tm, fn, X: np.ndarray) -> np.ndarray:
    """Target values ``(M, n_targets)`` of learned function ``fn`` at inputs ``X (M, n_in)`` (SI)."""
    from ..compiler import apply_learned as apply
    from ..compiler import get_xp, target_value

    xp = get_xp("numpy")
    arrays = {k.split(".", 1)[1]: v for k, v in tm.params.items() if k.startswith(fn.name + ".")}
    z = np.asarray(apply(xp, fn, arrays, X), dtype=float).reshape(len(X), -1)
    ysc = np.asarray(arrays.get("y_scale", np.ones(z.shape[1])), dtype=float)
    cols = []
    for i, t in enumerate(fn.targets):
        if t.kind == "param":
            p = next((q for q in tm.network.params if q.name == t.name), None)
            from ..ir import POSITIVE_ROLES

            positive = p is not None and p.role in POSITIVE_ROLES
            nominal = float(p.value) if p is not None and p.value is not None else (1.0 if positive else 0.0)
            cols.append(np.asarray(target_value(xp, z[:, i], nominal, positive, ysc[i]), dtype=float))
        else:
            cols.append(ysc[i] * z[:, i])
    return np.stack(cols, axis=1)


def run(args) -> int:
    from .. import plots
    from ..core import JSON, PLOT_DIR, save_figure, to_jsonable
    from ..fit import load_model

    check_outputs(args, [(args.json, JSON, "--json"), (args.plot, PLOT_DIR, "--plot")], inputs=[args.model])
    tm = load_model(args.model)
    meta = tm.meta
    rows = parameter_table(tm, args.all)
    out = sys.stdout if args.json != "-" else sys.stderr
    print(f"model {args.model}: network {tm.network.name}, trained with {meta.get('backend', '?')} "
          f"(rollout {meta.get('rollout', '?')}, stopped: {meta.get('stopped', '?')})", file=out)
    m = meta.get("metrics", {})
    for part in ("train", "validation"):
        if part in m and isinstance(m[part], dict):
            r = m[part]
            print(f"  {part:<10} MAE {r.get('mae') or math.nan:.4g} K  max {r.get('max_error') or math.nan:.4g} K",
                  file=out)
    if rows:
        print(f"\n{'parameter':<22} {'nominal':>26} {'fitted':>26} {'change':>9}", file=out)
        from ..fit.model_files import format_row

        for r in rows:
            print(format_row(r), file=out)
    if meta.get("estimation"):
        from ..estimation import estimation_summary

        print("\n" + estimation_summary(meta["estimation"]), file=out)
    diag = meta.get("diagnosis") or {}
    if diag.get("uncertainty"):  # a model written by `tnnc diagnose --model`: the doctor's standard errors
        from ..doctor.results import uncertainty_text

        print(f"\nthe model doctor's verdict: {diag.get('verdict', '?')}", file=out)
        for line in uncertainty_text(diag["uncertainty"], bool(diag.get("mlp_from_fit"))):
            print(line if line.startswith("  ") else "  " + line, file=out)
    summ = learned_summary(tm)
    for s in summ:
        fn = next(f for f in tm.network.learned if f.name == s["name"])
        extra = " (frozen)" if s["frozen"] else ""
        print(f"\nlearned {s['name']}: {', '.join(s['targets'])} as {s['kind']}({', '.join(s['inputs'])}){extra}",
              file=out)
        for a, k, lo, hi in zip(s["inputs"], s["input_kinds"], s["x_min"], s["x_max"]):
            unit = "K" if k == "node" else ""
            print(f"  input {a:<12} trained over [{lo:.5g}, {hi:.5g}] {unit}", file=out)
        if s["inputs"]:
            mid = (np.asarray(s["x_min"]) + np.asarray(s["x_max"])) / 2
            corners = np.stack([np.asarray(s["x_min"]), mid, np.asarray(s["x_max"])])
            vals = learned_values(tm, fn, corners)
            for j, t in enumerate(s["targets"]):
                print(f"  {t:<18} at low/mid/high inputs: {vals[0, j]:.5g} / {vals[1, j]:.5g} / {vals[2, j]:.5g}",
                      file=out)
        else:
            vals = learned_values(tm, fn, np.zeros((1, 0)))
            for j, t in enumerate(s["targets"]):
                print(f"  {t:<18} = {vals[0, j]:.6g}", file=out)
    for w in meta.get("warnings", []) or []:
        print(f"warning: {w}", file=out)
    if args.json:
        write_json(args.json, json.dumps(to_jsonable({"parameters": rows, "learned": summ, "metrics": m,
                                                       "estimation": meta.get("estimation")}), indent=2))
    if args.plot:
        os.makedirs(args.plot, exist_ok=True)
        for s in summ:
            fn = next(f for f in tm.network.learned if f.name == s["name"])
            path = os.path.join(args.plot, f"{s['name']}.png")
            save_figure(plots.learned_function(s, lambda X, fn=fn: learned_values(tm, fn, X)), path, dpi=100)
            print(f"wrote {path}", file=out)
    return 0
