"""The model doctor's hidden-effect suite (issue 6 acceptance): plant one known deficiency in simulated data,
run ``tnn_dsl.diagnose`` on the nominal network, and score what it names.

    python benchmarks/diagnose_suite.py [--quick [--all-nets]] [--only TEXT] [--seeds N] [--noise 0,0.01,0.05]
                                        [--jsonl FILE] [--resume] [--case-study-time] [--no-write]

Networks (three, as issue 6 asks):

* ``tclab``      TCLab-like two-heater board with fixed realistic values (``tests/hidden_nets/tclab_board.thn``);
                 the missing link is planted on ``tclab_board_nolink.thn`` (U12 left out);
* ``building``   Bacher & Madsen's one-state model Ti with fixed values (``tests/hidden_nets/building_ti.thn``);
                 the missing link is planted on ``building_tite.thn`` (interior–outdoor bypass), the missing
                 thermal mass is an envelope node planted in the middle of the interior–outdoor resistance;
* ``casestudy``  the thesis case study's nominal model (``networks/peltier_heatpipe/nominal.thn``, only the
                 Peltier coefficients free).

Kinds planted (every candidate kind of the doctor, plus the two that are not yet candidates): a parameter that
depends on an input or a temperature, an unmodelled heat load, a missing link, radiation, a sensor offset, a
wrong constant, a data column the model does not use (written to CSV: the doctor only sees unused columns in
files), a sensor lag and a missing thermal mass (both simulated from an edited ``.thn``), and null data sets
(the nominal model + noise only). Inputs are pseudo-random steps (case-study.md style): uniform hold times,
uniform levels in each input's bounds; training and validation sets use different seeds.

Metrics per run:

* ``first``: the doctor's first answer (the finding accepted in round 1, else its best fit of round 1) is the
  planted cause. ``first_eq`` also counts a candidate whose equations are *identical* to the planted one
  (e.g. a constant heat load at a node and a constant error of the source at that node; such pairs cannot be
  told apart by any data and the doctor names the more specific one by its placement rule); every such
  equivalence is listed with its reason in :data:`CASES`.
* ``dep``: the planted dependence variable is among the first answer's ``depends_on`` (kinds with one only).
* ``accepted``: a finding was accepted in round 1 and it is the planted cause (or its identical equivalent).
* ``ratio``: held-out MAE before / after (the whole forward selection); ``above_noise``: the baseline held-out
  MAE is at least 4 × the noise's own MAE (0.8 σ), so halving it is attainable.
* nulls: ``false_accept``: any finding accepted.

Targets (issue 6): first ≥ 90 %, dependence named ≥ 80 %, no accepted finding in ≥ 95 % of null runs, held-out
MAE at least halved (ratio ≥ 2) where the effect stands above the noise. The table goes to ``BENCHMARKS.md``
(section ``diagnosis``). Runs are sequential (the machine is shared); ``--jsonl`` + ``--resume`` keeps finished
runs so a long grid can be continued.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import tempfile
import time
from dataclasses import dataclass

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
NETS = os.path.join(ROOT, "tests", "hidden_nets")
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

NOISES = (0.0, 0.01, 0.05)
K0 = 273.15


@dataclass(frozen=True)
class NetSpec:
    """One network of the suite: its file, the input bounds (SI: fractions for ``[%]``, W, K), the sample
    step (s), the hold times of the steps (samples) and the data lengths (samples), full and quick."""

    path: str
    bounds: dict
    dt: float
    hold: tuple
    n_train: int
    n_val: int
    n_train_quick: int
    n_val_quick: int


NETWORKS: dict[str, NetSpec] = {
    "tclab": NetSpec(os.path.join(NETS, "tclab_board.thn"), {"Q1": (0.0, 1.0), "Q2": (0.0, 1.0)},
                     1.0, (60, 300), 2400, 1200, 900, 450),
    "tclab_nolink": NetSpec(os.path.join(NETS, "tclab_board_nolink.thn"), {"Q1": (0.0, 1.0), "Q2": (0.0, 1.0)},
                            1.0, (60, 300), 2400, 1200, 900, 450),
    # 5-min samples, steps held 1–6 h: heating 0–4 kW, sun 0–0.6 kW/m² (SI W/m²), outdoor −5…10 °C
    "building": NetSpec(os.path.join(NETS, "building_ti.thn"),
                        {"Ta": (K0 - 5, K0 + 10), "Ps": (0.0, 600.0), "Ph": (0.0, 4000.0)},
                        300.0, (12, 72), 2016, 1008, 1008, 504),
    "building_tite": NetSpec(os.path.join(NETS, "building_tite.thn"),
                             {"Ta": (K0 - 5, K0 + 10), "Ps": (0.0, 600.0), "Ph": (0.0, 4000.0)},
                             300.0, (12, 72), 2016, 1008, 1008, 504),
    # case-study.md: I ∈ [0, 3] A, u1 ∈ [0, 1], holds 120–600 s; Ta, Tf1, Tf2 constant 22, 25, 25 °C
    "casestudy": NetSpec(os.path.join(ROOT, "networks", "peltier_heatpipe", "nominal.thn"),
                         {"I": (0.0, 3.0), "u1": (0.0, 1.0), "Ta": (K0 + 22, K0 + 22), "Tf1": (K0 + 25, K0 + 25),
                          "Tf2": (K0 + 25, K0 + 25)},
                         1.0, (120, 600), 3600, 1800, 1800, 900),
}


@dataclass(frozen=True)
class Case:
    """One planted effect. ``plant`` = (candidate kind, target, dependence, strength) for
    ``tnn_dsl.studies.planted.plant`` (strength in the candidate's own coordinates, see there); ``edit`` = a
    structural truth: ``("lag", sensor, seconds)``, ``("mass", node, other, C J/K)`` (a new node in series on
    the link node–other, the link split into two of twice its conductance), ``("quad", node, input, coefficient)``
    (a source ``coefficient·input²``) or ``("truth", file)``; ``column`` = (node, column name, W per unit): a heat
    load driven by a data column the network does not read, or ``("param", parameter, column name, rel)``: the
    parameter scaled by ``1 + rel·column``.
    ``truth`` = (kind, target, dependence or "") the doctor should name; ``equivalent`` its identical-equation
    alternatives (with the reason in ``why``)."""

    net: str
    kind: str
    truth: tuple
    plant: tuple | None = None
    edit: tuple | None = None
    column: tuple | None = None
    equivalent: tuple = ()
    why: str = ""
    then: str = ""  # a curved term (``I²``) the accepted findings should name after the linear law

    @property
    def name(self) -> str:
        return f"{self.net}/{self.kind}"


def _cases() -> list[Case]:
    c = []
    # ---- TCLab-like board ----------------------------------------------------------------------
    c += [
        Case("tclab", "dependence", ("param_dependence", "U1", "T(h1)"),
             plant=("param_dependence", "U1", "T(h1)", 0.3)),
        Case("tclab", "heat_load", ("heat_load", "Q[h2]", "Q1"), plant=("heat_load", "Q[h2]", "Q1", 0.3),
             equivalent=(("param_dependence", "Q_src_h2", "Q1"),),
             why="the source at h2 is a derived heat flow: `Q_src_h2` depending on Q1 adds the same linear term"),
        Case("tclab_nolink", "missing_link", ("missing_link", "h1--h2", ""),
             plant=("missing_link", "h1--h2", None, 0.01)),
        Case("tclab", "radiation", ("radiation", "h1--amb", ""), plant=("radiation", "h1--amb", None, 0.9e-3)),
        Case("tclab", "sensor_offset", ("sensor_offset", "T1", ""), plant=("sensor_offset", "T1", None, 0.5)),
        Case("tclab", "wrong_constant", ("wrong_constant", "U12", ""), plant=("wrong_constant", "U12", None, 0.5)),
        Case("tclab", "unused_column", ("unused_column", "Q[h1]", "fan"), column=("h1", "fan", -0.15),
             equivalent=(("heat_load", "Q[h1]", "fan"), ("param_dependence", "Q_src_h1", "fan")),
             why="a heat load at h1 linear in the column; the source at h1 depending on it is the same term"),
        Case("tclab", "sensor_lag", ("sensor_lag", "T1", ""), edit=("lag", "T1", 25.0)),
        Case("tclab", "thermal_mass", ("thermal_mass", "h1--amb", ""), edit=("mass", "h1", "amb", 3.0)),
        # the heater's own mass (1 J/K behind 10 K/W, τ = 10 s) between the heater power and h1
        Case("tclab", "source_mass", ("source_mass", "Q_src_h1", ""), edit=("source", "h1", "a1 * Q1", 1.0, 10.0)),
        # a fan (a data column the network does not read) raising the convective conductance of heater 1
        Case("tclab", "column_dependence", ("param_dependence", "U1", "fan"), column=("param", "U1", "fan", 1.0)),
        # heater 1's driver warming h2 with the square of its command: the linear law first, then the square
        Case("tclab", "quadratic_load", ("heat_load", "Q[h2]", "Q1"), edit=("quad", "h2", "Q1", "0.6 W"),
             equivalent=(("param_dependence", "Q_src_h2", "Q1"),), then="Q1²",
             why="the source at h2 is a derived heat flow: `Q_src_h2` depending on Q1 adds the same linear term"),
        Case("tclab", "null", ("none", "", "")),
    ]
    # ---- building (Bacher & Madsen Ti) -------------------------------------------------------------
    c += [
        Case("building", "dependence", ("param_dependence", "Ria", "Ta"), plant=("param_dependence", "Ria", "Ta", 0.3)),
        Case("building", "heat_load", ("heat_load", "Q[ti]", "Ta"), plant=("heat_load", "Q[ti]", "Ta", 1.5),
             equivalent=(("param_dependence", "Q_solar", "Ta"),),
             why="the solar source is a derived heat flow at ti: its Ta dependence adds the same linear term; the "
                 "strength is small because the heat load's output scale (C·rms dT/dt) is per sample, not per s"),
        Case("building_tite", "missing_link", ("missing_link", "ti--amb", ""),
             plant=("missing_link", "ti--amb", None, 50.0)),
        Case("building", "radiation", ("radiation", "ti--amb", ""), plant=("radiation", "ti--amb", None, 10.0)),
        Case("building", "sensor_offset", ("sensor_offset", "Ti", ""), plant=("sensor_offset", "Ti", None, 0.5),
             equivalent=(("heat_load", "Q[ti]", ""), ("wrong_constant", "Q_solar", "")),
             why="one linear state started at its steady state: a constant heat load shifts the only sensor by a "
                 "constant, exactly as an offset does"),
        Case("building", "wrong_constant", ("wrong_constant", "Ria", ""), plant=("wrong_constant", "Ria", None, 0.4)),
        Case("building", "unused_column", ("unused_column", "Q[ti]", "Pocc"), column=("ti", "Pocc", 400.0),
             equivalent=(("heat_load", "Q[ti]", "Pocc"), ("param_dependence", "Q_solar", "Pocc")),
             why="a heat load at ti linear in the column; the solar source depending on it is the same term"),
        Case("building", "sensor_lag", ("sensor_lag", "Ti", ""), edit=("lag", "Ti", 1800.0)),
        # an envelope mass (3.8 kWh/K) in the middle of the interior–outdoor resistance: one effect only (the
        # TiTe file of the paper also changes Aw and Ci)
        Case("building", "thermal_mass", ("thermal_mass", "ti--amb", ""), edit=("mass", "ti", "amb", 1.37e7)),
        # the heaters' own mass (0.5 kWh/K behind 1 K/kW, τ = 30 min): Bacher & Madsen's TiTh
        Case("building", "source_mass", ("source_mass", "Q_heat", ""), edit=("source", "ti", "Ph", 1.8e6, 1e-3)),
        # ventilation (a data column the network does not read) lowering the envelope resistance
        Case("building", "column_dependence", ("param_dependence", "Ria", "vent"),
             column=("param", "Ria", "vent", -0.4)),
        # a heat load growing with the square of the heating power (kW): the linear law first, then the square
        Case("building", "quadratic_load", ("heat_load", "Q[ti]", "Ph"), edit=("quad", "ti", "Ph", "0.06 kW/kW^2"),
             equivalent=(("param_dependence", "Q_heat", "Ph"), ("param_dependence", "Q_solar", "Ph")), then="Ph²",
             why="Q_heat or Q_solar depending on Ph adds the same linear heat flow at ti"),
        Case("building", "null", ("none", "", "")),
    ]
    # ---- thesis case study (nominal) ---------------------------------------------------------------
    c += [
        Case("casestudy", "dependence", ("param_dependence", "R_hp1", "u1"),
             plant=("param_dependence", "R_hp1", "u1", 0.5)),
        Case("casestudy", "heat_load", ("heat_load", "Q[hx2]", "I"), plant=("heat_load", "Q[hx2]", "I", 0.5)),
        Case("casestudy", "missing_link", ("missing_link", "hx2--amb", ""),
             plant=("missing_link", "hx2--amb", None, 0.2)),
        Case("casestudy", "radiation", ("radiation", "hs--amb", ""), plant=("radiation", "hs--amb", None, 0.15)),
        Case("casestudy", "sensor_offset", ("sensor_offset", "T_out", ""), plant=("sensor_offset", "T_out", None, 0.3)),
        Case("casestudy", "wrong_constant", ("wrong_constant", "R_hp2", ""),
             plant=("wrong_constant", "R_hp2", None, 2.0)),
        Case("casestudy", "unused_column", ("unused_column", "Q[hx2]", "pump"), column=("hx2", "pump", 1.0)),
        Case("casestudy", "sensor_lag", ("sensor_lag", "T_out", ""), edit=("lag", "T_out", 20.0)),
        Case("casestudy", "thermal_mass", ("thermal_mass", "hx2--hp", ""), edit=("mass", "hx2", "hp", 300.0)),
        # the second fluid's pump speed (a data column the network does not read) changing its heat exchanger's UA
        Case("casestudy", "column_dependence", ("param_dependence", "f2.UA", "pump"),
             column=("param", "f2.UA", "pump", 1.0)),
        # Joule heating of a lead at hx2: a load growing with the square of the current
        Case("casestudy", "quadratic_load", ("heat_load", "Q[hx2]", "I"), edit=("quad", "hx2", "I", "1 W/A^2"),
             then="I²"),
        Case("casestudy", "null", ("none", "", "")),
    ]
    return c


CASES = _cases()


# ---------------------------------------------------------------------------------------------
# data
# ---------------------------------------------------------------------------------------------


def _edit_text(text: str, edit: tuple) -> str:
    """The truth's ``.thn`` text for a structural edit (see :class:`Case`)."""
    if edit[0] == "lag":
        _, sensor, tau = edit
        out, n = re.subn(rf"^(sensor {re.escape(sensor)} = \S+)", rf"\1  lag {tau} s", text, count=1, flags=re.M)
        assert n == 1, f"sensor {sensor} not found"
        return out
    if edit[0] == "mass":
        _, node, other, cap = edit
        # the link node -- other (either order), R or G, becomes node -- mid -- other with half the resistance each
        pat = re.compile(rf"^(R|G) ({re.escape(node)}|{re.escape(other)})\s+--\s+({re.escape(node)}|{re.escape(other)})"
                         rf"\s*=\s*([0-9.eE+-]+)\s*(\S+)(.*)$", re.M)
        m = next(m for m in pat.finditer(text) if {m.group(2), m.group(3)} == {node, other})
        form, value, unit = m.group(1), float(m.group(4)), m.group(5)
        half = value / 2 if form == "R" else value * 2
        mid = f"mass_{node}"
        repl = (f"node {mid} \"planted thermal mass\"  C = {cap} J/K\n"
                f"{form} {node} -- {mid} = {half:.6g} {unit}\n{form} {mid} -- {other} = {half:.6g} {unit}")
        return text[: m.start()] + repl + text[m.end():]
    if edit[0] == "source":
        _, node, expr, cap, res = edit
        mid = f"heater_{node}"
        pat = re.compile(rf"^source {re.escape(node)}(\s*=\s*{re.escape(expr)}\b.*)$", re.M)

        def repl(m):
            return (f"source {mid}{m.group(1)}\nnode {mid} \"planted heat capacity behind the source\"  C = {cap} J/K\n"
                    f"R {mid} -- {node} = {res} K/W")
        out, n = pat.subn(repl, text, count=1)
        assert n == 1, f"source {node} = {expr} not found"
        return out
    if edit[0] == "quad":  # a heat load growing with the square of an input: ``source NODE = COEF * INPUT^2``
        _, node, inp, coef = edit
        return text.rstrip("\n") + f"\nsource {node} = {coef} * {inp}^2  as Q_planted_quadratic\n"
    raise ValueError(edit)


def _simulate(net, u: np.ndarray, dt: float, noise: float, rng) -> np.ndarray:
    """Outputs (N, n_out) K of ``net`` (numpy reference backend, RK4) from the steady state of ``u[0]``."""
    from tnn_dsl.compiler.model import compile as _compile

    m = _compile(net, backend="numpy", dtype="float64")
    p = m.init_params(0)
    _, y = m.rollout(p, m.steady_state(p, u[0]), u, dt)
    y = np.asarray(y, dtype=float)
    return y + rng.normal(0.0, noise, y.shape) if noise > 0 else y


def _inputs(spec: NetSpec, names, n: int, seed: int):
    from tnn_dsl.studies.planted import step_inputs

    return step_inputs(np.random.default_rng(seed), n, spec.bounds, names, spec.hold)


def make_data(case: Case, noise: float, seed: int, quick: bool, workdir: str):
    """(network the doctor sees, train, val): Experiments, or CSV paths for an unused-column case."""
    import tnn_dsl
    from tnn_dsl.data.experiment import Experiment
    from tnn_dsl.studies.planted import plant

    spec = NETWORKS[case.net]
    n_tr, n_va = (spec.n_train_quick, spec.n_val_quick) if quick else (spec.n_train, spec.n_val)
    net = tnn_dsl.load(spec.path)
    if case.kind == "null" or case.plant is not None:
        kind, target, dep, strength = case.plant if case.plant else (None, None, None, 0.0)
        pl = plant(net, spec.bounds, kind, target, dep, strength, n_train=n_tr, n_val=n_va, dt=spec.dt,
                   noise=noise, seed=seed, backend="numpy", hold=spec.hold)
        return net, pl.train, pl.val
    names = net.input_names
    exps = []
    if case.edit is not None:
        text = open(spec.path, encoding="utf-8").read()
        truth = tnn_dsl.load(case.edit[1]) if case.edit[0] == "truth" else tnn_dsl.loads(_edit_text(text, case.edit),
                                                                                         "truth.thn")
        for n, s_in, s_noise in ((n_tr, 1000, 3000), (n_va, 2000, 4000)):
            u = _inputs(spec, names, n, s_in + seed)
            y = _simulate(truth, u, spec.dt, noise, np.random.default_rng(s_noise + seed))
            exps.append(Experiment(name=f"planted-{case.kind}-{seed}", path="<planted>", t=np.arange(n) * spec.dt,
                                   dt=spec.dt, inputs=u, outputs=y, input_names=tuple(names),
                                   output_names=tuple(s.name for s in net.sensors)))
        return net, exps[:1], exps[1:]
    # a data column the model does not read: the truth has it as an input driving a heat load
    from tnn_dsl.data.units import unit_factor
    from tnn_dsl.data.write import write_csv
    from tnn_dsl.ir.network import Binary, Input, Num, Param, Ref, Source

    if case.column[0] == "param":  # a parameter scaled by (1 + rel·column): a fan changing a conductance
        _, target, col, rel = case.column
        factor = Binary(op="+", left=Num(value=1.0), right=Binary(op="*", left=Num(value=float(rel)),
                                                                 right=Ref(name=col, kind="input")))
        params = [p.model_copy(update={"expr": Binary(op="*", left=p.expr, right=factor), "free": False,
                                       "lower": None, "upper": None})
                  if p.name == target else p for p in net.params]
        truth = net.model_copy(update={"inputs": list(net.inputs) + [Input(name=col, column=col, dim={}, unit=None)],
                                       "params": params}, deep=True)
    else:
        node, col, gain = case.column
        pname = f"Q_planted_{col}"
        watt = {"kg": 1.0, "m": 2.0, "s": -3.0}
        q = Param(name=pname, expr=Binary(op="*", left=Num(value=float(gain), dim=watt, unit="W"),
                                          right=Ref(name=col, kind="input")),
                  dim=watt, unit="W", role="heat_flow", owner=f"source {pname}")
        truth = net.model_copy(update={
            "inputs": list(net.inputs) + [Input(name=col, column=col, dim={}, unit=None)],
            "params": list(net.params) + [q],
            "sources": list(net.sources) + [Source(name=pname, node=node, value=pname)],
        }, deep=True)
    paths = []
    for which, n, s_in, s_col, s_noise in (("train", n_tr, 1000, 5000, 3000), ("val", n_va, 2000, 6000, 4000)):
        u = _inputs(spec, names, n, s_in + seed)
        uc = _inputs(NetSpec("", {col: (0.0, 1.0)}, spec.dt, spec.hold, 0, 0, 0, 0), [col], n, s_col + seed)
        y = _simulate(truth, np.concatenate([u, uc], 1), spec.dt, noise, np.random.default_rng(s_noise + seed))
        cols = {}
        for j, i in enumerate(net.inputs):
            cols[i.column] = u[:, j] / (1.0 if i.is_temperature else unit_factor(i.unit))
        cols[col] = uc[:, 0]
        for j, s in enumerate(net.sensors):
            cols[s.column] = y[:, j]
        path = os.path.join(workdir, f"{case.net}_{case.kind}_{seed}_{which}.csv")
        write_csv(path, np.arange(n) * spec.dt, cols, net.temperature_unit,
                  kelvin=[i.column for i in net.inputs if i.is_temperature] + [s.column for s in net.sensors])
        paths.append(path)
    return net, [paths[0]], [paths[1]]


# ---------------------------------------------------------------------------------------------
# scoring
# ---------------------------------------------------------------------------------------------


def _key(kind, target, dep) -> tuple:
    return (kind, target, dep or "")


def first_answer(d):
    """The doctor's first answer: the finding accepted in round 1, else its best fit of round 1 (or None)."""
    r1 = [f for f in d.findings if f.round == 1]
    acc = [f for f in r1 if f.accepted]
    if acc:
        return acc[0]
    return min(r1, key=lambda f: f.rank) if r1 else None


def score(case: Case, d, noise: float) -> dict:
    """Per-run metrics (see the module doc)."""
    f = first_answer(d)
    truth = _key(*case.truth)
    eq = {truth} | {_key(*e) for e in case.equivalent}
    # a curved truth (``then``) may be answered by its line and square together in one finding (the doctor's
    # look-ahead, when the line alone does not pay): the square is scored by ``shape``, the first answer by the rest
    deps = [d for d in f.depends_on if not (case.then and d.endswith("²"))] if f is not None else []
    got = _key(f.kind, f.target, ",".join(deps)) if f is not None else None
    before, after = d.baseline["val_mae"], d.extended["val_mae"]
    r = {
        "case": case.name, "net": case.net, "kind": case.kind, "noise": noise,
        "first_answer": None if f is None else f"{f.kind}:{f.target}:{','.join(f.depends_on)}",
        "first_accepted": bool(f is not None and f.accepted),
        "n_accepted": len(d.accepted),
        "mae_before": before, "mae_after": after,
        "ratio": (before / after) if after > 0 else float("inf"),
        "above_noise": bool(before >= 4 * 0.798 * noise),
        "time_s": d.timings.get("total"),
    }
    if case.kind == "null":
        r["false_accept"] = bool(d.accepted)
        return r
    r["first"] = got == truth
    r["first_eq"] = got in eq
    # the cautions of an accepted first answer: candidates whose linearised correction is nearly its own and that the
    # held-out run did not separate ("the data cannot tell them apart"); reported, not counted as first
    caution = [tuple(t["key"].split(":", 2)) for t in (f.evidence.get("indistinguishable_from") or [])
               if f is not None and f.accepted and not t.get("separated")] if f is not None else []
    r["first_or_caution"] = bool(r["first_eq"] or any(_key(*k) in eq for k in caution if len(k) == 3))
    r["accepted"] = bool(f is not None and f.accepted and got in eq)
    if case.truth[2]:
        r["dep"] = bool(f is not None and case.truth[2] in f.depends_on)
    if case.then:
        r["shape"] = any(case.then in a.depends_on for a in d.accepted)
    return r


def run_case(case: Case, noise: float, seed: int, quick: bool, backend: str = "jax", top: int | None = None,
             max_rounds: int = 2, workdir: str | None = None, keep: bool = False) -> dict:
    """Plant, diagnose, score one run. ``keep``: the diagnosis itself under ``"diagnosis"`` too (not JSON-able).
    ``top``: candidates fitted per round (``None``: the doctor's default, ``doctor.scoring.SHORTLIST_TOP`` = 3, which
    this suite judges)."""
    import tnn_dsl

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.monotonic()
        net, train, val = make_data(case, noise, seed, quick, workdir or tmp)
        t1 = time.monotonic()
        d = tnn_dsl.diagnose(NETWORKS[case.net].path if isinstance(train[0], str) else net, train, val,
                             backend=backend, top=top, max_rounds=max_rounds)
        r = score(case, d, noise)
    r.update(seed=seed, quick=quick, backend=backend, plant_s=round(t1 - t0, 2), verdict=d.verdict)
    if keep:
        r["diagnosis"] = d
    return r


# ---------------------------------------------------------------------------------------------
# table
# ---------------------------------------------------------------------------------------------


def _pct(xs) -> str:
    xs = [bool(x) for x in xs]
    return f"{100 * sum(xs) / len(xs):.0f} % ({sum(xs)}/{len(xs)})" if xs else "–"


def table(rows: list[dict]) -> str:
    """Markdown: per network × kind × noise, then the totals against the targets."""
    out = ["| network | kind | noise K | runs | first | first (≡) | dependence named | accepted | "
           "MAE before → after K (median) | ratio ≥ 2 where above noise | doctor's first answer (last run) |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["net"], r["kind"], r["noise"]), []).append(r)
    for (net, kind, noise), rs in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1], kv[0][2])):
        b = np.median([r["mae_before"] for r in rs])
        a = np.median([r["mae_after"] for r in rs])
        above = [r["ratio"] >= 2 for r in rs if r["above_noise"]]
        if kind == "null":
            out.append(f"| {net} | null | {noise:g} | {len(rs)} | | | | "
                       f"false acceptance {_pct(r['false_accept'] for r in rs)} "
                       f"| {b:.3g} → {a:.3g} | | {rs[-1]['first_answer'] or '–'} |")
            continue
        dep = [r["dep"] for r in rs if "dep" in r]
        out.append(f"| {net} | {kind} | {noise:g} | {len(rs)} | {_pct(r['first'] for r in rs)} | "
                   f"{_pct(r['first_eq'] for r in rs)} | {_pct(dep) if dep else 'n/a'} | "
                   f"{_pct(r['accepted'] for r in rs)} | {b:.3g} → {a:.3g} | {_pct(above) if above else 'n/a'} | "
                   f"{rs[-1]['first_answer'] or '–'} |")
    eff = [r for r in rows if r["kind"] != "null"]
    nul = [r for r in rows if r["kind"] == "null"]
    dep = [r["dep"] for r in eff if "dep" in r]
    halved = [r["ratio"] >= 2 for r in eff if r["above_noise"]]
    out += ["", "| total | value | target |", "|---|---|---|",
            f"| true cause ranked first, as planted (exact name) | {_pct(r['first'] for r in eff)} | |",
            f"| … or an identical-equation equivalent (no data can tell them apart; the first rank scored) | "
            f"{_pct(r['first_eq'] for r in eff)} | ≥ 90 % |",
            f"| dependence variable named | {_pct(dep)} | ≥ 80 % |",
            f"| true cause accepted | {_pct(r['accepted'] for r in eff)} | |",
            f"| null runs without an accepted finding | {_pct(not r['false_accept'] for r in nul)} | ≥ 95 % |",
            f"| held-out MAE at least halved where the effect stands above the noise | {_pct(halved)} | 100 % |"]
    if eff and all("first_or_caution" in r for r in eff):  # runs recorded before the field existed lack it
        out.insert(out.index("| total | value | target |") + 4,
                   f"| … or named in the first answer's caution (the data do not tell them apart) | "
                   f"{_pct(r['first_or_caution'] for r in eff)} | (not the target) |")
    kinds_missed = sorted({r["kind"] for r in eff if not r["first_eq"]})
    if kinds_missed:
        out += ["", "Kinds with at least one miss: " + ", ".join(kinds_missed) + "."]
    return "\n".join(out)


