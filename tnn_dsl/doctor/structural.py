"""Structural candidates, not exactly null: a sensor lag, a missing thermal mass on a link, a heat capacity behind a
source. Each is an IR edit of its own network (:func:`apply_structural`) with its starting values; once fitted,
:func:`tnn_dsl.doctor.extension.extend_network` writes the fitted values into it and the printer writes it."""

from __future__ import annotations

import numpy as np

from ..ir import (
    Binary,
    Link,
    Network,
    Num,
    Param,
    Ref,
    ThermalNode,
)
from .base import MASS_FRACTION_BOUNDS, STRUCTURAL_KINDS, Candidate, Column, _unique_name, refs_in

__all__ = ["structural_candidates", "apply_structural", "mass_values", "source_mass_values"]


def _btemp(net: Network, boundary: str) -> str | None:
    for b in net.boundaries:
        if b.name == boundary:
            return b.temperature
    return None


def _mass_ends(net: Network, link: Link) -> tuple[str, str]:
    """The order ``(a, b)`` of a thermal-mass candidate's target ``a--b``: a node before a boundary; between two
    nodes, a sensed node first (the mass sits "behind" what is measured), then declaration order."""
    nodes = net.node_names
    if link.a not in nodes:
        return link.b, link.a
    if link.b not in nodes:
        return link.a, link.b
    sensed = {s.node for s in net.sensors}
    return tuple(sorted((link.a, link.b), key=lambda n: (n not in sensed, nodes.index(n))))  # type: ignore[return-value]


def _mass_skip(net: Network, link: Link, learned: dict) -> bool:
    """True for links a thermal-mass candidate cannot split cleanly (see :func:`structural_candidates`)."""
    if link.value in learned:
        # the value is a learned function's output: the function is fitted on the whole link; splitting it would
        # need the function on two links (and its training data describe the unsplit link)
        return True
    try:
        p = net.param(link.value)
    except KeyError:
        return True
    if not p.is_constant or not p.value or p.value <= 0:
        # a derived value (a law in inputs, temperatures or other parameters, e.g. 1/(h·A(T))): which of its
        # factors belongs to which side of the new node is not determined by the link; zero or negative
        # values are not conduction paths
        return True
    if "." in link.name or link.name.startswith("G_dx_"):
        # a link inside a subnet instance is written once for every instance (its text cannot be split for one
        # instance); G_dx_ links are the doctor's own candidate links
        return True
    main = net.source_files[0] if net.source_files else None
    if link.span is not None and main is not None and link.span.file != main:
        return True  # written in an included file: the extension cannot edit that line
    return False


def structural_candidates(net: Network, kinds: tuple[str, ...] | None = None) -> list[Candidate]:
    """Candidates that are not exactly null (see module doc): one ``sensor_lag`` per sensor without a lag and
    one ``thermal_mass`` per link (R or G, node–node or node–boundary) whose value is a positive constant (free
    or fixed); links whose value is learned or a derived expression, or written inside a subnet or an
    included file, are skipped (:func:`_mass_skip` says why). Their ``columns`` name the parameters the edited
    network gets (:func:`apply_structural`): ``[lag]``, or ``[C_m, f]`` for a thermal mass."""
    kinds = kinds or STRUCTURAL_KINDS
    out: list[Candidate] = []
    if "sensor_lag" in kinds:
        names = {p.name for p in net.params}
        for sn in net.sensors:
            if sn.lag is not None or sn.node not in net.node_names:
                continue
            lag = f"{sn.name}.lag"
            if lag in names:
                continue
            out.append(Candidate("sensor_lag", sn.name, [], [Column(lag, 0)],
                                 element={"sensor": sn.name, "node": sn.node, "param": lag}))
    if "thermal_mass" in kinds:
        learned = net.learned_targets()
        taken = set(net.param_names) | set(net.node_names) | set(net.boundary_names) | {l.name for l in net.links}
        taken |= set(net.input_names)

        def unique(name: str) -> str:
            return _unique_name(name, taken)

        for link in net.links:
            if _mass_skip(net, link, learned):
                continue
            a, b = _mass_ends(net, link)
            m = unique(f"m_{a}_{b}")
            cap, frac = unique(f"C_{m}"), unique(f"f_{m}")
            l1, l2 = unique(f"{link.form}_{a}_{m}"), unique(f"{link.form}_{m}_{b}")
            out.append(Candidate("thermal_mass", f"{a}--{b}", [], [Column(cap, 0), Column(frac, 0)],
                                 element={"a": a, "b": b, "link": link.name, "value": link.value, "form": link.form,
                                          "node": m, "param": cap, "frac": frac, "links": [l1, l2]}))
    if "source_mass" in kinds:
        learned = net.learned_targets()
        taken = set(net.param_names) | set(net.node_names) | set(net.boundary_names) | {l.name for l in net.links}
        taken |= set(net.input_names)
        main = net.source_files[0] if net.source_files else None
        for src in net.sources:
            if src.node not in net.node_names or src.value in learned or "." in src.name:
                continue  # a boundary, a learned heat flow, or written once for every subnet instance
            if src.span is None or (main is not None and src.span.file != main):
                continue  # no line to edit (built by a tool, or in an included file)
            if not _varies_with_inputs(net, src.value):
                continue  # a constant heat load: a lag behind it is invisible
            m = _unique_name(f"m_{src.name}", taken)
            cap, res = _unique_name(f"C_{m}", taken), _unique_name(f"R_{m}", taken)
            out.append(Candidate("source_mass", src.name, [], [Column(cap, 0), Column(res, 0)],
                                 element={"source": src.name, "at": src.node, "value": src.value, "node": m,
                                          "param": cap, "res": res, "link": res}))
    return out


