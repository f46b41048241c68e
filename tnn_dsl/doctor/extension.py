"""The extension: accepted findings as `learn` clauses (merged per target and per input set) and the extended
`.thn` text, checked by parsing it."""

from __future__ import annotations

import re

import numpy as np

from ..ir import Network
from .base import Candidate, Extended
from .engine import _Engine
from .words import _var_text


def _clause(c: Candidate, params, ext: Extended, eng: _Engine) -> str:
    net = ext.network
    if c.kind in ("param_dependence", "wrong_constant"):
        if not c.vars:
            return f"learn {c.target} as const"
        return f"learn {c.target} as linear({', '.join(_var_text(net, k, v) for k, v in c.vars)})"
    if c.kind in ("heat_load", "unused_column"):
        if not c.vars:
            return f"learn {c.target} as const"
        return f"learn {c.target} as linear({', '.join(_var_text(net, k, v) for k, v in c.vars)})"
    if c.kind == "missing_link":
        g = float(np.asarray(params[c.element["param"]]).reshape(-1)[0])
        a, b = (_var_text(net, "node", c.element["a"]), c.element["b"])
        b = _var_text(net, "node", b) if b in net.node_names else b
        return f"G {c.element['a']} -- {c.element['b']} = {max(g, 1e-9):.4g} W/K  free"
    if c.kind == "radiation":
        a = float(np.asarray(params[c.element["param"]]).reshape(-1)[0])
        return (f"radiation {c.element['a']} -- {c.element['b']}  area = {max(a, 1e-9):.4g} m^2 free"
                f"  emissivity = 1")
    if c.kind == "sensor_offset":
        o = float(np.asarray(params[c.element["param"]]).reshape(-1)[0])
        return f"offset {o:.4g} K free"
    if c.kind == "sensor_lag":
        tau = float(np.asarray(params[c.element["param"]]).reshape(-1)[0])
        return f"lag {tau:.4g} s free"
    if c.kind == "thermal_mass":  # the new node and the two links (the .thn extension has the parameters too)
        from .structural import mass_lines

        return "; ".join(mass_lines(net, c, params)[2:])
    if c.kind == "source_mass":  # the new node and its link (the source's line moves to the new node)
        from .structural import source_mass_lines

        return "; ".join(source_mass_lines(net, c, params))
    return ""


def _merged_clauses(accepted: list[Candidate], params, ext: Extended, eng: _Engine) -> list[str]:
    """One clause per target: dependence candidates on the same target merge into one function with
    several inputs (``learn R as linear(u1, T(hx1))``); targets with the same inputs share one clause."""
    by_target: dict[str, list[Candidate]] = {}
    order: list[str] = []
    out: list[str] = []
    for c in accepted:
        if c.kind in ("param_dependence", "wrong_constant", "heat_load", "unused_column"):
            if c.target not in by_target:
                order.append(c.target)
            by_target.setdefault(c.target, []).append(c)
    groups: dict[tuple, list[str]] = {}
    gorder: list[tuple] = []
    net = ext.network
    for tgt in order:
        vars_: list[tuple[str, str]] = []
        for c in by_target[tgt]:
            for v in c.vars:
                if v not in vars_:
                    vars_.append(v)
        key = tuple(vars_)
        if key not in groups:
            gorder.append(key)
        groups.setdefault(key, []).append(tgt)
    for key in gorder:
        tg = ", ".join(groups[key])
        if key:
            out.append(f"learn {tg} as linear({', '.join(_var_text(net, k, v) for k, v in key)})")
        else:
            out.append(f"learn {tg} as const")
    for c in accepted:
        if c.kind in ("missing_link", "radiation"):
            out.append(_clause(c, params, ext, eng))
    for c in accepted:
        if c.kind == "thermal_mass":  # the split link's value, the share f, the new node, the two new links
            from .structural import mass_lines

            out += mass_lines(net, c, params)
    for c in accepted:
        if c.kind == "source_mass":  # the new node and its link; the source's own line is moved in the text
            from .structural import source_mass_lines

            out += source_mass_lines(net, c, params)
    return out


