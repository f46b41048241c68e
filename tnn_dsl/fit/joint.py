"""Several independent data sets of one network — units of a fleet: boards, heat exchangers, buildings — fitted in
one compiled program: :func:`train_jointly`.

Each set's free constants are made per-experiment parameters (``free ... per experiment``: one value per data
file) of one joint network, and the trainer fits every set's file at once: one loss, one compiled program, one
Adam run and one L-BFGS polish for all of them (the loss holds one rollout per set; they share no parameter, so
the sets do not pull on each other). Afterwards each set gets its own :class:`~tnn_dsl.fit.TrainedModel`, as if it
had been trained alone: the template network, the set's values, its file's fitted initial state, its own
standard errors (the output-error Gauss–Newton information of its own residuals, or with ``objective="ml"`` its
own likelihood fit started from the joint fit's values) and its own training and held-out errors. All sets use one
compiled model of the template (the values are arguments, not constants of the program), so the per-set work
compiles nothing new after the first set.

What differs from fitting each set alone (``train(net, [file])``): the step-size schedule, early stopping and the
L-BFGS stopping rule see the sum of the sets' losses, so a set's values agree with its separate fit to within the
optimiser's tolerance, not to round-off (the fleet's test: within a tenth of a standard error). No set's held-out
data is seen by the fit (early stopping on the training loss).

Limits (:func:`joint_fit_problem` says which applies): each set has exactly one training file; the network has no
learned function (its weights would be shared by the sets) and no per-experiment parameter of its own.
"""

from __future__ import annotations

import dataclasses
import os
import time
from typing import Any, Callable, Sequence

import numpy as np

from ..core import Diagnostic, TnnError
from ..data import Experiment
from ..ir import Network
from .config import TrainConfig, one_sequence_per_file, single_shooting_route, torch_compile_pays
from .initial import fingerprint
from .model_files import TrainedModel
from .trainer import _net_of
from .training import _best_route, _estimates, _fitted, make_config, model_meta

__all__ = ["train_jointly", "joint_fit_problem", "joint_network"]


def joint_fit_problem(network: Network, sets: Sequence[tuple[Sequence[Any], Sequence[Any]]]) -> str | None:
    """Why ``sets`` (``(training experiments, held-out experiments)`` per set) cannot be fitted jointly with
    ``network``, or ``None`` when they can."""
    if len(sets) < 2:
        return "a joint fit needs at least two data sets"
    if network.learned:
        return (f"network {network.name!r} has learned functions ({', '.join(f.name for f in network.learned)}): "
                "their weights would be shared by the sets")
    pe = [p.name for p in network.params if getattr(p, "per_experiment", False)]
    if pe:
        return f"network {network.name!r} already has per-experiment parameters ({', '.join(pe)})"
    if not any(p.free for p in network.params):
        return f"network {network.name!r} has no free constant"
    for i, (train, _val) in enumerate(sets):
        if len(train) != 1:
            return f"data set {i + 1} has {len(train)} training files; a joint fit takes one per set"
    return None


def joint_network(network: Network) -> Network:
    """``network`` with every free constant per experiment (one value per data file)."""
    params = [p.model_copy(update={"per_experiment": True}) if p.free else p for p in network.params]
    return network.model_copy(update={"params": params}, deep=True)


