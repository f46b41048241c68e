"""Linear or MLP? The model doctor's last step for the dependences it accepted (issue 6, step 4: "the chosen
``learn`` clause(s), linear or mlp, as the evidence says").

The forward selection fits each dependence as ``linear(v…)`` (cheap, exactly null at zero, a score test).
When the extended model's held-out residual is still not white (every sensor and both whiteness tests taken
together at a family-wise 5 %: :func:`tnn_dsl.analysis.residuals.all_white`), the law may be curved in its variables.
The evidence is then a fit, not a guess: the extension is trained twice with the shared trainer
(``tnn_dsl.train``, same data, same options, same time limit) — once as written, once with every ``linear``
function the doctor added turned into ``mlp(…; hidden = [8], activation = tanh)`` (:func:`mlp_variant`, an IR
edit; the user's own ``learn`` clauses are left alone) — and the
MLP is kept only if it pays on the held-out data by the doctor's own test (Diebold–Mariano on the
held-out squared errors with a charge for the extra parameters, p < ``P_ACCEPT``, and a held-out MAE gain of
at least ``MIN_GAIN``).

**From the doctor's fit (the doctor's default).** The MLP starts as the doctor's fitted linear law
(:func:`values_for_extension` puts the doctor's values under the extension's names, :func:`mlp_start` makes an MLP
that computes that law) and only its weights are trained, every other value held at the doctor's fit, by the
trainer's L-BFGS polish; the linear law is the doctor's fit itself, free-run on the held-out files as the trainer
runs any model. The MLP contains the linear law it starts from, so whatever it gains on the held-out data is the
shape of the law — the nested comparison a statistician makes, and one training instead of two. Measured (issue 18,
2026-12-06, BENCHMARKS.md): from nominal values the case study's MLP ended at 3.8 mK held out, above the doctor's
linear fit (3.0 mK), so the check could not have chosen it whatever the law's shape; from the fit it reaches 2.40 mK
against the law's 3.00 mK (p = 0.036; scored without the held-out files' burn-in, as the doctor scores them) in
6.0–6.1 s of training, stopping on the end of the training file (:data:`EARLY_STOP_FRACTION`; the MLP from nominal
values: 17.0–19.4 s): the heat
pipe's resistances are linear in ``u1`` in the truth, and the linear law's output passes through the positive
transform ``nominal·pos1(1 + z)``, which bends it where ``u1`` makes them small. On TCLab's ``U12 ~ T(h1)`` the MLP
from the fit does not pay: it ends at the law's own 0.6543 K (p = 1; 0.6498 K, p = 0.14, while its training
stopped on the held-out file, a validation-only run).

Where the MLP is chosen the result holds the trained model (``model``): the doctor hands it out and saves it
(:mod:`.saved_model`, ``tnnc diagnose --model``), so the gain it reports can be had again from what it wrote.

**From nominal values** (``compare`` without ``start``; the doctor falls back to it where an extension's function
has no counterpart in its fit): both variants start from the same nominal values and go through the same trainer.
The doctor keeps an MLP only if it also beats its own fit (its linear law converged) by ``MIN_GAIN``; so it trains
the MLP first, alone, and the linear clauses only when the MLP clears that bar (``compare(..., bar=)``): otherwise
the trained linear law could not change the answer.

Each training runs the trainer's fixed schedule (its default epochs, early stopping and L-BFGS iterations), so the
answer does not depend on the machine — unless the time limit (``mlp_time``, 60 s by default) cuts a training
short. A cut only matters when it could change the answer: an MLP stopped early that does not pay might with its
whole schedule, a linear law stopped early makes an MLP look better than it is (a training is cut when the limit
stops any of its routes, the single-shooting fit the trainer compares its windowed fit with included:
``fit.training._best_route``). Then the check says it did not
decide (``decided: False``, the linear law kept, the reason naming the cut training and the limit to raise).
Measured on the case study (``python benchmarks/bench_diagnose.py --threads 1,2`` on a contended host,
2026-11-28): one training at a time the MLP finished its schedule in 54 s (p = 0.062); two side by side it was
stopped at 60 s (p = 0.29) — the same data, two answers, both reported as decided before this.
"""

