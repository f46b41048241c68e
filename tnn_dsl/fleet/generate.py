"""A synthetic fleet of TCLab-like boards for tests and the benchmark: a product line with manufacturing spread,
some units with a planted fault of one of the doctor's kinds, sensor noise.

Every board is the two-heater network of ``networks/tclab/tclab_fleet.thn`` (the fleet's template: heaters
apart, no conduction between them; datasheet heater gains; capacities, conductances to ambient and the ambient
fitted per unit), simulated from its own truth: capacities, conductances and heater gains spread uniformly by
±``spread`` around the template's values, an ambient between 21 and 25 °C, the board switched on cold (at
ambient). A faulty unit's truth has one more element:

========================  ==============================================================================
``dependence``            ``U1`` grows with the heater's temperature: ``U1·(1 + 0.01 1/K·(T(h1) − Ta))``
``heat_load``             heater 1's command also heats h2: ``source h2 = 0.003 W/% · Q1``
``sensor_lag``            ``T1`` lags its heater by 25 s
``missing_link``          the heaters touch: ``G h1 -- h2 = 0.01 W/K``
``sensor_offset``         ``T1`` reads 0.5 K high
========================  ==============================================================================

The heater gains are not identifiable apart from the capacity and conductance they heat (the data hold the
command, not the power), so the template fixes them at the datasheet's values and the truth of what a unit's fit
can recover is the *apparent* capacity and conductance, ``C·a_nom/a`` and ``U·a_nom/a``: ``truth.json`` holds both.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..core import Diagnostic, TnnError

__all__ = ["FAULT_KINDS", "generate_fleet", "TEMPLATE", "template_path"]

FAULT_KINDS = ("dependence", "heat_load", "sensor_lag", "missing_link", "sensor_offset")
"""The faults a generated unit may carry (module docstring)."""

NOMINAL = {"C1": 4.0, "C2": 4.0, "U1": 0.02, "U2": 0.02, "a1": 0.01, "a2": 0.0075}
"""The template's values (J/K, W/K, W/%)."""

EXPECTED = {"dependence": ("param_dependence", "U1"), "heat_load": ("heat_load", "Q[h2]"),
            "sensor_lag": ("sensor_lag", "T1"), "missing_link": ("missing_link", "h1--h2"),
            "sensor_offset": ("sensor_offset", "T1")}
"""What the doctor should name for each fault: ``(kind, target)`` of its finding."""

TEMPLATE = "tclab/tclab_fleet.thn"


def template_path() -> Path:
    """The fleet template shipped with the package (``networks/tclab/tclab_fleet.thn``)."""
    from ..studies.casestudy import network_path

    return network_path(TEMPLATE)


_TRUTH = """network board_truth "one generated board"
units temperature = degC
input Q1 : [%]  column "Q1_pct"
input Q2 : [%]  column "Q2_pct"
param Ta = {Ta!r} degC
param a1 = {a1!r} W/%
param a2 = {a2!r} W/%
boundary amb = Ta
node h1 C = {C1!r} J/K
node h2 C = {C2!r} J/K
G h1 -- amb = {G1} as U1
G h2 -- amb = {U2!r} W/K as U2
source h1 = a1 * Q1
source h2 = {S2}
sensor T1 = h1 {T1} column "T1_degC"
sensor T2 = h2 column "T2_degC"
{extra}
"""


def _truth_text(p: dict[str, float], fault: str | None) -> str:
    g1, s2, t1, extra = f"{p['U1']!r} W/K", "a2 * Q2", "", ""
    if fault == "dependence":
        g1 = f"{p['U1']!r} W/K * (1 + 0.01 1/K * (T(h1) - Ta))"
    elif fault == "heat_load":
        s2 = "a2 * Q2 + 0.003 W/% * Q1"
    elif fault == "sensor_lag":
        t1 = "lag 25 s"
    elif fault == "sensor_offset":
        t1 = "offset 0.5 K"
    elif fault == "missing_link":
        extra = "G h1 -- h2 = 0.01 W/K as U12"
    elif fault is not None:
        raise TnnError(Diagnostic(f"unknown fault kind {fault!r}", hint=f"one of {', '.join(FAULT_KINDS)}"))
    return _TRUTH.format(G1=g1, S2=s2, T1=t1, extra=extra, **p)