def train_jointly(network: Network | str | os.PathLike, sets: Sequence[tuple[Sequence[Experiment],
                                                                             Sequence[Experiment]]], *,
                  config: TrainConfig | dict | str | os.PathLike | None = None,
                  log: Callable[[str], None] | None = None, **options: Any) -> list[TrainedModel]:
    """Fit ``network`` to every data set of ``sets`` at once (module docstring).

    Parameters
    ----------
    network : the template (a :class:`Network` or a ``.thn`` path) every set shares
    sets : ``(training experiments, held-out experiments)`` per set; exactly one training file per set; the held-out
        ones (possibly none) are only scored, never used by the fit
    config, **options : as :func:`~tnn_dsl.fit.train` (``val_fraction`` is not used: nothing is held out of the
        training files)

    Returns one :class:`TrainedModel` per set, in order: the template network, the set's fitted values, its
    training file's fitted initial state, ``meta["estimation"]`` (its own standard errors), ``meta["metrics"]``
    (``train`` and, with held-out files, ``validation``) and ``meta["joint"]`` (``sets``, ``index``, ``seconds`` of
    the joint fit, ``stopped``)."""
    from ..compiler import compile as compile_network

    net = _net_of(network)
    problem = joint_fit_problem(net, sets)
    if problem:
        raise TnnError(Diagnostic(f"no joint fit: {problem}", hint="fit the sets one by one with tnn_dsl.train"))
    cfg = make_config(config, {**options, "val_fraction": 0.0})
    say = log or (lambda s: None)
    exps = [list(train)[0] for train, _ in sets]
    auto = torch_compile_pays(cfg, sum(int(e.n_steps) for e in exps), one_sequence_per_file(cfg, exps),
                              single_shooting_route(cfg, exps))
    if auto is not None and auto != cfg.torch_compile:
        cfg = dataclasses.replace(cfg, torch_compile=auto)
    joint = joint_network(net)
    joint_cfg = dataclasses.replace(cfg, objective="output-error")  # each set's likelihood fit follows, alone
    t0 = time.perf_counter()
    joint_model = compile_network(joint, backend=cfg.backend, dtype=cfg.dtype, torch_compile=cfg.torch_compile)
    tr, z, strategy, compile_s = _best_route(joint, exps, [], joint_cfg, joint_model, None, log)
    seconds = time.perf_counter() - t0
    values = tr.experiment_values(z)
    starts = tr.fitted_initial_states(z)
    common = tr.numpy_params(z)
    fitted_joint = _fitted(tr, joint_model, common)
    say(f"joint fit of {len(exps)} data sets: {seconds:.1f} s ({tr.stopped})")

    model = compile_network(net, backend=cfg.backend, dtype=cfg.dtype, torch_compile=cfg.torch_compile)
    out = []
    for k, (e, (_train, val)) in enumerate(zip(exps, sets)):
        fp = fingerprint(e)
        mine = values[k]["values"]
        params = {name: np.asarray(v, dtype=np.float64).copy() for name, v in common.items()}
        for name, v in mine.items():
            params[name] = np.asarray(v, dtype=np.float64).reshape(np.shape(params[name]))
        start = next(({**r, "name": e.name} for r in starts if r.get("fingerprint") == fp), None)
        trained = TrainedModel(net, params, meta={"initial_states": [start] if start else [], "per_experiment": [],
                                                  "config": cfg.to_dict()})
        trained._models[(cfg.backend, cfg.dtype)] = model
        view = _SetView(tr)  # the joint trainer's record, with this set's own warnings
        est = _estimates(trained, model, [e], cfg, view)
        fitted = {name: {"value": float(np.asarray(trained.params[name]).reshape(-1)[0]),
                         "initial": fitted_joint[name]["initial"]} for name in mine if name in fitted_joint}
        meta = model_meta(trained, view, model, [e], list(val), cfg, est, fitted=fitted, strategy=strategy,
                          seconds=seconds / len(exps), compile_seconds=compile_s / len(exps))
        meta["joint"] = {"sets": len(exps), "index": k, "seconds": seconds, "stopped": tr.stopped,
                         "note": "fitted together with the other sets (one compiled program; the curve is the "
                                 "sum of their losses)"}
        trained.meta = meta
        out.append(trained)
    return out


class _SetView:
    """What :func:`~tnn_dsl.fit.training.model_meta` and the estimates read of a trainer, for one set of a joint
    fit: the joint trainer's record (curve, normalisation, layout, why it stopped) with a copy of its warnings, to
    which this set's own are added."""

    def __init__(self, tr: Any) -> None:
        self.stopped = tr.stopped
        self.warnings = list(tr.warnings)
        self.log = tr.log
        self.normalisation = tr.normalisation
        self.curve = tr.curve
        self.windowed = tr.windowed
        self.single_shooting = tr.single_shooting
        self.mode = tr.mode
        self.window = getattr(tr, "window", None)