from __future__ import annotations

import math
import time
from typing import Any, Callable, Mapping

import numpy as np

from ..analysis import held_out_test
from ..compiler.backends.adapter import lean_programs
from ..ir import Network
from .selection import MIN_GAIN, P_ACCEPT
from .threads import side_by_side, two_at_once

HIDDEN = 8

EARLY_STOP_FRACTION = 0.3
"""The end of each training file that a check's training validates on (its early stopping and the iterate it keeps:
the trainer's ``val_fraction``); the rest of the file is what it trains on. The held-out files are read only to judge
the two laws, never to steer a training: they are the ones the test's p-value is computed on, and on real data they
may be files kept for validation only (``examples/diagnose_real_data.py`` holds TCLab's closed-loop run out so).
Before 2026-12-06 the check's training stopped on the held-out files themselves; the case study's MLP then scored
2.030 mK against the law's 2.995 mK (p = 0.0077), a number its own stopping had chosen (BENCHMARKS.md, "The MLP
check's stopping rule, three ways")."""


def mlp_variant(net: Network, targets: set[str]) -> tuple[Network, int]:
    """``net`` with every ``linear`` learned function whose targets are all in ``targets`` (keys of
    :meth:`Network.learned_targets`: ``R_hp1``, ``Q[hx2]``; the doctor's own functions) turned into an MLP with
    one hidden layer of ``HIDDEN`` tanh units. Returns ``(new network, number of functions changed)``."""
    learned, n = [], 0
    for fn in net.learned:
        keys = {f"Q[{t.name}]" if t.kind == "heat_load" else t.name for t in fn.targets}
        if fn.kind == "linear" and keys <= targets:
            fn = fn.model_copy(update={"kind": "mlp", "hidden": [HIDDEN], "activation": "tanh"})
            n += 1
        learned.append(fn)
    return net.model_copy(update={"learned": learned}), n


_MONOMIAL_KINDS = ("const", "linear", "poly")
"""Learned-function kinds that are sums of monomials of the normalised inputs, mapped term by term."""


def _monomials(fn, ins: list) -> list[tuple]:
    """The terms of a ``linear`` or ``poly`` function's weight rows (``W``), each the sorted tuple of the variables it
    multiplies (``ins``: the function's inputs as ``(kind, name)``); none for ``const``."""
    from ..compiler.learned import monomial_index

    if fn.kind == "const":
        return []
    if fn.kind == "linear":
        return [(v,) for v in ins]
    return [tuple(sorted(ins[i - 1] for i in row if i > 0)) for row in monomial_index(len(ins), int(fn.degree or 2))]


