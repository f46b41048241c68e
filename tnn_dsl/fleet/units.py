"""One unit's work, the same whether it runs in a Ray task, in this process or in a batch: the network template
with the unit's overrides, its data, the fit (estimates with standard errors, held-out error) and, for
``diagnose``, the model doctor's findings. Pure: it reads nothing from disk (the driver reads the data and passes
the experiments) and returns what is to be written; :mod:`tnn_dsl.fleet.engine` writes it.
"""

from __future__ import annotations

import math
import re
import time
import traceback
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ..core import Diagnostic, TnnError
from ..ir import Network, Num

__all__ = ["FleetOptions", "unit_network", "run_unit", "run_batch", "batch_problem", "unit_key", "HELD_OUT_FRACTION"]

HELD_OUT_FRACTION = 0.3
"""A unit without held-out files is judged on the last 30 % of each training file (as ``tnnc diagnose``)."""

MODES = ("train", "diagnose")


@dataclass(frozen=True)
class FleetOptions:
    """What is done to every unit. ``mode``: ``train`` (the fit, its estimates with standard errors, held-out
    error) or ``diagnose`` (that, then the model doctor on the same data). ``epochs``: the trainer's epochs
    (``None``: its default). ``top``, ``max_rounds``, ``budget_s`` (per unit), ``mlp_check`` (off by default in a
    fleet: it trains two MLP extensions per unit), ``init``, ``burn_in``: as ``tnnc diagnose``."""

    mode: str = "diagnose"
    backend: str = "jax"
    epochs: int | None = None
    top: int | None = None
    max_rounds: int = 4
    budget_s: float | None = None
    mlp_check: bool = False
    init: str = "estimate"
    burn_in: float | None = None

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise TnnError(Diagnostic(f"fleet mode must be one of {', '.join(MODES)}, got {self.mode!r}",
                                      hint="`tnnc fleet train ...` or `tnnc fleet diagnose ...`"))
        if self.backend not in ("jax", "torch"):
            raise TnnError(Diagnostic(f"backend must be jax or torch, got {self.backend!r}"))

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def unit_key(template_text: str, unit: dict[str, Any], options: FleetOptions, data_digest: str) -> str:
    """What a finished unit's result depends on (the template's text, the unit's entry, the options and its data's
    SHA-256): a re-run skips a unit whose stored key matches and redoes one whose key differs."""
    import hashlib
    import json

    blob = json.dumps({"template": template_text, "unit": unit, "options": options.to_dict(), "data": data_digest},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


_QUANTITY = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(.*?)\s*$")


def unit_network(net: Network, unit: dict[str, Any]) -> Network:
    """The template ``net`` with the unit's overrides: ``columns`` (an input or sensor name -> its column in this
    unit's files) and ``params`` (a parameter name -> a known value as written, e.g. ``"22.5 degC"``: fixed at it,
    no longer free). A name the network does not have, or a value in the wrong dimension, is a clear error."""
    from ..lang.units import UnitError, parse_quantity

    columns = dict(unit.get("columns") or {})
    known = dict(unit.get("params") or {})
    name = unit["name"]
    inputs, sensors = {i.name for i in net.inputs}, {s.name for s in net.sensors}
    for k in columns:
        if k not in inputs | sensors:
            raise TnnError(Diagnostic(f"unit {name!r}: `columns:` names {k!r}, which is neither an input nor a sensor "
                                      f"of network {net.name!r}",
                                      hint=f"inputs: {', '.join(sorted(inputs)) or '—'}; sensors: "
                                           f"{', '.join(sorted(sensors)) or '—'}"))
    params = {p.name: p for p in net.params}
    new_params = []
    for p in net.params:
        if p.name not in known:
            new_params.append(p)
            continue
        text = str(known[p.name])
        m = _QUANTITY.match(text)
        if not m:
            raise TnnError(Diagnostic(f"unit {name!r}: known value {text!r} of {p.name} is not a number with a unit",
                                      hint=f"write e.g. `{p.name}: 1.5 {p.unit or ''}`".rstrip() + "`"))
        try:
            si, dim = parse_quantity(float(m.group(1)), m.group(2) or None)
        except UnitError as e:
            raise TnnError(Diagnostic(f"unit {name!r}: known value {text!r} of {p.name}: {e}",
                                      hint=f"write it in {p.unit or 'the unit of the network file'}"))
        want = {k: v for k, v in (p.dim or {}).items() if v}
        if {k: v for k, v in dim.items() if v} != want:
            raise TnnError(Diagnostic(f"unit {name!r}: known value {text!r} of {p.name} has the wrong dimension",
                                      hint=f"{p.name} is written in {p.unit or 'SI'} in the network"))
        new_params.append(p.model_copy(update={"expr": Num(value=si, dim=p.dim, unit=p.unit), "free": False,
                                               "lower": None, "upper": None}))
    for k in known:
        if k not in params:
            raise TnnError(Diagnostic(f"unit {name!r}: `params:` names {k!r}, which is not a parameter of network "
                                      f"{net.name!r}", hint=f"parameters: {', '.join(sorted(params))}"))
    new_inputs = [i.model_copy(update={"column": columns[i.name]}) if i.name in columns else i for i in net.inputs]
    new_sensors = [s.model_copy(update={"column": columns[s.name]}) if s.name in columns else s for s in net.sensors]
    return net.model_copy(update={"params": new_params, "inputs": new_inputs, "sensors": new_sensors}, deep=True)


def _split(exps: list, val: list) -> tuple[list, list]:
    if val:
        return exps, val
    from ..data.experiment import split_by_time

    parts = [split_by_time(e, 1.0 - HELD_OUT_FRACTION) for e in exps]
    return [a for a, _ in parts], [b for _, b in parts]


def _finite(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def run_unit(net: Network, unit: dict[str, Any], train: list, val: list, options: FleetOptions) -> dict[str, Any]:
    """Fit (and with ``mode="diagnose"`` diagnose) one unit. ``net``: the unit's network (overrides applied);
    ``train``/``val``: its experiments (``val`` empty: the last 30 % of each training file). Returns the result
    row: ``unit``, ``status`` (``ok``, or ``failed`` with ``reason`` when the unit's data or fit is at fault),
    ``val_mae`` K, ``train_mae`` K, ``params`` (``{name: {"estimate", "se", "status", "unit_si", "display"}}``),
    ``findings`` (as ``tnnc diagnose --json``, accepted first), ``gain`` (held-out MAE before / after the doctor's
    extension), ``extended`` (the extended ``.thn`` text, if any), ``model`` (files of the saved model: name ->
    bytes), ``seconds``. A :class:`~tnn_dsl.core.TnnError` makes the row ``failed`` with its message; any other
    exception is an internal error (``error``, with the traceback's last line)."""
    t0 = time.perf_counter()
    row: dict[str, Any] = {"unit": unit["name"], "status": "ok", "reason": "", "val_mae": None, "train_mae": None,
                           "params": {}, "findings": [], "gain": None, "extended": None, "model": {}}
    try:
        _fit(net, unit, train, val, options, row)
    except TnnError as e:
        row.update(status="failed", reason=str(e).strip())
    except Exception as e:  # noqa: BLE001 - one unit's internal error must not stop the fleet; it is reported
        last = traceback.format_exc().strip().splitlines()[-1]
        row.update(status="error", reason=f"internal error: {type(e).__name__}: {e} ({last})")
    row["seconds"] = time.perf_counter() - t0
    return row


def _fit(net: Network, unit: dict[str, Any], train: list, val: list, options: FleetOptions, row: dict) -> None:
    from ..fit import train as train_model

    exps, vals = _split(list(train), list(val))
    extra = {} if options.epochs is None else {"epochs": int(options.epochs)}
    # the held-out files are only scored: early stopping on the training loss, as in a joint fit (run_batch)
    tm = train_model(net, exps, None, backend=options.backend, init=options.init, burn_in=options.burn_in,
                     val_fraction=0.0, **extra)
    _score_held_out(tm, vals, options)
    _fill_row(tm, row)
    if options.mode == "diagnose":
        _diagnose(net, exps, vals, options, row)


def _score_held_out(tm: Any, vals: list, options: FleetOptions) -> None:
    """The held-out error of a model fitted without ``vals`` (``meta["metrics"]["validation"]``)."""
    from ..fit.training import _data_desc

    try:
        m = tm.evaluate(vals, backend=options.backend, init=options.init, burn_in_s=options.burn_in)
    except (FloatingPointError, TnnError):  # a model that leaves the physical range there
        m = {"mae": math.nan}
    tm.meta.setdefault("metrics", {})["validation"] = m
    tm.meta.setdefault("data", {})["validation"] = _data_desc(vals)


def _fill_row(tm: Any, row: dict) -> None:
    """A fitted unit's row: errors, the network's constants with their standard errors, the saved model's files."""
    metrics = tm.meta.get("metrics") or {}
    row["train_mae"] = _finite((metrics.get("train") or {}).get("mae"))
    row["val_mae"] = _finite((metrics.get("validation") or {}).get("mae"))
    est = tm.meta.get("estimation") or {}
    for r in est.get("rows") or []:  # the network's constants (not initial states, noise levels or weights)
        name = str(r.get("name", ""))
        if "[" in name or name.startswith(("x0", "sigma_", "p0_std")):
            continue
        row["params"][name] = {"estimate": _finite(r.get("estimate")), "se": _finite(r.get("se")),
                               "status": r.get("status"), "unit_si": r.get("unit_si"), "display": r.get("display")}
    if tm.meta.get("joint"):
        row["joint"] = {k: tm.meta["joint"][k] for k in ("sets", "seconds", "stopped")}
    row["model"] = _model_files(tm)


def _model_files(tm: Any, source_text: str | None = None) -> dict[str, bytes]:
    """A model directory's files as ``{name: bytes}`` (written by the fleet's driver under the unit's result)."""
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory(prefix="tnn-fleet-") as tmp:
        out = tm.save(Path(tmp) / "model", source_text=source_text)
        return {p.name: p.read_bytes() for p in sorted(Path(out).iterdir()) if p.is_file()}


def _diagnose(net: Network, exps: list, vals: list, options: FleetOptions, row: dict) -> None:
    from ..doctor import diagnose

    # one fit at a time: a fleet's parallelism is across units (a Ray CPU each); the result does not depend on it
    d = diagnose(net, exps, vals, budget_s=options.budget_s, backend=options.backend, top=options.top,
                 max_rounds=options.max_rounds, mlp_check=options.mlp_check, init=options.init,
                 burn_in=options.burn_in, threads=1)
    doc = d.to_dict()
    findings = sorted(doc.get("findings") or [], key=lambda f: (not f.get("accepted"), f.get("rank") or 0))
    row["findings"] = findings
    gain = doc.get("gain") or {}
    row["gain"] = _finite(gain.get("val_mae_ratio")) if d.accepted else 1.0
    row["extended"] = d.extended_text if d.accepted else None
    if d.accepted and d.model is not None:  # the extended model at the doctor's values (tnnc diagnose --model)
        row["extended_model"] = _model_files(d.model, source_text=d.extended_text)
    row["diagnosis"] = {k: doc.get(k) for k in ("verdict", "decided", "budget", "notes", "baseline", "gain", "left",
                                                "diff")}


def batch_problem(net: Network, members: list[tuple[dict[str, Any], list, list]], options: FleetOptions) -> str | None:
    """Why the units ``members`` (``(unit, train, val)``, each with ``net``, its overrides applied) cannot be fitted
    together in one compiled program (:func:`tnn_dsl.fit.joint.train_jointly`), or ``None``."""
    from ..fit.joint import joint_fit_problem

    if options.mode != "train":
        return "the model doctor runs unit by unit"
    return joint_fit_problem(net, [_split(list(t), list(v)) for _u, t, v in members])


def run_batch(net: Network, members: list[tuple[dict[str, Any], list, list]], options: FleetOptions,
              networks: list[Network] | None = None) -> list[dict[str, Any]]:
    """Fit the units ``members`` (``(unit, train, val)``, all with the network ``net``) in one compiled program
    (:func:`tnn_dsl.fit.joint.train_jointly`) and return their rows, as :func:`run_unit`'s. ``networks``: each
    unit's own network (the same structure; its column names may differ), kept in its saved model. Where they
    cannot be fitted together (:func:`batch_problem`) or the joint fit fails (one unit's bad data), each unit is run
    on its own, so that a bad unit gets its own row and the rest go on."""
    nets = list(networks) if networks is not None else [net] * len(members)
    from ..fit.joint import train_jointly

    t0 = time.perf_counter()
    if len(members) < 2 or batch_problem(net, members, options) is not None:
        return [run_unit(n, u, t, v, options) for n, (u, t, v) in zip(nets, members)]
    sets = [_split(list(t), list(v)) for _u, t, v in members]
    extra = {} if options.epochs is None else {"epochs": int(options.epochs)}
    try:
        models = train_jointly(net, sets, backend=options.backend, init=options.init, burn_in=options.burn_in,
                               **extra)
    except Exception:  # noqa: BLE001 - one unit's data or fit: each unit on its own says which
        return [run_unit(n, u, t, v, options) for n, (u, t, v) in zip(nets, members)]
    rows = []
    share = (time.perf_counter() - t0) / len(members)
    for (u, _t, _v), tm, own in zip(members, models, nets):
        tm.network = own  # the unit's column names in its saved model (the structure is the batch's)
        row: dict[str, Any] = {"unit": u["name"], "status": "ok", "reason": "", "val_mae": None, "train_mae": None,
                               "params": {}, "findings": [], "gain": None, "extended": None, "model": {}}
        try:
            _fill_row(tm, row)
        except TnnError as e:
            row.update(status="failed", reason=str(e).strip())
        row["seconds"] = share
        rows.append(row)
    return rows


def data_digest(experiments: list) -> str:
    """SHA-256 of a unit's experiments' arrays (the data its result depends on)."""
    import hashlib

    h = hashlib.sha256()
    for e in experiments:
        for a in (e.t, e.inputs, e.outputs):
            arr = np.ascontiguousarray(np.asarray(a, dtype=np.float64))
            h.update(str(arr.shape).encode())
            h.update(arr.tobytes())
    return h.hexdigest()
