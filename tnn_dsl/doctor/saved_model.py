"""The diagnosed model as a trained model (``Diagnosis.model``; ``tnnc diagnose --model DIR`` writes it): the network
the doctor ends with — the extension (its ``linear`` clauses, or the MLP where the MLP check chose it), or the user's
own network where nothing was accepted — at the values the doctor measured it with. Its held-out numbers are the
report's: ``tnnc evaluate DIR VAL.csv`` free-runs it from the same initial-state rule and scores the same samples.

Before this the doctor's fitted values lived in memory only: the extended ``.thn`` holds the new constants rounded to
four digits and no learned weights, so the gain the report measured could not be had again from what it wrote (the
case study's MLP, trained by the check, was lost). A training file's fitted initial state is stored under its
fingerprint, as the trainer stores it, so a free run on that file starts where the doctor's did.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from ..ir import Network

__all__ = ["model_values", "diagnosed_model"]


def model_values(net: Network, values: Mapping[str, np.ndarray], backend: str) -> dict[str, np.ndarray]:
    """Every array ``net`` compiled for ``backend`` reads (SI): its initial values (``init_params(seed=0)``: a
    learned function's normalisation and scales, constants at their written values) with ``values`` put in where a
    name and shape match (the doctor's fit, :func:`~tnn_dsl.doctor.mlp_check.values_for_extension`)."""
    from ..compiler import compile as compile_network

    model = compile_network(net, backend=backend)
    out = {k: np.asarray(v, float) for k, v in model.to_numpy(model.init_params(seed=0)).items()}
    out.update({k: np.array(v, dtype=float, copy=True) for k, v in values.items()
                if k in out and np.shape(v) == np.shape(out[k])})
    return out


def _initial_state_records(net: Network, eng: Any, train_arg: Any) -> list[dict]:
    """The engine's fitted initial states of the training files, keyed as the trainer keys them (``name``,
    ``fingerprint`` of the file as ``net`` reads it, ``T0`` by state name, K); none under the ``steady`` rule, for
    data given as something other than files the network can read again, or where the files do not match the
    engine's experiments one for one."""
    from ..core import TnnError
    from ..data import as_experiments
    from ..fit.initial import fingerprint
    from .engine import x0_key

    if not eng.exps or not eng.x0_keys(0):
        return []
    n_train = len(eng.exps) - len(eng.val_only)
    try:
        exps = as_experiments(net, train_arg)
    except (TnnError, TypeError, ValueError):
        return []
    if len(exps) != n_train or any(a.n_steps != b.n_steps or float(a.dt) != float(b.dt)
                                   for a, b in zip(exps, eng.exps[:n_train])):
        return []
    states = list(eng.model.state_names)
    out = []
    for i, exp in enumerate(exps):
        T0 = {s: float(np.asarray(eng.params[x0_key(i, s)]).reshape(-1)[0]) for s in states
              if x0_key(i, s) in eng.params}
        if len(T0) == len(states) and all(np.isfinite(list(T0.values()))):
            out.append({"name": exp.name, "fingerprint": fingerprint(exp), "T0": T0})
    return out


def diagnosed_model(net: Network, values: Mapping[str, np.ndarray], *, backend: str, init_rule: str,
                    eng: Any, train_arg: Any, data_files: Sequence[Any], diagnosis: dict,
                    trained: Any = None) -> Any:
    """The :class:`~tnn_dsl.fit.TrainedModel` of the network the doctor ends with.

    ``net``: that network (the extension parsed from its printed text, or the user's); ``values``: the doctor's
    fitted values by ``net``'s names (SI; ignored when ``trained`` is given); ``eng``: the engine that fitted them
    (its training files' initial states are stored); ``trained``: the MLP check's trained model where the MLP was
    chosen (its values and its trainer's ``meta`` are kept). ``diagnosis`` goes into ``meta["diagnosis"]``: the
    verdict, the form, the held-out numbers the report gives and which data they were measured on."""
    from ..fit import TrainedModel
    from ..fit.config import TrainConfig
    from ..fit.model_files import data_records, versions

    if trained is not None:
        return TrainedModel(trained.network, dict(trained.params), {**trained.meta, "diagnosis": diagnosis})
    held = diagnosis.get("held_out") or {}
    meta = {
        "network": net.name,
        "backend": backend,
        "dtype": "float64",
        "versions": versions(backend),
        "config": TrainConfig(backend=backend, init=init_rule).to_dict(),
        "init": init_rule,
        "data_files": data_records(data_files),
        "initial_states": _initial_state_records(net, eng, train_arg),
        "per_experiment": [],
        "metrics": {"validation": {"mae": held.get("mae"), "max_error": held.get("max")}},
        "stopped": "the doctor's fit",
        "diagnosis": diagnosis,
    }
    return TrainedModel(net, model_values(net, values, backend), meta)