def values_for_extension(ext: Network, fitted_net: Network,
                         params: Mapping[str, np.ndarray]) -> dict[str, np.ndarray] | None:
    """The doctor's fitted values (``params``: its engine's values, SI, for the network it fitted, ``fitted_net``) by
    the names of the extension it printed (``ext``): physical parameters by name; a learned function's arrays by
    what they mean, not by its name (the doctor fits its dependences in functions of its own, ``dx_params``; the
    extension names them anew and groups the targets by their variables). For each target of an extension's
    function, the fitted function holding that target gives its bias, its weight for each term (a variable, or for a
    ``poly`` a square or product of them, matched by the variables it multiplies; 0 for a term it does not have) and
    its output scale; each input's statistics come from a fitted function reading it (the mid-range and half-range of
    the same training rows in every function). ``const``, ``linear`` and ``poly`` functions are mapped so (the doctor
    fits a round's dependences as a ``poly`` when the round also tries their curvature; a curved term it did not
    accept is zero there); another kind only where the fitted network has the same function (name, kind, inputs,
    targets). Returns None where an extension's function has no counterpart, or the fit uses a term the extension's
    function cannot hold (then there is no fit to start from)."""
    fitted_fns = {fn.name: fn for fn in fitted_net.learned}
    out = {k: np.asarray(v, float) for k, v in params.items() if k.split(".", 1)[0] not in fitted_fns}
    holder = fitted_net.learned_targets()

    def arr(fn, name):
        v = params.get(f"{fn.name}.{name}")
        return None if v is None else np.asarray(v, float)

    for fn in ext.learned:
        keys = [f"Q[{t.name}]" if t.kind == "heat_load" else t.name for t in fn.targets]
        ins = [(i.kind, i.name) for i in fn.inputs]
        same = fitted_fns.get(fn.name)
        if (same is not None and same.kind == fn.kind and [(i.kind, i.name) for i in same.inputs] == ins
                and [f"Q[{t.name}]" if t.kind == "heat_load" else t.name for t in same.targets] == keys):
            names = [k for k in params if k.startswith(fn.name + ".")]
            out.update({k: np.asarray(params[k], float) for k in names})
            continue
        if fn.kind not in _MONOMIAL_KINDS or any(k not in holder for k in keys):
            return None
        monos = _monomials(fn, ins)  # the extension's terms, each a sorted tuple of its variables
        W, b = np.zeros((len(monos), len(keys))), np.zeros(len(keys))
        x_mean, x_scale, y_scale = np.zeros(len(ins)), np.ones(len(ins)), np.ones(len(keys))
        found = [False] * len(ins)
        for j, key in enumerate(keys):
            g, col = holder[key]
            if g.kind not in _MONOMIAL_KINDS:
                return None
            bias = arr(g, "c" if g.kind == "const" else "b")
            if bias is None:
                return None
            b[j] = bias.reshape(-1)[col]
            ysc = arr(g, "y_scale")
            y_scale[j] = 1.0 if ysc is None else ysc.reshape(-1)[col]
            g_ins = [(i.kind, i.name) for i in g.inputs]
            Wg = arr(g, "W")
            weights = {} if g.kind == "const" or Wg is None else {
                m: float(Wg[row, col]) for row, m in enumerate(_monomials(g, g_ins))}
            if any(w != 0.0 and m not in monos for m, w in weights.items()):
                return None  # a term the fit uses that the extension's function cannot hold
            for row, m in enumerate(monos):
                W[row, j] = weights.get(m, 0.0)
            for r, var in enumerate(ins):
                if var not in g_ins:
                    continue
                q = g_ins.index(var)
                xm, xs = arr(g, "x_mean"), arr(g, "x_scale")
                if xm is not None and xs is not None:
                    x_mean[r], x_scale[r], found[r] = xm[q], xs[q], True
        if not all(found):
            return None
        if fn.kind == "const":
            out[f"{fn.name}.c"] = b
        else:
            out.update({f"{fn.name}.W": W, f"{fn.name}.b": b, f"{fn.name}.x_mean": x_mean,
                        f"{fn.name}.x_scale": x_scale})
        out[f"{fn.name}.y_scale"] = y_scale
    return out


PAIR_SLOPES = (0.05, 0.1)
"""Input weights (per unit of the normalised input along one of the linear law's directions) of the two hidden units
that carry that direction in an MLP started as a linear law (:func:`mlp_start`): ``tanh`` is nearly linear there and
the pair's output weights cancel each other's cubic terms (``tanh(a·u) ≈ a·u − (a·u)³/3``), so the MLP computes the
law to within 1e-6 of its raw output over the data's range for one or two inputs and 4e-5 for up to six, with output
weights up to 47 (``python benchmarks/check_mlp_start.py``; 1.4e-13 on the case study's one input)."""


