"""The extension: the accepted findings applied to the IR — ``learn`` functions merged per target and per input set,
new links and radiation, sensor offsets and lags, thermal masses, capacities behind sources, inputs for the data
columns they read — with the fitted values in the new parameters, printed as ``.thn`` by
:func:`tnn_dsl.lang.print_thn` and checked by parsing it."""

from __future__ import annotations

import difflib
import os

from ..ir import LearnFunction, LearnInput, LearnTarget, Link, Network, Num, Param, Radiation
from ..lang import parse_quantity, print_thn, unit_scale
from .base import STRUCTURAL_KINDS, Candidate, _unique_name
from .structural import _scalar as _value

__all__ = ["extend_network", "finding_clause", "extension_text", "doctor_targets", "changed_lines"]

_DEPENDENCE_KINDS = ("param_dependence", "wrong_constant", "heat_load", "unused_column")


def _num(value_si: float, unit: str | None, digits: int) -> Num:
    """``value_si`` as a literal in ``unit`` (``None``: a plain number) rounded to ``digits`` significant digits
    there (``0.0123 W/K``, ``3.2 kWh/K``): what a person would write, not the fit's last digits."""
    if unit is None:
        return Num(value=float(f"{value_si:.{digits}g}"))
    scale, offset = unit_scale(unit)
    value, dim = parse_quantity(float(f"{(value_si - offset) / scale:.{digits}g}"), unit)
    return Num(value=value, dim=dim, unit=unit)


def _plain_unit(net: Network, pname: str | None, fallback: str) -> str:
    """The unit the file writes parameter ``pname`` in, if it is a plain factor (``kWh/K``, ``K/kW``), else
    ``fallback`` (SI)."""
    try:
        unit = net.param(pname).unit if pname else None
        if unit and unit_scale(unit)[1] == 0.0 and unit_scale(unit)[0] > 0:
            return unit
    except (KeyError, ValueError):
        pass
    return fallback


def _set(net: Network, name: str, num: Num, **update) -> Network:
    """``net`` with constant ``name`` set to ``num`` (and ``update`` applied: label, bounds ...)."""
    params = [p.model_copy(update={"expr": num, "dim": dict(num.dim), "unit": num.unit, **update})
              if p.name == name else p for p in net.params]
    return net.model_copy(update={"params": params})


def _fitted_structural(net: Network, c: Candidate, params: dict) -> Network:
    """A structural edit already in ``net`` (:func:`~tnn_dsl.doctor.structural.apply_structural`) with its fitted
    values: the lag (s), the mass's capacity (in its neighbour's capacity unit) and share, the capacity behind
    a source and its resistance (in the file's units). One-sided bounds of the fit are dropped (the language has
    none)."""
    el = c.element
    if c.kind == "sensor_lag":
        return _set(net, el["param"], _num(_value(params, el["param"], net), "s", 4), lower=None, upper=None)
    if c.kind == "thermal_mass":
        cap_of = {n.name: n.capacitance for n in net.nodes}
        unit = _plain_unit(net, cap_of.get(el["a"]), "J/K")
        net = _set(net, el["param"], _num(_value(params, el["param"], net), unit, 6), lower=None, upper=None)
        f = net.param(el["frac"])
        net = _set(net, el["frac"], _num(_value(params, el["frac"], net), None, 4), lower=f.lower, upper=f.upper)
        total = net.param(el["value"])
        return _set(net, el["value"], total.expr, label=f"total of the links {el['a']}–{el['node']}–{el['b']}")
    if c.kind == "source_mass":
        cap_of = {n.name: n.capacitance for n in net.nodes}
        unit_c = _plain_unit(net, cap_of.get(el["at"]), "J/K")
        r_link = next((lk.value for lk in net.links if lk.form == "R" and lk.name != el["link"]
                       and net.param(lk.value).unit), None)
        unit_r = _plain_unit(net, r_link, "K/W")
        net = _set(net, el["param"], _num(_value(params, el["param"], net), unit_c, 6), lower=None, upper=None)
        return _set(net, el["res"], _num(_value(params, el["res"], net), unit_r, 6), lower=None, upper=None)
    raise ValueError(f"not a structural candidate kind: {c.kind}")


