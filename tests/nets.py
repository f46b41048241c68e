"""Small networks built directly from the IR classes (no parser), for the compiler's tests.

Each function returns a validated-looking :class:`tnn_dsl.Network` with automatic parameter names as in
docs/architecture.md. Temperatures in kelvin.
"""

from __future__ import annotations

from tnn_dsl.ir.network import (
    Binary,
    Boundary,
    Call,
    Fluid,
    Input,
    LearnFunction,
    LearnInput,
    LearnTarget,
    Link,
    Network,
    Num,
    Param,
    Peltier,
    Radiation,
    Ref,
    Sensor,
    Source,
    Table,
    Temp,
    ThermalNode,
)

K0 = 273.15


class B:
    """A tiny builder: keeps the parameter table and element lists in declaration order."""

    def __init__(self, name):
        self.name = name
        self.params, self.inputs, self.nodes, self.bnds, self.links = [], [], [], [], []
        self.rads, self.pes, self.fluids, self.sources, self.sensors, self.learned = [], [], [], [], [], []

    def param(self, name, value, role="generic", free=False, lower=None, upper=None, owner=None):
        expr = value if not isinstance(value, (int, float)) else Num(value=float(value))
        self.params.append(Param(name=name, expr=expr, role=role, free=free, lower=lower, upper=upper, owner=owner))
        return name

    def input(self, name, is_temperature=False):
        self.inputs.append(Input(name=name, column=name, is_temperature=is_temperature))

    def node(self, name, C, free=False):
        self.nodes.append(ThermalNode(name=name, capacitance=self.param(f"C_{name}", C, "capacitance", free)))

    def boundary(self, name, T):
        self.bnds.append(Boundary(name=name, temperature=self.param(f"T_{name}", T, "temperature")))

    def R(self, a, b, value, name=None, free=False):
        name = name or f"R_{a}_{b}"
        self.links.append(Link(name=name, a=a, b=b, form="R", value=self.param(name, value, "resistance", free)))

    def G(self, a, b, value, name=None, free=False):
        name = name or f"G_{a}_{b}"
        self.links.append(Link(name=name, a=a, b=b, form="G", value=self.param(name, value, "conductance", free)))

    def radiation(self, a, b, area, emissivity, view_factor=1.0):
        n = f"rad_{a}_{b}"
        self.rads.append(Radiation(
            name=n, a=a, b=b, area=self.param(f"{n}.area", area, "component"),
            emissivity=self.param(f"{n}.emissivity", emissivity, "component"),
            view_factor=self.param(f"{n}.view_factor", view_factor, "component")))

    def peltier(self, name, hot, cold, current, seebeck, resistance, r_internal=None):
        self.pes.append(Peltier(
            name=name, hot=hot, cold=cold, current=self.param(f"{name}.current", current, "component"),
            seebeck=self.param(f"{name}.seebeck", seebeck, "component", free=True),
            resistance=self.param(f"{name}.resistance", resistance, "component", free=True),
            r_internal=None if r_internal is None else self.param(f"{name}.R_internal", r_internal, "resistance")))

    def fluid(self, name, node, inlet, mdot, cp, ua):
        self.fluids.append(Fluid(
            name=name, node=node, inlet=self.param(f"{name}.inlet", inlet, "temperature"),
            mdot=self.param(f"{name}.mdot", mdot, "component"), cp=self.param(f"{name}.cp", cp, "component"),
            ua=self.param(f"{name}.UA", ua, "component")))

    def source(self, node, value, name=None):
        name = name or f"Q_src_{node}"
        self.sources.append(Source(name=name, node=node, value=self.param(name, value, "heat_flow")))

    def sensor(self, name, node, lag=None, offset=None):
        self.sensors.append(Sensor(
            name=name, node=node, column=name,
            lag=None if lag is None else self.param(f"{name}.lag", lag, "time_constant"),
            offset=None if offset is None else self.param(f"{name}.offset", offset, "offset")))

    def learn(self, name, kind, targets, inputs=(), **kw):
        tg = []
        for t in targets:
            if t.startswith("Q["):
                tg.append(LearnTarget(kind="heat_load", name=t[2:-1]))
            elif t.endswith((".Q_hot", ".Q_cold", ".Q")) and "." in t:
                tg.append(LearnTarget(kind="flow", name=t))
            else:
                tg.append(LearnTarget(kind="param", name=t))
        self.learned.append(LearnFunction(name=name, kind=kind, targets=tg,
                                          inputs=[LearnInput(name=i) for i in inputs], **kw))

    def build(self) -> Network:
        return Network(name=self.name, temperature_unit="K", params=self.params, inputs=self.inputs,
                       nodes=self.nodes, boundaries=self.bnds, links=self.links, radiations=self.rads,
                       peltiers=self.pes, fluids=self.fluids, sources=self.sources, sensors=self.sensors,
                       learned=self.learned)


