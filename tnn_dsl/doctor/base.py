"""What a candidate is: :class:`Candidate` (kind, target, what it depends on, its columns), :class:`Column`, the
:class:`Extended` network holding candidates, the candidate kinds, and the name helpers every kind uses."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from ..ir import (
    Network,
    Ref,
    Temp,
    walk,
)

__all__ = ["STRUCTURAL_KINDS", "BOUNDED_AT_ZERO_KINDS", "MASS_FRACTION_BOUNDS", "Column", "Candidate", "Extended",
           "refs_in", "temps_in", "element_value", "var_label", "fn_name"]

STRUCTURAL_KINDS = ("sensor_lag", "thermal_mass", "source_mass")
# exactly-null candidates whose one new parameter starts at its lower bound 0 (a conductance, a radiating area)
BOUNDED_AT_ZERO_KINDS = ("missing_link", "radiation")


MASS_FRACTION_BOUNDS = (0.05, 0.95)
"""Bounds of a thermal-mass candidate's ``f`` (the share of the split link's resistance on the ``a`` side):
at f → 0 or 1 the new node merges into a neighbour and its capacity stops being identifiable."""


# parameter roles a dependence / wrong-constant candidate may target
_DEP_ROLES = ("resistance", "conductance", "capacitance", "component", "heat_flow", "generic")


_K_DIM = {"K": 1.0}


_GK_DIM = {"kg": 1.0, "m": 2.0, "s": -3.0, "K": -1.0}  # W/K


_AREA_DIM = {"m": 2.0}


@dataclass(frozen=True)
class Column:
    """One scalar of the compiled model's parameter dict: ``params[key].ravel()[index]``."""

    key: str
    index: int = 0


@dataclass
class Candidate:
    """One exactly-null deficiency. ``columns`` are its new parameters (k = len(columns)).

    ``kind`` see module doc; ``target`` a parameter name, ``Q[node]``, ``a--b`` or a sensor name;
    ``depends_on`` the variables (input names or ``T(node)``) its value depends on."""

    kind: str
    target: str
    depends_on: list[str]
    columns: list[Column]
    fn: str | None = None  # the extended network's learned function holding it (param/heat-load kinds)
    vars: list[tuple[str, str]] = field(default_factory=list)  # (kind "node"|"input", name) for learn inputs
    element: dict = field(default_factory=dict)  # extra info (link ends, sensor, ...)

    @property
    def k(self) -> int:
        return len(self.columns)

    @property
    def key(self) -> str:
        dep = ",".join(self.depends_on)
        return f"{self.kind}:{self.target}:{dep}"

    @property
    def members(self) -> list["Candidate"]:
        """The per-target candidates this one stands for: itself, or the parts of a whole learned function's
        dependence (``R_hp1, R_hp2, R_hpa depend together on u1``: one candidate per target, one column each)."""
        return list(self.element.get("members") or [self])

    def describe(self) -> str:
        words = {
            "param_dependence": f"{self.target} "
            f"{'depend together' if len({m.target for m in self.members}) > 1 else 'depends'}"
            f" on {', '.join(self.depends_on)}",
            "wrong_constant": f"{self.target} has the wrong value",
            "heat_load": f"unmodelled heat load at {self.target[2:-1]}"
            + (f" depending on {', '.join(self.depends_on)}" if self.depends_on else " (constant)"),
            "missing_link": f"missing conduction path {self.target}",
            "radiation": f"missing radiation {self.target}",
            "sensor_offset": f"offset on sensor {self.target}",
            "sensor_lag": f"sensor {self.target} lags its node {self.element.get('node', '')}",
            "thermal_mass": f"missing thermal mass between {self.element.get('a', '')} and"
            f" {self.element.get('b', '')} (on link {self.element.get('link', '')})",
            "source_mass": f"missing heat capacity behind source {self.target} (between it and node"
            f" {self.element.get('at', '')})",
            "unused_column": f"heat load at {self.target[2:-1]} driven by unused data column"
            f" {', '.join(self.depends_on)}",
        }
        return words.get(self.kind, f"{self.kind} {self.target}")


@dataclass
class Extended:
    """The extended network (original + every candidate at its null value) and the candidates.
    ``stats`` holds, per learned function of the extension, the variables of its inputs in order."""

    network: Network
    candidates: list[Candidate]
    fn_vars: dict[str, list[tuple[str, str]]]
    replaced: dict[str, str] = field(default_factory=dict)
    """Learned functions of the original network whose kind the extension changed (name → old kind)."""
    candidate_keys: set[str] = field(default_factory=set)
    """Parameter-dict keys whose scalars are candidate columns (never fitted as nominal free params)."""


def refs_in(expr) -> set[str]:
    """Names referenced (``Ref``) in an expression tree."""
    return {e.name for e in walk(expr) if isinstance(e, Ref)}


def temps_in(expr) -> set[str]:
    """Nodes whose temperature (``Temp``) an expression reads."""
    return {e.node for e in walk(expr) if isinstance(e, Temp)}


def var_label(kind: str, name: str) -> str:
    """How a variable is named in findings: an input by its name, a node temperature as ``T(node)``."""
    return f"T({name})" if kind == "node" else name


def fn_name(target: str) -> str:
    """The extended network's learned-function name for a target (an identifier)."""
    return "dx_" + re.sub(r"[^A-Za-z0-9_]", "_", target)


def element_value(params: dict, c: Candidate) -> float:
    """The fitted value (SI) of the one parameter a single-parameter candidate adds
    (``c.element["param"]``: a missing link's G, a radiation area, a sensor offset or lag)."""
    return float(np.asarray(params[c.element["param"]]).reshape(-1)[0])


def _unique_name(name: str, taken: set[str]) -> str:
    """``name``, or ``name_2``, ``name_3`` … the first not in ``taken``; the result is added to ``taken``
    (names the doctor adds to a network never shadow the user's)."""
    base, i = name, 2
    while name in taken:
        name = f"{base}_{i}"
        i += 1
    taken.add(name)
    return name