def _varies_with_inputs(net: Network, pname: str, depth: int = 0) -> bool:
    """Whether parameter ``pname``'s value depends on an input (directly or through other parameters)."""
    if depth > 64:
        return False
    try:
        p = net.param(pname)
    except KeyError:
        return pname in net.input_names
    for r in refs_in(p.expr):
        if r in net.input_names or (r != pname and _varies_with_inputs(net, r, depth + 1)):
            return True
    return False


_J_PER_K = {"kg": 1.0, "m": 2.0, "s": -2.0, "K": -1.0}


def apply_structural(net: Network, cand: Candidate, value: float, lower: float | None = None,
                     frac: float = 0.5, resistance: float | None = None,
                     resistance_lower: float | None = None) -> Network:
    """``net`` with the structural candidate ``cand`` built in, its new parameter(s) ``free``.

    * ``sensor_lag``: the lag ``value`` (s), bounded below by ``lower``.
    * ``thermal_mass``: a node ``m`` of capacity ``value`` (J/K, bounded below by ``lower``) between ``a`` and
      ``b``; the link a–b (value ``P``, a constant) becomes a–m and m–b, ``f·P`` and ``(1−f)·P`` for a resistance,
      ``P/f`` and ``P/(1−f)`` for a conductance (derived parameters: ``P`` stays in the table, free if it was),
      ``f = frac`` free in :data:`MASS_FRACTION_BOUNDS`. The total resistance is ``P`` for every ``f``, so the
      steady state is the original one. The new node is the last state; the links take the place of the old
      one in ``links``.
    * ``source_mass``: a node ``m`` of capacity ``value`` (J/K, bounded below by ``lower``) that the source now
      heats, joined to the source's node by a resistance ``resistance`` (K/W, free, bounded below by
      ``resistance_lower``; the link is appended to ``links``). Same steady state; the new node is the last
      state."""
    if cand.kind == "sensor_lag":
        lag = cand.element["param"]
        dim = {"s": 1.0}
        p = Param(name=lag, expr=Num(value=float(value), dim=dim, unit="s"), dim=dim, unit="s", role="time_constant",
                  free=True, lower=lower, owner=f"sensor {cand.target}")
        sensors = [s.model_copy(update={"lag": lag}) if s.name == cand.target else s for s in net.sensors]
        return net.model_copy(update={"params": list(net.params) + [p], "sensors": sensors}, deep=True)
    if cand.kind == "thermal_mass":
        el = cand.element
        a, b, m, pv = el["a"], el["b"], el["node"], el["value"]
        old = next((l for l in net.links if l.name == el["link"]), None)
        if old is None:
            raise ValueError(f"no link {el['link']!r} in network {net.name!r}")
        base = net.param(pv)
        f_lo, f_hi = MASS_FRACTION_BOUNDS
        ref_f, ref_p = Ref(name=el["frac"], kind="param"), Ref(name=pv, kind="param")
        one_minus_f = Binary(op="-", left=Num(value=1.0), right=ref_f)
        if old.form == "R":
            e1, e2 = Binary(op="*", left=ref_f, right=ref_p), Binary(op="*", left=one_minus_f, right=ref_p)
        else:
            e1, e2 = Binary(op="/", left=ref_p, right=ref_f), Binary(op="/", left=ref_p, right=one_minus_f)
        role = "resistance" if old.form == "R" else "conductance"
        l1, l2 = el["links"]
        new = [
            Param(name=el["param"], expr=Num(value=float(value), dim=_J_PER_K, unit="J/K"), dim=_J_PER_K, unit="J/K",
                  role="capacitance", free=True, lower=lower, owner=f"node {m}"),
            Param(name=el["frac"], expr=Num(value=float(frac)), role="generic", free=True, lower=f_lo, upper=f_hi,
                  label=f"share of {old.name}'s resistance on the {a} side of {m}"),
            Param(name=l1, expr=e1, dim=dict(base.dim), unit=base.unit, role=role, owner=f"link {l1}"),
            Param(name=l2, expr=e2, dim=dict(base.dim), unit=base.unit, role=role, owner=f"link {l2}"),
        ]
        links = []
        for l in net.links:
            if l.name == old.name:
                links += [Link(name=l1, a=a, b=m, form=old.form, value=l1),
                          Link(name=l2, a=m, b=b, form=old.form, value=l2)]
            else:
                links.append(l)
        node = ThermalNode(name=m, capacitance=el["param"], label="thermal mass found by the model doctor")
        return net.model_copy(update={"params": list(net.params) + new, "links": links,
                                      "nodes": list(net.nodes) + [node]}, deep=True)
    if cand.kind == "source_mass":
        el = cand.element
        if resistance is None or not resistance > 0:
            raise ValueError("a source_mass edit needs resistance > 0 (K/W)")
        m, at = el["node"], el["at"]
        if not any(sr.name == el["source"] for sr in net.sources):
            raise ValueError(f"no source {el['source']!r} in network {net.name!r}")
        r_dim = {"kg": -1.0, "m": -2.0, "s": 3.0, "K": 1.0}  # K/W
        new = [
            Param(name=el["param"], expr=Num(value=float(value), dim=_J_PER_K, unit="J/K"), dim=_J_PER_K, unit="J/K",
                  role="capacitance", free=True, lower=lower, owner=f"node {m}"),
            Param(name=el["res"], expr=Num(value=float(resistance), dim=r_dim, unit="K/W"), dim=r_dim, unit="K/W",
                  role="resistance", free=True, lower=resistance_lower, owner=f"link {el['link']}"),
        ]
        sources = [sr.model_copy(update={"node": m}) if sr.name == el["source"] else sr for sr in net.sources]
        node = ThermalNode(name=m, capacitance=el["param"],
                           label=f"heat capacity behind source {el['source']}, found by the model doctor")
        link = Link(name=el["link"], a=m, b=at, form="R", value=el["res"])
        return net.model_copy(update={"params": list(net.params) + new, "links": list(net.links) + [link],
                                      "nodes": list(net.nodes) + [node], "sources": sources}, deep=True)
    raise ValueError(f"not a structural candidate kind: {cand.kind}")


