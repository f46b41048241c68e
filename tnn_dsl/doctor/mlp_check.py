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

Both variants start from the same nominal values and go through the same trainer, so neither is favoured by
the doctor's own Levenberg–Marquardt fit. The doctor keeps an MLP only if it also beats that fit (its linear law
converged) by ``MIN_GAIN``; so it trains the MLP first, alone, and the linear clauses only when the MLP clears that
bar (``compare(..., bar=)``): otherwise the trained linear law could not change the answer.

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
from typing import Callable

import numpy as np

from ..analysis import held_out_test
from ..compiler.backends.adapter import lean_programs
from ..ir import Network
from .selection import MIN_GAIN, P_ACCEPT
from .threads import side_by_side

HIDDEN = 8


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


def _held_out_errors(trained, vals) -> np.ndarray:
    """Measured − predicted on the held-out experiments, flattened (NaN where not measured), K."""
    out = []
    for r in trained.predict(vals, check=False):
        out.append((np.asarray(r["measured"], float) - np.asarray(r["y"], float)).ravel())
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
            stop: Callable[[], bool] | None = None) -> dict | None:
    """Train the extension ``net`` as it is (the doctor's linear functions, of ``targets``) and with those as MLPs
    (:func:`mlp_variant`) on ``train`` (Experiments), measure both on ``val`` (Experiments; free runs). Returns
    None when there is no linear function to compare, else a dict: ``linear`` / ``mlp`` (held-out MAE and max,
    K; trainable parameter count; seconds; how its training stopped), ``dm_stat``, ``p_value``, ``mae_gain``,
    ``choice`` ("mlp" or "linear"), ``decided`` (False: a training cut by ``time_limit`` s could have changed the
    answer, the linear law is kept; so does a training ``stop()`` stopped, checked after each of its epochs: the
    doctor's Ctrl-C), ``reason``, ``network`` (the chosen variant), ``n_clauses``. Without ``bar`` and
    with ``threads`` ≥ 2 the two trainings run side by side (their progress lines are said in order when both are
    done).

    ``bar`` (K): the held-out MAE the MLP must beat by ``MIN_GAIN`` to be chosen at all — the doctor's own linear
    fit of the extension (its Levenberg–Marquardt values, converged; the session's rule). Given, the MLP is trained
    first and alone, and the linear clauses are trained only when the MLP clears it: an MLP that does not cannot
    be chosen whatever the trained linear law scores, so the result has no ``linear`` entry, no test, and says so.
    On the case study the trained linear law (4.7 mK held out) never decided anything: the MLP (3.6 mK) did not
    beat the doctor's own fit (3.0 mK), and the two trainings side by side had been the diagnosis' peak memory
    (issue 18)."""
    from ..fit import train as train_model

    net_mlp, n = mlp_variant(net, targets)
    if n == 0:
        return None
    out: dict = {"n_clauses": n}
    errors = {}

    def run(form: str, variant: Network, tell: Callable[[str], None]) -> tuple[np.ndarray, dict]:
        t0 = time.monotonic()
        tell(f"  training the extension with {form} clauses (at most {time_limit:.0f} s of training) ...")
        # each training's programs are compiled for it alone: XLA's lean options, whose compilation needs a
        # fraction of the memory (this check was the diagnosis' peak; issue 18)
        with lean_programs():
            trained = train_model(variant, train, val, backend=backend, time_limit=time_limit, seed=0,
                                  callback=_stopping(stop))
            e = _held_out_errors(trained, val)
        row = {"val_mae": float(np.nanmean(np.abs(e))), "val_max": float(np.nanmax(np.abs(e))),
               "k": _n_params(trained), "seconds": round(time.monotonic() - t0, 1),
               "stopped": trained.meta.get("stopped")}
        tell(f"    held-out MAE {row['val_mae']:.4g} K ({row['seconds']} s)")
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
    k_extra = max(out["mlp"]["k"] - out["linear"]["k"], 1)
    stat, p, n_eff = held_out_test(errors["linear"], errors["mlp"], k_extra)
    gain = 1 - out["mlp"]["val_mae"] / out["linear"]["val_mae"] if out["linear"]["val_mae"] > 0 else 0.0
    out.update(dm_stat=stat, p_value=p, n_eff=n_eff, mae_gain=gain)
    pays = p < P_ACCEPT and gain >= MIN_GAIN
    # a training the time limit cut short that could have changed the answer: the MLP's when it did not pay, the
    # linear law's when the MLP did
    cut = [f for f in (("linear",) if pays else ("mlp",)) if out[f].get("stopped") in _CUT]
    out["decided"] = not cut
    if cut:
        out.update(choice="linear", network=net,
                   reason=(f"not decided: the {cut[0]} variant's training was {_cut_words(out[cut[0]], time_limit)} "
                           f"before its schedule ended (so far the MLP {'pays' if pays else 'does not pay'}, p = "
                           f"{p:.2g}); the linear law is kept — {_decides(out[cut[0]])}"))
    elif pays:
        out.update(choice="mlp", network=net_mlp,
                   reason=f"the MLP pays on held-out data (p = {p:.2g}, MAE −{100 * gain:.0f} %)")
    else:
        why = (f"p = {p:.2g} ≥ {P_ACCEPT}" if p >= P_ACCEPT
               else f"gain {100 * gain:.1f} % < {100 * MIN_GAIN:.0f} %")
        out.update(choice="linear", network=net, reason=f"the MLP does not pay on held-out data ({why})")
    return out