def case_study_time(backend: str = "jax") -> dict:
    """The case-study diagnosis (m1.thn, 4 h training, 2 h validation, noise 0) timed end to end."""
    import tnn_dsl

    with tempfile.TemporaryDirectory() as tmp:
        cs = tnn_dsl.generate_case_study(tmp, n_ood=1, widen=(0.1,))
        m1 = os.path.join(ROOT, "networks", "peltier_heatpipe", "m1.thn")
        t0 = time.monotonic()
        d = tnn_dsl.diagnose(m1, cs["train"], cs["val"], backend=backend)
        dt = time.monotonic() - t0
    return {"seconds": dt, "verdict": d.verdict, "mae_before": d.baseline["val_mae"],
            "mae_after": d.extended["val_mae"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="one seed, noise 0.01, short data, TCLab only")
    ap.add_argument("--all-nets", action="store_true", help="with --quick: every network, not only TCLab")
    ap.add_argument("--only", default=None, help="run only cases whose name contains this text (e.g. tclab/)")
    ap.add_argument("--seeds", type=int, default=None, help="seeds per case and noise (default 2; 1 with --quick)")
    ap.add_argument("--noise", default=None, help="comma-separated noise levels in K (default 0,0.01,0.05)")
    ap.add_argument("--jsonl", default=None, help="append each run's metrics to this file")
    ap.add_argument("--resume", action="store_true", help="skip runs already in --jsonl")
    ap.add_argument("--backend", default="jax", choices=("jax", "torch"))
    ap.add_argument("--case-study-time", action="store_true", help="also time the case-study diagnosis (m1.thn, 4 h)")
    ap.add_argument("--no-write", action="store_true", help="do not write BENCHMARKS.md")
    ap.add_argument("--table-only", action="store_true", help="only rebuild the table from --jsonl")
    ap.add_argument("--note", default=None, help="a sentence added under the table (scope of a partial run)")
    a = ap.parse_args(argv)
    import jax  # the persistent compilation cache makes runs on the same network and data shape much cheaper

    cache = os.path.join(tempfile.gettempdir(), f"tnn_diagnose_suite_jax_cache_{os.getuid()}")
    jax.config.update("jax_compilation_cache_dir", cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_compilation_cache_max_size", 2**31)  # a limit turns on the file lock

    noises = tuple(float(x) for x in a.noise.split(",")) if a.noise else ((0.01,) if a.quick else NOISES)
    seeds = range(a.seeds if a.seeds is not None else (1 if a.quick else 2))
    cases = [c for c in CASES
             if (a.only is None or a.only in c.name) and (not a.quick or a.all_nets or c.net.startswith("tclab"))]
    done: dict[tuple, dict] = {}
    rows: list[dict] = []
    if a.jsonl and (a.resume or a.table_only) and os.path.exists(a.jsonl):
        for line in open(a.jsonl, encoding="utf-8"):
            r = json.loads(line)
            done[(r["case"], r["noise"], r["seed"], r["quick"])] = r
    for case in ([] if a.table_only else cases):
        for noise in noises:
            for seed in seeds:
                k = (case.name, noise, seed, a.quick)
                if k in done:
                    rows.append(done[k])
                    continue
                try:
                    r = run_case(case, noise, seed, a.quick, a.backend)
                except Exception as exc:  # noqa: BLE001 - a crash is a result of the suite, not the end of it
                    r = {"case": case.name, "net": case.net, "kind": case.kind, "noise": noise, "seed": seed,
                         "quick": a.quick, "error": f"{type(exc).__name__}: {exc}"}
                print(json.dumps({k_: v for k_, v in r.items() if k_ != "verdict"}), flush=True)
                if a.jsonl:
                    with open(a.jsonl, "a", encoding="utf-8") as fh:
                        fh.write(json.dumps(r) + "\n")
                rows.append(r)
    if a.table_only:
        rows = list(done.values())
    errors = [r for r in rows if "error" in r]
    ok = [r for r in rows if "error" not in r]
    md = table(ok) if ok else "(no runs)"
    if errors:
        md += "\n\nRuns that raised: " + "; ".join(f"{r['case']} noise {r['noise']} seed {r['seed']}: {r['error']}"
                                                  for r in errors)
    times = [r["time_s"] for r in ok if r.get("time_s")]
    if times:
        md += f"\n\nDiagnosis time per run: median {np.median(times):.0f} s, max {max(times):.0f} s ({a.backend})."
    if a.case_study_time:
        cs = case_study_time(a.backend)
        md += (f"\n\nCase-study diagnosis (m1.thn, 4 h training, 2 h validation): {cs['seconds']:.0f} s "
               f"(target ≤ 300 s); held-out MAE {cs['mae_before']:.3g} → {cs['mae_after']:.3g} K; {cs['verdict']}")
    if a.note:
        md += "\n\n" + a.note
    print(md)
    if not a.no_write:
        sys.path.insert(0, HERE)
        from _report import write_section

        write_section("diagnosis", md, path=os.path.join(ROOT, "BENCHMARKS.md"),
                      title="Model doctor: hidden-effect suite")
    return 0


if __name__ == "__main__":
    sys.exit(main())