def ref(name):
    return Ref(name=name)


def one_node_rc(R=2.0, C=50.0, Ta=300.0, Q=None) -> Network:
    """One node ``n`` (C J/K) to a boundary ``amb`` at input ``Ta`` through R K/W; optional heat ``Q`` W."""
    b = B("rc")
    b.input("Ta", is_temperature=True)
    b.boundary("amb", ref("Ta"))
    b.node("n", C)
    b.R("n", "amb", R)
    if Q is not None:
        b.input("Q")
        b.source("n", ref("Q"))
    b.sensor("T", "n")
    return b.build()


def two_node() -> Network:
    """Two nodes, two boundaries, a heat source on node 1 (input ``P`` W)."""
    b = B("two")
    b.input("Ta", is_temperature=True)
    b.input("P")
    b.boundary("amb", ref("Ta"))
    b.boundary("wall", 290.0)
    b.node("n1", 100.0)
    b.node("n2", 300.0)
    b.R("n1", "amb", 2.0)
    b.G("n1", "n2", 0.8)
    b.R("n2", "wall", 4.0)
    b.source("n1", ref("P"))
    b.sensor("T2", "n2", offset=0.25)
    return b.build()


def adiabatic() -> Network:
    """Three nodes with links and radiation between them, nothing to the outside (energy conserved)."""
    b = B("adiabatic")
    b.node("a", 10.0)
    b.node("b", 25.0)
    b.node("c", 40.0)
    b.R("a", "b", 0.5)
    b.G("b", "c", 1.5)
    b.R("a", "c", 3.0)
    b.radiation("a", "c", area=0.05, emissivity=0.8)
    b.sensor("Tc", "c")
    return b.build()


def peltier_fluid() -> Network:
    """A Peltier element between two nodes and a fluid through one of them, inputs ``I`` and ``Tf``."""
    b = B("pf")
    b.input("I")
    b.input("Tf", is_temperature=True)
    b.node("h", 40.0)
    b.node("c", 40.0)
    b.peltier("pe", "h", "c", ref("I"), 0.05, 2.0, r_internal=1.5)
    b.fluid("f1", "c", ref("Tf"), 0.002, 4186.0, 5.0)
    b.boundary("amb", 295.0)
    b.R("h", "amb", 0.5)
    b.sensor("Tc", "c")
    return b.build()