def _merged_learned(net: Network, cands: list[Candidate]) -> list[LearnFunction]:
    """The learned functions of ``net`` and one new ``learn`` per group of dependence candidates: candidates on
    the same target merge into one function of all their variables (``learn R as linear(u1, hx1)``; ``poly(…; degree
    = 2)`` when one of them is quadratic or a product), targets
    with the same variables share one function, a target without variables is ``const``. A learned constant of
    ``net`` whose targets now depend on something keeps its other targets."""
    by_target: dict[str, list[tuple[str, str]]] = {}
    curved: set[str] = set()  # targets with a quadratic or product dependence: written as poly(…; degree = 2)
    for c in cands:
        vars_ = by_target.setdefault(c.target, [])
        vars_ += [v for v in c.vars if v not in vars_]
        if c.element.get("shape") in ("quadratic", "product"):
            curved.add(c.target)
    groups: dict[tuple, list[str]] = {}
    for target, vars_ in by_target.items():
        groups.setdefault((tuple(vars_), target in curved), []).append(target)
    moved: dict[str, set[str]] = {}
    for c in cands:
        if c.element.get("learned"):
            moved.setdefault(c.element["learned"], set()).add(c.target)
    learned = []
    for fn in net.learned:
        keep = [t for t in fn.targets if t.name not in moved.get(fn.name, set())]
        if keep:
            learned.append(fn.model_copy(update={"targets": keep}) if len(keep) < len(fn.targets) else fn)
    taken = {fn.name for fn in learned} | set(net.param_names)
    for (key, bent), targets in groups.items():
        first = "".join(ch if ch.isalnum() else "_" for ch in targets[0]).strip("_")
        out = [LearnTarget(kind="heat_load", name=t[2:-1]) if t.startswith("Q[") and t.endswith("]")
               else LearnTarget(kind="param", name=t) for t in targets]
        kind = "poly" if bent else "linear" if key else "const"
        learned.append(LearnFunction(name=_unique_name(f"fn_{first}", taken), kind=kind, degree=2 if bent else None,
                                     targets=out, inputs=[LearnInput(kind=k, name=v) for k, v in key]))
    return learned


def _with_element(net: Network, c: Candidate, params: dict, taken: set[str]) -> Network:
    """``net`` with a new conductance (W/K), radiation (its area in m², emissivity 1) or sensor offset (K), free,
    at its fitted value."""
    el = c.element
    if c.kind == "missing_link":
        g = _num(max(_value(params, el["param"], net), 1e-9), "W/K", 4)
        name = _unique_name(f"G_{el['a']}_{el['b']}", taken)
        p = Param(name=name, expr=g, dim=dict(g.dim), unit=g.unit, role="conductance", free=True,
                  owner=f"link {name}")
        link = Link(name=name, a=el["a"], b=el["b"], form="G", value=name)
        return net.model_copy(update={"params": [*net.params, p], "links": [*net.links, link]})
    if c.kind == "radiation":
        area = _num(max(_value(params, el["param"], net), 1e-9), "m^2", 4)
        name = _unique_name(f"rad_{el['a']}_{el['b']}", taken)
        owner = f"radiation {name}"
        new = [Param(name=f"{name}.area", expr=area, dim=dict(area.dim), unit=area.unit, role="component", free=True,
                     owner=owner),
               Param(name=f"{name}.emissivity", expr=Num(value=1.0), role="component", owner=owner),
               Param(name=f"{name}.view_factor", expr=Num(value=1.0), role="component", owner=owner)]
        rad = Radiation(name=name, a=el["a"], b=el["b"], area=f"{name}.area", emissivity=f"{name}.emissivity",
                        view_factor=f"{name}.view_factor")
        return net.model_copy(update={"params": [*net.params, *new], "radiations": [*net.radiations, rad]})
    if c.kind == "sensor_offset":
        off = _num(_value(params, el["param"], net), "K", 4)
        p = Param(name=el["param"], expr=off, dim=dict(off.dim), unit="K", role="offset", free=True,
                  owner=f"sensor {c.target}")
        sensors = [s.model_copy(update={"offset": el["param"]}) if s.name == c.target else s for s in net.sensors]
        return net.model_copy(update={"params": [*net.params, p], "sensors": sensors})
    return net