def _commands(rng: np.random.Generator, n: int) -> np.ndarray:
    """Heater commands (n, 2) %: steps held 60–300 s at levels 0–100 %, both heaters off for the first 60 s."""
    u = np.zeros((n, 2))
    for j in range(2):
        k = 60
        while k < n:
            h = int(rng.integers(60, 301))
            u[k:k + h, j] = rng.uniform(0.0, 100.0)
            k += h
    return u


def generate_fleet(out: str | os.PathLike, n_units: int = 20, n_faulty: int = 4, *, noise: float = 0.02,
                   spread: float = 0.1, n_train: int = 1800, n_val: int = 900, seed: int = 0,
                   kinds: tuple[str, ...] = FAULT_KINDS, force: bool = False) -> dict[str, Any]:
    """Write a fleet directory ``out`` (one sub-directory per unit, ``train.csv`` and ``val.csv`` at 1 s) and
    ``out/truth.json`` (per unit: its fault or ``null``, its true and apparent parameters). The faulty units are
    drawn at random (seeded), their kinds cycling through ``kinds``. Returns the truth."""
    from ..compiler import compile as compile_network
    from ..core import check_output
    from ..core.files import OutputKind
    from ..lang import loads
    from ..lang.units import unit_scale

    if n_units < 1 or not (0 <= n_faulty <= n_units):
        raise TnnError(Diagnostic(f"a fleet of {n_units} units with {n_faulty} faulty ones is not possible",
                                  hint="ask for at least one unit and at most as many faulty ones as units"))
    kind = OutputKind("generated fleet directory", is_dir=True, example="fleet/",
                      ours=lambda p: (p / "truth.json").is_file())
    outp = check_output(out, kind, force=force)
    rng = np.random.default_rng(seed)
    faulty = set(rng.choice(n_units, size=n_faulty, replace=False).tolist()) if n_faulty else set()
    order = sorted(faulty)
    fault_of = {i: kinds[k % len(kinds)] for k, i in enumerate(order)}
    width = max(3, len(str(n_units)))
    truth: dict[str, Any] = {"noise_K": noise, "spread": spread, "seed": seed, "n_train": n_train, "n_val": n_val,
                             "units": {}}
    outp.mkdir(parents=True, exist_ok=True)
    models: dict[str | None, Any] = {}
    for i in range(n_units):
        name = f"board-{i:0{width}d}"
        p = {k: v * (1.0 + rng.uniform(-spread, spread)) for k, v in NOMINAL.items()}
        p["Ta"] = float(rng.uniform(21.0, 25.0))
        fault = fault_of.get(i)
        net = loads(_truth_text(p, fault), f"<{name} truth>")
        # the units of one kind differ only in their values: one compiled model (and its compiled rollouts) for all
        # of them, each unit's values as its parameters (a model per unit compiled its rollouts again: 0.7 s a unit)
        if fault not in models:
            models[fault] = compile_network(net, backend="jax", dtype="float64")
        model = models[fault]
        own = compile_network(net, backend="jax", dtype="float64")
        params = model.from_numpy(own.to_numpy(own.init_params(seed=0)))
        B = model.xp
        d = outp / name
        d.mkdir(exist_ok=True)
        for part, n in (("train", n_train), ("val", n_val)):
            U = _commands(rng, n)
            Usi = U * np.array([unit_scale(i.unit)[0] if i.unit else 1.0 for i in net.inputs])  # % -> fraction
            T0 = model.steady_state(params, B.asarray(Usi[0]))
            _, y = model.rollout(params, T0, B.asarray(Usi), 1.0)
            y = np.asarray(B.to_numpy(y)) - 273.15 + rng.normal(0.0, noise, (n, 2))
            rows = ["time_s,Q1_pct,Q2_pct,T1_degC,T2_degC"]
            rows += [f"{k},{U[k, 0]:.3f},{U[k, 1]:.3f},{y[k, 0]:.5f},{y[k, 1]:.5f}" for k in range(n)]
            (d / f"{part}.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
        apparent = {"C_h1": p["C1"] * NOMINAL["a1"] / p["a1"], "C_h2": p["C2"] * NOMINAL["a2"] / p["a2"],
                    "U1": p["U1"] * NOMINAL["a1"] / p["a1"], "U2": p["U2"] * NOMINAL["a2"] / p["a2"],
                    "Ta": p["Ta"] + 273.15}
        truth["units"][name] = {"fault": fault, "expected": list(EXPECTED[fault]) if fault else None,
                                "true": p, "apparent": apparent}
    (outp / "truth.json").write_text(json.dumps(truth, indent=1), encoding="utf-8")
    return truth