def case_study(learn: str | None = "linear", extra: bool = False) -> Network:
    """The case study (spec/case-study.md, model M2 by default). ``learn``: ``None`` (nominal constants),
    ``"const"``, ``"linear"``, ``"mlp"`` (M3, hidden [8, 8] sigmoid), ``"mlp_peltier"`` (M4), ``"linear_u1"`` (the
    heat pipe's resistances linear in ``u1`` alone: links whose conductances depend on the inputs only), ``"two_fns"``
    (two functions of node temperatures sharing out four links, their targets interleaved in the links' order).
    ``extra`` adds every other component kind: a lagged offset sensor, radiation, a derived
    table conductance, a learned heat load and a derived source, so one rollout exercises everything."""
    b = B("peltier_heatpipe")
    for name, temp in (("I", False), ("u1", False), ("Ta", True), ("Tf1", True), ("Tf2", True)):
        b.input(name, temp)
    for name, C in (("ph", 40), ("pc", 40), ("hs", 600), ("hx1", 300), ("hp", 60), ("hx2", 300), ("base", 800)):
        b.node(name, C)
    b.boundary("amb", ref("Ta"))
    b.R("ph", "hs", 0.08)
    b.R("pc", "hx1", 0.05)
    b.R("hx1", "hp", 0.2, name="R_hp1")
    b.R("hp", "hx2", 0.2, name="R_hp2")
    b.R("hp", "amb", 10.0, name="R_hpa")
    b.R("hs", "amb", 0.3)
    b.R("base", "hs", 2.0)
    b.R("base", "hx1", 2.0)
    b.R("base", "amb", 3.0)
    b.peltier("pe", "ph", "pc", ref("I"), 0.05, 2.0, r_internal=1.5)
    b.fluid("f1", "hx1", ref("Tf1"), 0.002, 4186.0, 5.0)
    b.fluid("f2", "hx2", ref("Tf2"), 0.002, 4186.0, 5.0)
    if extra:
        b.sensor("T_out", "hx2", lag=5.0, offset=0.1)
        b.sensor("T_hs", "hs")
        b.radiation("hs", "amb", area=0.02, emissivity=0.9)
        b.G("base", "hx2", Table(x=Call(fn="mean", args=[Temp(node="base"), Temp(node="hx2")]),
                                  xs=[K0, K0 + 50.0], ys=[2.0, 2.4]), name="G_tab")
        b.param("P_aux", 0.5, "heat_flow")
        b.source("base", Binary(op="*", left=ref("P_aux"), right=ref("u1")))
    else:
        b.sensor("T_out", "hx2")
    if learn == "const":
        b.learn("f1_hp", "const", ["R_hp1", "R_hp2", "R_hpa"])
    elif learn == "linear":
        b.learn("f1_hp", "linear", ["R_hp1", "R_hp2", "R_hpa"], ["hx1", "hp", "hx2", "u1"])
    elif learn == "mlp":
        b.learn("f1_hp", "mlp", ["R_hp1", "R_hp2", "R_hpa"], ["hx1", "hp", "hx2", "u1"], hidden=[8, 8],
                activation="sigmoid")
    elif learn == "mlp_peltier":
        b.learn("f_pe", "mlp", ["pe.Q_hot", "pe.Q_cold"], ["ph", "pc", "I"], hidden=[8, 8])
    elif learn == "linear_u1":  # the doctor's answer on the case study: resistances depending on the command only
        b.learn("f1_hp", "linear", ["R_hp1", "R_hp2", "R_hpa"], ["u1"])
    elif learn == "two_fns":  # like the doctor's second round: several state-dependent functions own the links
        b.learn("f1_hp", "linear", ["R_hp2", "R_hpa"], ["hp", "u1"])
        b.learn("f2_bs", "poly", ["R_base_hs", "R_hp1"], ["hs", "I"], degree=2)
    elif learn is not None:
        raise ValueError(learn)
    if extra:
        b.learn("f_load", "poly", ["Q[hp]"], ["hp", "u1"], degree=2)
    return b.build()


def case_inputs(N, seed=1, dt=1.0):
    """Pseudo-random step inputs ``(N, 5)`` [I, u1, Ta, Tf1, Tf2] like the case study's generator."""
    import numpy as np

    rng = np.random.default_rng(seed)
    u = np.empty((N, 5))
    u[:, 2] = K0 + 22.0
    u[:, 3] = K0 + 25.0
    u[:, 4] = K0 + 25.0
    for col, (lo, hi) in ((0, (0.0, 3.0)), (1, (0.0, 1.0))):
        k = 0
        while k < N:
            hold = int(rng.uniform(120, 600) / dt)
            u[k:k + hold, col] = rng.uniform(lo, hi)
            k += hold
    return u


def random_params(model, seed=0):
    """The model's initial parameter table (numpy) with every learned weight random and non-zero (so the
    learned terms act): ``0.3·N(0, 1)``, seeded."""
    import numpy as np

    rng = np.random.default_rng(seed)
    p = model.to_numpy(model.init_params(seed))
    for k, spec in model.param_specs.items():
        if spec.kind == "weights":
            p[k] = 0.3 * rng.standard_normal(spec.shape)
    return p


def dynamo_restarts() -> int:
    """How many times dynamo restarted a frame's analysis in this process so far (its second, third … attempts,
    ``torch._dynamo.utils.compilation_time_metrics``): each restart traces the whole graph again."""
    from torch._dynamo.utils import compilation_time_metrics

    return sum(len(v) for k, v in compilation_time_metrics.items()
               if k.startswith("compile_attempt_") and k != "compile_attempt_0")


def assert_compiled_forward_matches_jax(mc, mj, p_np, T0, U, atol=1e-9):
    """A ``torch_compile=True`` model's forward rollout (no gradient) on the batch ``T0 (B, n), U (B, N, m)`` and
    on its first sequence alone gives the JAX model's states to ``atol`` K, compiled (a ``TorchCompileWarning``,
    the fallback to eager, fails)."""
    import warnings

    import numpy as np
    import torch

    import tnn_dsl

    for t0, u in ((T0, U), (T0[0], U[0])):
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)
            s, _ = mc.rollout(mc.from_numpy(p_np), torch.as_tensor(t0), torch.as_tensor(u), 1.0)
        s_ref, _ = mj.rollout(mj.from_numpy(p_np), t0, u, 1.0)
        assert np.max(np.abs(s.numpy() - np.asarray(s_ref))) <= atol