def _scalar(params: dict, name: str, net: Network) -> float:
    if name in params:
        return float(np.asarray(params[name]).reshape(-1)[0])
    return float(net.param(name).value)


def mass_values(net: Network, cand: Candidate, params: dict) -> dict:
    """A fitted thermal mass in SI: ``C`` (J/K), ``f`` (share of the resistance on a's side), ``R`` (the split
    link's total resistance, K/W) and ``tau`` (s), the new node's own time constant ``C·f(1−f)·R``.
    ``net`` is a network holding the edit, ``params`` its numpy parameter values."""
    el = cand.element
    c = _scalar(params, el["param"], net)
    f = _scalar(params, el["frac"], net)
    v = _scalar(params, el["value"], net)
    r = v if el["form"] == "R" else (1.0 / v if v else float("inf"))
    return {"C": c, "f": f, "R": r, "tau": c * f * (1.0 - f) * r}


def source_mass_values(net: Network, cand: Candidate, params: dict) -> dict:
    """A fitted capacity behind a source in SI: ``C`` (J/K), ``R`` (K/W) and ``tau = C·R`` (s)."""
    el = cand.element
    c = _scalar(params, el["param"], net)
    r = _scalar(params, el["res"], net)
    return {"C": c, "R": r, "tau": c * r}