def _extend_text(text: str, clauses: list[str], accepted: list[Candidate], net: Network, params, ext, unused):
    """The input text plus the chosen clauses (and sensor offsets edited in place); a unified diff."""
    import difflib

    if not accepted:
        return text, ""
    lines = text.splitlines()
    for c in accepted:
        if c.kind not in ("sensor_offset", "sensor_lag"):
            continue
        s = next(s for s in net.sensors if s.name == c.target)
        o = float(np.asarray(params[c.element["param"]]).reshape(-1)[0])
        if s.span is not None and 1 <= s.span.line <= len(lines):
            ln = lines[s.span.line - 1]
            m = re.search(r"\bcolumn\b", ln)
            ins = f"offset {o:.4g} K free  " if c.kind == "sensor_offset" else f"lag {o:.4g} s free  "
            lines[s.span.line - 1] = (ln[: m.start()] + ins + ln[m.start():]) if m else ln.rstrip() + "  " + ins.strip()
    # a thermal mass replaces its link: the original line is commented out (its value is a `param` line now)
    for c in accepted:
        if c.kind != "thermal_mass":
            continue
        link = next((l for l in net.links if l.name == c.element["link"]), None)
        if link is None or link.span is None:
            continue
        for ln in range(link.span.line, link.span.end_line + 1):
            if 1 <= ln <= len(lines):
                lines[ln - 1] = (f"# (split by `tnnc diagnose` at the new thermal mass {c.element['node']}, see below) "
                                 + lines[ln - 1])
    # a capacity behind a source: the source's line now heats the new node (or, if the line has another form,
    # it is commented out and written again below)
    moved_src: list[str] = []
    for c in accepted:
        if c.kind != "source_mass":
            continue
        from .structural import source_line_moved

        src = next((sr for sr in net.sources if sr.name == c.element["source"]), None)
        if src is None or src.span is None or not 1 <= src.span.line <= len(lines):
            continue
        new_line = source_line_moved(lines[src.span.line - 1], c) if src.span.line == src.span.end_line else None
        if new_line is not None:
            lines[src.span.line - 1] = new_line
        else:
            for ln in range(src.span.line, src.span.end_line + 1):
                lines[ln - 1] = f"# (moved by `tnnc diagnose` to the new node {c.element['node']}, see below) " + lines[ln - 1]
            moved_src.append(f"source {c.element['node']} = {c.element['value']}")
    # a learned constant of the original network that now depends on something: its clause is replaced
    # (the dependent targets get their own clause; the others stay constant)
    for fname in dict.fromkeys(c.element.get("learned") for c in accepted if c.element.get("learned")):
        fn = next((f for f in net.learned if f.name == fname), None)
        if fn is None or fn.span is None:
            continue
        moved = {c.target for c in accepted if c.element.get("learned") == fname}
        for ln in range(fn.span.line, fn.span.end_line + 1):
            if 1 <= ln <= len(lines):
                lines[ln - 1] = "# (replaced by `tnnc diagnose`, see below) " + lines[ln - 1]
        rest = [t.name for t in fn.targets if t.name not in moved]
        if rest:
            clauses = [f"learn {', '.join(rest)} as {fn.kind}"] + list(clauses)
    used_inputs = {v for c in accepted for k, v in c.vars if k == "input"}
    add = ["", "# ---- added by `tnnc diagnose` -------------------------------------------------"]
    for name, col in unused:
        if name in used_inputs:
            add.append(f'input {name} : [1]  column "{col}"')
    for c in accepted:
        add.append(f"# {c.describe()}")
    add += clauses + moved_src
    new = "\n".join(lines).rstrip("\n") + "\n" + "\n".join(add) + "\n"
    diff = "".join(difflib.unified_diff(text.splitlines(True), new.splitlines(True), "original", "extended"))
    return new, diff


def _check_text(text: str, filename: str) -> None:
    """Re-load the extension to make sure it is a valid ``.thn`` (a failure here is a bug: say so)."""
    from ..lang import loads

    loads(text, filename=filename)