def extend_network(base: Network, accepted: list[Candidate], params: dict,
                   unused: list[tuple[str, str]] = ()) -> Network:
    """The extended network: ``base`` (the user's network, with the inputs of the unused data columns and the
    accepted structural edits already built in, as the doctor fits it) with every accepted finding applied and
    the fitted values (``params``: the engine's parameter dict, SI) in its new parameters. Of the ``unused``
    columns' inputs (name, column), only those an accepted finding reads are kept."""
    net = base
    for c in accepted:
        if c.kind in STRUCTURAL_KINDS:
            net = _fitted_structural(net, c, params)
    dependences = [m for c in accepted if c.kind in _DEPENDENCE_KINDS for m in c.members]
    net = net.model_copy(update={"learned": _merged_learned(net, dependences)})
    taken = set(net.param_names) | {p.split(".")[0] for p in net.param_names} | set(net.node_names)
    taken |= set(net.boundary_names) | {e.name for e in (*net.links, *net.radiations, *net.sensors)}
    for c in accepted:
        net = _with_element(net, c, params, taken)
    used = {v for c in accepted for k, v in c.vars if k == "input"}
    drop = {name for name, _ in unused} - used
    return net.model_copy(update={"inputs": [i for i in net.inputs if i.name not in drop]}, deep=True)


def doctor_targets(accepted: list[Candidate]) -> set[str]:
    """The targets of the ``learn`` functions the extension adds (``R_hp1``, ``Q[hx2]``): the keys of
    :meth:`Network.learned_targets` the MLP comparison may turn into MLPs."""
    return {m.target for c in accepted if c.kind in _DEPENDENCE_KINDS for m in c.members}


def changed_lines(before: Network, after: Network) -> list[str]:
    """The statements of ``after``, printed, that ``before`` printed does not have (new or changed lines)."""
    old = set(print_thn(before).splitlines())
    return [ln for ln in print_thn(after).splitlines() if ln and ln not in old]


def finding_clause(base: Network, c: Candidate, params: dict, edited: Network | None = None) -> str:
    """A finding's ``.thn`` change: the statements its extension adds or changes, ``; ``-joined (``base``: the
    network it was fitted on; ``edited``: a structural candidate's own network)."""
    after = extend_network(edited if edited is not None else base, [c], params)
    return "; ".join(changed_lines(base, after))


def extension_text(original: Network, extended: Network, accepted: list[Candidate],
                   source: str | None = None) -> tuple[str, str]:
    """The extension's ``.thn`` text (a comment naming the accepted findings, then the printed network) and a
    unified diff from the printed original to the printed extension (only the change shows)."""
    head = [f"# {original.name}" + (f" ({os.path.basename(source)})" if source else "")
            + " extended by `tnnc diagnose` with the accepted findings:"]
    head += [f"#   {c.describe()}" for c in accepted]
    printed = print_thn(extended)
    diff = "".join(difflib.unified_diff(print_thn(original).splitlines(True), printed.splitlines(True),
                                        "original", "extended"))
    return "\n".join(head) + "\n" + printed, diff


def _check_text(text: str, filename: str) -> Network:
    """Re-load the extension to make sure it is a valid ``.thn`` (a failure here is a bug: say so); returns it."""
    from ..lang import loads

    return loads(text, filename=filename)