def mlp_start(net_mlp: Network, start: Mapping[str, np.ndarray], seed: int = 0,
              n_points: int = 4000) -> tuple[dict[str, np.ndarray], float]:
    """The MLP variant's starting values from the doctor's fit of the linear extension: ``start`` (its values by
    the linear extension's parameter names, SI) with each linear function that :func:`mlp_variant` turned into an
    MLP replaced by an MLP that computes the same raw output ``z = xn·W + b``. The MLP keeps the linear function's
    input statistics (``x_mean``, ``x_scale``, ``y_scale``); of its one hidden layer, two units per direction of the
    law (the left singular vectors of ``W``, ``r`` of them) look along that direction with the weights
    :data:`PAIR_SLOPES`, the other units are drawn as the trainer draws them (Glorot-uniform, ``seed``), every bias 0;
    the output layer is fitted by least squares to the law over the normalised inputs' box ``[-1, 1]^n`` (the
    training data's range: the statistics are its mid-range and half-range; a grid of 41 points per input for one or
    two inputs, else ``n_points`` drawn uniformly). Returns ``(values, largest |Δz|)``, the difference between the
    MLP and the law at ``n_points`` other points of the box (raw output: 1 is the target's nominal scale)."""
    from ..compiler.learned import apply_normalised, init_arrays

    out = dict(start)
    rng = np.random.default_rng(seed)
    worst = 0.0
    for fn in net_mlp.learned:
        W, b = start.get(f"{fn.name}.W"), start.get(f"{fn.name}.b")
        if fn.kind != "mlp" or W is None or b is None or np.ndim(W) != 2 or f"{fn.name}.W0" in start:
            continue
        if len(fn.hidden) != 1 or fn.activation != "tanh":
            raise ValueError(f"mlp_start: {fn.name} is mlp(hidden = {list(fn.hidden)}, {fn.activation}); the MLP check "
                             f"makes one hidden layer of tanh units")
        W, b = np.asarray(W, float), np.asarray(b, float)
        n_in, n_out = W.shape
        h = int(fn.hidden[0])
        arrays = init_arrays(fn, n_in, n_out, rng)
        u, sv, _ = np.linalg.svd(W, full_matrices=False)
        r = int(np.sum(sv > 1e-12 * sv.max())) if sv.size and sv.max() > 0 else 0
        slopes = PAIR_SLOPES if 2 * r <= h else PAIR_SLOPES[:1]
        for d in range(min(r, h // len(slopes))):
            for m, a in enumerate(slopes):
                arrays["W0"][:, len(slopes) * d + m] = a * u[:, d]
        if n_in <= 2:
            g = np.linspace(-1.0, 1.0, 41)
            X = np.stack(np.meshgrid(*([g] * n_in)), axis=-1).reshape(-1, n_in)
        else:
            X = rng.uniform(-1.0, 1.0, size=(n_points, n_in))

        def hidden(x: np.ndarray) -> np.ndarray:
            return np.concatenate([np.tanh(x @ arrays["W0"] + arrays["b0"]), np.ones((len(x), 1))], axis=1)

        coef = np.linalg.lstsq(hidden(X), X @ W + b, rcond=None)[0]
        arrays["W1"], arrays["b1"] = coef[:-1], coef[-1]
        for name in ("x_mean", "x_scale", "y_scale"):
            if f"{fn.name}.{name}" in start:
                arrays[name] = np.asarray(start[f"{fn.name}.{name}"], float)
        X_check = rng.uniform(-1.0, 1.0, size=(n_points, n_in))
        worst = max(worst, float(np.max(np.abs(apply_normalised(np, fn, arrays, X_check) - (X_check @ W + b)))))
        out.pop(f"{fn.name}.W"), out.pop(f"{fn.name}.b")
        out.update({f"{fn.name}.{name}": v for name, v in arrays.items()})
    return out, worst


def _held_out_errors(trained, vals) -> np.ndarray:
    """Measured − predicted on the held-out experiments, K: every measured sample after each file's burn-in (the
    samples its initial state was fitted to, not scored: as ``TrainedModel.evaluate`` and the doctor's own held-out
    rows score them), flattened (samples × sensors); the same entries for any model of the same files, NaN only where
    the prediction is not finite (a diverged run, which the held-out test rejects). Scored with the burn-in, the case
    study's check reported 2.83 mK for the doctor's linear law, whose held-out MAE the doctor measured as 3.0 mK
    without it (2026-12-06)."""
    out = []
    for r in trained.predict(vals, check=False):
        burn = int(r.get("burn_in", 0))
        measured = np.asarray(r["measured"], float)[burn:]
        e = measured - np.asarray(r["y"], float)[burn:]
        out.append(e[np.isfinite(measured)])
    return np.concatenate(out) if out else np.zeros(0)


def _n_params(trained) -> int:
    """Trainable scalars of a trained model (learned-function weights and free physical parameters)."""
    model = trained.compiled()
    return int(sum(int(np.prod(s.shape)) for s in model.param_specs.values() if s.trainable))


_CUT = ("time_limit", "interrupted")
"""How a training stopped when it was cut short of its schedule: its time limit, or Ctrl-C (the doctor's ``stop``)."""


def _cut_words(row: dict, time_limit: float) -> str:
    return "stopped by Ctrl-C" if row.get("stopped") == "interrupted" else f"stopped at the {time_limit:.0f} s limit"


def _decides(row: dict) -> str:
    return ("the check run to its end decides" if row.get("stopped") == "interrupted" else
            "a faster machine or a longer limit (mlp_time, tnnc diagnose --mlp-time S) decides")


def _stopping(stop: Callable[[], bool] | None) -> Callable[[dict], None] | None:
    """A training callback that stops the training (as Ctrl-C does: its best state kept) once ``stop()`` is true."""
    if stop is None:
        return None

    def callback(_record: dict) -> None:
        if stop():
            raise KeyboardInterrupt

    return callback


def compare(net: Network, targets: set[str], train, val, *, backend: str = "jax", time_limit: float = 60.0,
            say: Callable[[str], None] = lambda s: None, threads: int = 1, bar: float | None = None,
            stop: Callable[[], bool] | None = None, start: Mapping[str, np.ndarray] | None = None) -> dict | None:
    """Train the extension ``net`` as it is (the doctor's linear functions, of ``targets``) and with those as MLPs
    (:func:`mlp_variant`) on ``train`` (Experiments; each training stops on the end of its files,
    :data:`EARLY_STOP_FRACTION`), measure both on ``val`` (Experiments; free runs), which no training reads. Returns
    None when there is no linear function to compare, else a dict: ``linear`` / ``mlp`` (held-out MAE and max,
    K; trainable parameter count; seconds; how its training stopped), ``dm_stat``, ``p_value``, ``mae_gain``,
    ``choice`` ("mlp" or "linear"), ``decided`` (False: a training cut by ``time_limit`` s could have changed the
    answer, the linear law is kept; so does a training ``stop()`` stopped, checked after each of its epochs: the
    doctor's Ctrl-C), ``reason``, ``network`` (the chosen variant), ``model`` (where the MLP is chosen: the trained
    MLP variant, a :class:`~tnn_dsl.fit.TrainedModel`), ``n_clauses``. Without ``bar`` and
    with ``threads`` ≥ 2 the two trainings run side by side (their progress lines are said in order when both are
    done).

    ``bar`` (K): the held-out MAE the MLP must beat by ``MIN_GAIN`` to be chosen at all — the doctor's own linear
    fit of the extension (its Levenberg–Marquardt values, converged; the session's rule). Given, the MLP is trained
    first and alone, and the linear clauses are trained only when the MLP clears it: an MLP that does not cannot
    be chosen whatever the trained linear law scores, so the result has no ``linear`` entry, no test, and says so.
    On the case study the trained linear law (4.7 mK held out) never decided anything: the MLP (3.6 mK) did not
    beat the doctor's own fit (3.0 mK), and the two trainings side by side had been the diagnosis' peak memory
    (issue 18).

    ``start`` (the doctor's fit of the extension: its values by ``net``'s parameter names, SI): the check becomes a
    nested one (:func:`_compare_from_fit`): the MLP starts as the fitted linear law and only it is trained; ``bar``
    is then not used."""
    from ..fit import train as train_model

    net_mlp, n = mlp_variant(net, targets)
    if n == 0:
        return None
    if start is not None:
        return _compare_from_fit(net, net_mlp, n, start, train, val, backend=backend, time_limit=time_limit, say=say,
                                 stop=stop, threads=threads)
    out: dict = {"n_clauses": n}
    errors = {}
    trained_as: dict = {}

    def run(form: str, variant: Network, tell: Callable[[str], None]) -> tuple[np.ndarray, dict]:
        t0 = time.monotonic()
        tell(f"  training the extension with {form} clauses (at most {time_limit:.0f} s of training) ...")
        # each training's programs are compiled for it alone: XLA's lean options, whose compilation needs a
        # fraction of the memory (this check was the diagnosis' peak; issue 18)
        with lean_programs():
            trained = train_model(variant, train, None, val_fraction=EARLY_STOP_FRACTION, backend=backend,
                                  time_limit=time_limit, seed=0, callback=_stopping(stop))
            e = _held_out_errors(trained, val)
        row = {"val_mae": float(np.nanmean(np.abs(e))), "val_max": float(np.nanmax(np.abs(e))),
               "k": _n_params(trained), "seconds": round(time.monotonic() - t0, 1),
               "stopped": trained.meta.get("stopped")}
        tell(f"    held-out MAE {row['val_mae']:.4g} K ({row['seconds']} s)")
        trained_as[form] = trained
        return e, row

    forms = (("linear", net), ("mlp", net_mlp))
    if bar is not None and math.isfinite(bar):
        e_mlp, row = run("mlp", net_mlp, say)
        if row["val_mae"] > (1 - MIN_GAIN) * bar:  # it cannot be chosen (the session's own rule)
            cut = row.get("stopped") in _CUT
            out.update(mlp=row, choice="linear", network=net, decided=not cut)
            why = (f"the trained MLP ({row['val_mae']:.4g} K held out) does not beat the doctor's own linear fit "
                   f"({bar:.4g} K) by {100 * MIN_GAIN:.0f} %")
            out["reason"] = (f"not decided: {why}, but its training was {_cut_words(row, time_limit)} before its "
                             f"schedule ended; the linear law is kept — {_decides(row)}" if cut else
                             f"{why}: the linear law is kept (the linear clauses were not trained)")
            return out
        e_lin, row_lin = run("linear", net, say)
        done = [(e_lin, row_lin), (e_mlp, row)]
    else:
        done = side_by_side([lambda tell, f=f, v=v: run(f, v, tell) for f, v in forms], min(threads, 2), say)
    for (f, _), (e, row) in zip(forms, done):
        errors[f], out[f] = e, row
    return _with_model(_decide(out, errors["linear"], errors["mlp"], max(out["mlp"]["k"] - out["linear"]["k"], 1),
                               net, net_mlp, time_limit), trained_as.get("mlp"))


def _compare_from_fit(net: Network, net_mlp: Network, n: int, start: Mapping[str, np.ndarray], train, val, *,
                      backend: str, time_limit: float, say: Callable[[str], None],
                      stop: Callable[[], bool] | None, threads: int = 1) -> dict:
    """The nested check from the doctor's fit: the linear law is the doctor's fitted extension (``start``), free-run
    on ``val`` as the trainer runs a model (a burn-in estimate of each file's initial state); the MLP variant starts
    as that law (:func:`mlp_start`) with every other value held at the doctor's fit (``freeze``), and the trainer's
    L-BFGS polish alone trains its weights (Adam's steps, sized for a start from nominal values, would first walk
    away from the fitted law). Whatever the MLP gains on the held-out data is then the shape of the law, not a
    different fit of the physical parameters. The result is :func:`compare`'s, the ``linear`` row not trained
    (``stopped``: ``"the doctor's fit"``) and ``start_dz``: the largest raw-output difference between the MLP's start
    and the linear law."""
    from ..compiler import compile as compile_network
    from ..fit import TrainedModel
    from ..fit import train as train_model
    from ..fit.config import TrainConfig

    out: dict = {"n_clauses": n}
    lin_model = compile_network(net, backend=backend)
    lin_params = {k: np.asarray(v, float) for k, v in lin_model.to_numpy(lin_model.init_params(seed=0)).items()}
    lin_params.update({k: np.asarray(v, float) for k, v in start.items()
                       if k in lin_params and np.shape(v) == np.shape(lin_params[k])})
    k_lin = int(sum(int(np.prod(s.shape)) for name, s in lin_model.param_specs.items()
                    if s.trainable and s.kind != "physical" and name.split(".", 1)[0] in _converted(net, net_mlp)))

    def linear_run() -> tuple[np.ndarray, float]:
        """The linear law's held-out errors and its seconds (its own free run: nothing is trained)."""
        t_l = time.monotonic()
        with lean_programs():
            linear = TrainedModel(net, lin_params, meta={"backend": backend,
                                                          "config": TrainConfig(backend=backend).to_dict()})
            e = _held_out_errors(linear, val)
        return e, time.monotonic() - t_l

    mlp_values, dz = mlp_start(net_mlp, lin_params)
    out["start_dz"] = dz
    converted = _converted(net, net_mlp)
    specs = compile_network(net_mlp, backend=backend).param_specs
    freeze = sorted({k for k, s in specs.items() if s.trainable and s.kind == "physical"}
                    | {fn.name for fn in net_mlp.learned if fn.name not in converted})

    def mlp_run() -> tuple[Any, np.ndarray, float]:
        """The MLP trained from the linear law, its held-out errors and its seconds."""
        t_m = time.monotonic()
        say(f"  training the MLP from the doctor's linear law (at most {time_limit:.0f} s of training) ...")
        with lean_programs():
            trained = train_model(net_mlp, train, None, val_fraction=EARLY_STOP_FRACTION, backend=backend,
                                  time_limit=time_limit, seed=0, epochs=0, freeze=freeze, start=mlp_values,
                                  callback=_stopping(stop))
            e = _held_out_errors(trained, val)
        return trained, e, time.monotonic() - t_m

    def linear_then_warm() -> tuple[np.ndarray, float]:
        """The linear law's run, then, in the rest of the MLP's training, the MLP's held-out free run at its start
        values, its errors let go: the programs of its burn-in over the held-out files (0.9 s of compiling on the case
        study) go into the process's persistent program cache, and the trained MLP's held-out run reads them back
        instead of compiling them after its training (issue 18). A failure here changes nothing but that time."""
        out = linear_run()
        if stop is None or not stop():
            warm = TrainedModel(net_mlp, {**lin_params, **mlp_values},
                                meta={"backend": backend, "config": TrainConfig(backend=backend).to_dict()})
            try:
                with lean_programs():
                    _held_out_errors(warm, val)
            except Exception:  # noqa: BLE001 - only a cache is warmed: the trained MLP's own run says what fails
                pass
        return out

    # with a second thread the linear law's free run (its burn-in programs compiled, ~1.3 s on the case study) goes
    # beside the MLP's training, which it does not feed: the MLP starts from ``lin_params``, not from that run
    # (issue 18); the numbers are the same either way. Where JAX keeps the programs it compiles (``tnnc diagnose``),
    # that thread then compiles the trained MLP's held-out programs ahead.
    warm_ahead = threads > 1 and backend == "jax" and _programs_kept()
    (e_lin, lin_s), (trained, e_mlp, mlp_s) = two_at_once(linear_then_warm if warm_ahead else linear_run, mlp_run,
                                                          threads)
    out["linear"] = {"val_mae": float(np.nanmean(np.abs(e_lin))), "val_max": float(np.nanmax(np.abs(e_lin))),
                     "k": k_lin, "seconds": round(lin_s, 1), "stopped": "the doctor's fit"}
    k_mlp = int(sum(int(np.prod(s.shape)) for name, s in specs.items()
                    if s.trainable and s.kind != "physical" and name.split(".", 1)[0] in converted))
    row = {"val_mae": float(np.nanmean(np.abs(e_mlp))), "val_max": float(np.nanmax(np.abs(e_mlp))), "k": k_mlp,
           "seconds": round(mlp_s, 1), "stopped": trained.meta.get("stopped")}
    say(f"    held-out MAE {row['val_mae']:.4g} K against the linear law's {out['linear']['val_mae']:.4g} K "
        f"({row['seconds']} s)")
    out["mlp"] = row
    return _with_model(_decide(out, e_lin, e_mlp, max(k_mlp - k_lin, 1), net, net_mlp, time_limit, nested=True),
                       trained)


def _programs_kept() -> bool:
    """:func:`~tnn_dsl.compiler.backends.jax_ops.programs_kept` (JAX imported only here)."""
    from ..compiler.backends.jax_ops import programs_kept

    return programs_kept()


def _with_model(out: dict, trained_mlp) -> dict:
    """``out`` with ``model``: the trained MLP variant (a :class:`~tnn_dsl.fit.TrainedModel`, its compiled programs
    let go) where the MLP is chosen — the model whose held-out numbers the check reports, for the doctor to hand out
    and save (``tnnc diagnose --model``); else no ``model`` (the linear law is the doctor's own fit)."""
    if out.get("choice") == "mlp" and trained_mlp is not None:
        trained_mlp.release_compiled()
        out["model"] = trained_mlp
    return out


def _decide(out: dict, e_lin: np.ndarray, e_mlp: np.ndarray, k_extra: int, net: Network, net_mlp: Network,
            time_limit: float, nested: bool = False) -> dict:
    """The answer of both checks, written into ``out``: the held-out test (:func:`_test`), then ``decided`` — False
    where a training the time limit (or Ctrl-C) cut short could have changed it: the MLP's when it does not pay, the
    linear law's when the MLP does (``nested``: the linear law is the doctor's fit, never cut) — ``choice``,
    ``network`` and ``reason``."""
    p, gain, pays = _test(out, e_lin, e_mlp, k_extra)
    cut = [f for f in (("linear",) if pays else ("mlp",)) if out[f].get("stopped") in _CUT]
    out["decided"] = not cut
    if cut:
        row = out[cut[0]]
        who = "the MLP's training" if nested else f"the {cut[0]} variant's training"
        so_far = "it does not pay" if nested else f"the MLP {'pays' if pays else 'does not pay'}"
        out.update(choice="linear", network=net,
                   reason=(f"not decided: {who} was {_cut_words(row, time_limit)} before its schedule ended (so far "
                           f"{so_far}, p = {p:.2g}); the linear law is kept — {_decides(row)}"))
    elif pays:
        against = " against the doctor's linear law it started as" if nested else ""
        out.update(choice="mlp", network=net_mlp,
                   reason=f"the MLP pays on held-out data (p = {p:.2g}, MAE −{100 * gain:.0f} %{against})")
    else:
        subject = "the MLP, started as the doctor's linear law," if nested else "the MLP"
        out.update(choice="linear", network=net,
                   reason=f"{subject} does not pay on held-out data ({_why_not(p, gain)})")
    return out


def _test(out: dict, e_lin: np.ndarray, e_mlp: np.ndarray, k_extra: int) -> tuple[float, float, bool]:
    """The held-out test of the MLP's errors against the linear law's (Diebold–Mariano with ``k_extra`` parameters
    charged) and the MAE gain, written into ``out`` (``dm_stat``, ``p_value``, ``n_eff``, ``mae_gain``) → ``(p, gain,
    whether the MLP pays)``."""
    stat, p, n_eff = held_out_test(e_lin, e_mlp, k_extra)
    gain = 1 - out["mlp"]["val_mae"] / out["linear"]["val_mae"] if out["linear"]["val_mae"] > 0 else 0.0
    out.update(dm_stat=stat, p_value=p, n_eff=n_eff, mae_gain=gain)
    return p, gain, p < P_ACCEPT and gain >= MIN_GAIN


def _why_not(p: float, gain: float) -> str:
    """Why an MLP does not pay: its p-value, else its gain."""
    return f"p = {p:.2g} ≥ {P_ACCEPT}" if p >= P_ACCEPT else f"gain {100 * gain:.1f} % < {100 * MIN_GAIN:.0f} %"


def _converted(net: Network, net_mlp: Network) -> set[str]:
    """Names of the learned functions :func:`mlp_variant` turned from ``linear`` into an MLP."""
    kinds = {fn.name: fn.kind for fn in net.learned}
    return {fn.name for fn in net_mlp.learned if fn.kind == "mlp" and kinds.get(fn.name) == "linear"}
