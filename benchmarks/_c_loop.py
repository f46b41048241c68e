"""A compiled C loop of the same equations as the compiled model, to show the limit of the hardware.

:func:`build_c_rollout` reads a :class:`~tnn_dsl.ir.network.Network` (links, Peltier elements, fluids, boundaries
fed by inputs or constants, at most one MLP whose targets are link resistances/conductances) and the
model's parameter table, writes a C source with the network's sizes as compile-time constants (so the
compiler unrolls every small loop), compiles it with ``cc -O3 -march=native -shared`` into a temporary
directory and loads it with :mod:`ctypes`. Nothing of the model's Python code runs inside the loop.

The equations are those of ``tnn_dsl.compiler.model`` (thesis eq. 2.4/2.10–2.14), written out per element:

* link ``a -- b`` with conductance ``g`` (``1/R``): ``g·(T_b − T_a)`` into ``a``, the opposite into ``b``;
* Peltier: ``Q_hot = S·T_hot·I + ½R I²``, ``Q_cold = −S·T_cold·I + ½R I²`` and the internal link;
* fluid: ``ṁcp(1 − e^{−UA/ṁcp})·(T_in − T_node)``;
* MLP: ``z = W_k σ(… σ(W_0 xn + b_0) …) + b_k``, ``xn = (x − x_mean)/x_scale``; a positive target is
  ``nominal · softplus(4(1 + z))/softplus(4)``;
* explicit Euler or classical RK4 over each sample interval with ``sub`` equal sub-steps.

Networks outside that class (radiation, sources, derived expressions, lagged sensors, other learned
kinds) raise :class:`Unsupported`; the benchmark then reports that it has no C reference.
"""

from __future__ import annotations

import ctypes
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np


class Unsupported(Exception):
    """The network uses something the C reference does not implement."""


_C_TEMPLATE = r"""
#include <math.h>
#include <stddef.h>

/* sizes (compile-time constants) */
#define NN {NN}      /* nodes (states) */
#define NB {NB}      /* boundaries */
#define NV (NN + NB) /* vertices: nodes then boundaries */
#define NU {NU}      /* inputs */
#define NLS {NLS}    /* links with constant conductance */
#define NLD {NLD}    /* links whose value is a learned target */
#define NPE {NPE}    /* Peltier elements */
#define NF {NF}      /* fluids */
#define NX {NX}      /* MLP inputs */
#define NO {NO}      /* MLP outputs */
#define SUB {SUB}    /* sub-steps per sample */
static const double H = {DT!r} / SUB;
static const double SOFTPLUS4 = {SOFTPLUS4!r};

/* integer tables */
static const int LS_A[NLS + 1] = {{{LS_A}}}, LS_B[NLS + 1] = {{{LS_B}}};
static const int LD_A[NLD + 1] = {{{LD_A}}}, LD_B[NLD + 1] = {{{LD_B}}}, LD_OUT[NLD + 1] = {{{LD_OUT}}},
                 LD_ISR[NLD + 1] = {{{LD_ISR}}}, LD_POS[NLD + 1] = {{{LD_POS}}};
static const int B_IN[NB + 1] = {{{B_IN}}};            /* input index of a boundary, -1: constant */
static const int PE_H[NPE + 1] = {{{PE_H}}}, PE_C[NPE + 1] = {{{PE_C}}}, PE_I[NPE + 1] = {{{PE_I}}};
static const int F_N[NF + 1] = {{{F_N}}}, F_IN[NF + 1] = {{{F_IN}}};
static const int X_KIND[NX + 1] = {{{X_KIND}}}, X_IDX[NX + 1] = {{{X_IDX}}}; /* 0: node T, 1: input */

/* parameters, filled by set_params() from the model's parameter table */
static double invC[NN], gS[NLS + 1], nomD[NLD + 1], Bc[NB + 1];
static double peS[NPE + 1], peR[NPE + 1], peI[NPE + 1];
static double fG[NF + 1], fTin[NF + 1];
static double xmean[NX + 1], xinv[NX + 1];
{MLP_DECL}

static inline double sigm(double x) {{ return 1.0 / (1.0 + exp(-x)); }}
static inline double softplus(double x) {{ return fmax(x, 0.0) + log1p(exp(-fabs(x))); }}
static inline double act(double x) {{ return {ACT}; }}

static void mlp(const double *xn, double *z) {{
{MLP_BODY}
}}

static void rhs(const double *T, const double *u, double *dT) {{
    double V[NV], Q[NN];
    for (int i = 0; i < NN; i++) {{ V[i] = T[i]; Q[i] = 0.0; }}
    for (int j = 0; j < NB; j++) V[NN + j] = B_IN[j] >= 0 ? u[B_IN[j]] : Bc[j];
    for (int k = 0; k < NLS; k++) {{
        int a = LS_A[k], b = LS_B[k];
        double q = gS[k] * (V[b] - V[a]);
        if (a < NN) Q[a] += q;
        if (b < NN) Q[b] -= q;
    }}
#if NO > 0
    double xn[NX], z[NO];
    for (int j = 0; j < NX; j++) xn[j] = ((X_KIND[j] ? u[X_IDX[j]] : T[X_IDX[j]]) - xmean[j]) * xinv[j];
    mlp(xn, z);
#endif
    for (int k = 0; k < NLD; k++) {{
#if NO > 0
        double zk = z[LD_OUT[k]];
#else
        double zk = 0.0;
#endif
        double v = LD_POS[k] ? nomD[k] * softplus(4.0 * (1.0 + zk)) / SOFTPLUS4 : nomD[k] + zk;
        double g = LD_ISR[k] ? 1.0 / v : v;
        int a = LD_A[k], b = LD_B[k];
        double q = g * (V[b] - V[a]);
        if (a < NN) Q[a] += q;
        if (b < NN) Q[b] -= q;
    }}
    for (int k = 0; k < NPE; k++) {{
        double I = PE_I[k] >= 0 ? u[PE_I[k]] : peI[k];
        double joule = 0.5 * peR[k] * I * I;
        int h = PE_H[k], c = PE_C[k];
        if (h < NN) Q[h] += peS[k] * V[h] * I + joule;
        if (c < NN) Q[c] += -peS[k] * V[c] * I + joule;
    }}
    for (int k = 0; k < NF; k++) {{
        double Tin = F_IN[k] >= 0 ? u[F_IN[k]] : fTin[k];
        Q[F_N[k]] += fG[k] * (Tin - T[F_N[k]]);
    }}
    for (int i = 0; i < NN; i++) dT[i] = Q[i] * invC[i];
}}

static void step(double *T, const double *u) {{
    for (int s = 0; s < SUB; s++) {{
#if RK4
        double k1[NN], k2[NN], k3[NN], k4[NN], x[NN];
        rhs(T, u, k1);
        for (int i = 0; i < NN; i++) x[i] = T[i] + (0.5 * H) * k1[i];
        rhs(x, u, k2);
        for (int i = 0; i < NN; i++) x[i] = T[i] + (0.5 * H) * k2[i];
        rhs(x, u, k3);
        for (int i = 0; i < NN; i++) x[i] = T[i] + H * k3[i];
        rhs(x, u, k4);
        for (int i = 0; i < NN; i++) T[i] = T[i] + (H / 6.0) * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
#else
        double k1[NN];
        rhs(T, u, k1);
        for (int i = 0; i < NN; i++) T[i] = T[i] + H * k1[i];
#endif
    }}
}}

/* p: the flat parameter vector (layout documented in _c_loop.py) */
void set_params(const double *p) {{
    size_t o = 0;
    for (int i = 0; i < NN; i++) invC[i] = p[o++];
    for (int k = 0; k < NLS; k++) gS[k] = p[o++];
    for (int k = 0; k < NLD; k++) nomD[k] = p[o++];
    for (int j = 0; j < NB; j++) Bc[j] = p[o++];
    for (int k = 0; k < NPE; k++) {{ peS[k] = p[o++]; peR[k] = p[o++]; peI[k] = p[o++]; }}
    for (int k = 0; k < NF; k++) {{ fG[k] = p[o++]; fTin[k] = p[o++]; }}
    for (int j = 0; j < NX; j++) {{ xmean[j] = p[o++]; xinv[j] = p[o++]; }}
{MLP_SET}
}}

/* one sequence: T0 (NN), U (N, NU) -> S (N, NN), S[0] = T0 */
void rollout(long N, const double *T0, const double *U, double *S) {{
    double T[NN];
    for (int i = 0; i < NN; i++) {{ T[i] = T0[i]; S[i] = T0[i]; }}
    for (long k = 0; k + 1 < N; k++) {{
        step(T, U + k * NU);
        for (int i = 0; i < NN; i++) S[(k + 1) * NN + i] = T[i];
    }}
}}

/* B windows: T0 (B, NN), U (B, N, NU) -> S (B, N, NN) */
void rollout_batch(long B, long N, const double *T0, const double *U, double *S) {{
    for (long b = 0; b < B; b++) rollout(N, T0 + b * NN, U + b * N * NU, S + b * N * NN);
}}
"""


def _slot(net, pname, input_idx, consts):
    """A parameter slot as ``("input", index)`` or ``("const", value)``; anything derived → Unsupported."""
    from tnn_dsl.ir.network import Num, Ref

    params = {p.name: p for p in net.params}
    seen = set()
    while True:
        if pname in seen:
            raise Unsupported(f"circular parameter {pname!r}")
        seen.add(pname)
        p = params[pname]
        if p.is_constant:
            return ("const", float(consts[pname]))
        e = p.expr
        if isinstance(e, Ref) and e.name in input_idx:
            return ("input", input_idx[e.name])
        if isinstance(e, Ref) and e.name in params:
            pname = e.name
            continue
        if isinstance(e, Num):
            return ("const", float(e.value))
        raise Unsupported(f"parameter {pname!r} is a derived expression")


def _ints(xs):
    xs = [int(x) for x in xs]
    return ", ".join(str(x) for x in xs) if xs else "0"


def build_c_rollout(model, params_np: dict, dt: float, integrator: str, substeps: int, workdir=None,
                    cc: str | None = None):
    """Generate, compile and load the C loop for ``model``'s network with the numpy parameter table
    ``params_np``. Returns a :class:`CRollout`. Raises :class:`Unsupported` (network outside the class, or
    no C compiler) or ``RuntimeError`` (compilation failed)."""
    net = model.network
    if integrator not in ("euler", "rk4"):
        raise Unsupported(f"integrator {integrator!r} (the C loop has euler and rk4)")
    if net.radiations or net.sources or any(s.lag for s in net.sensors):
        raise Unsupported("radiation, sources and lagged sensors are not in the C reference")
    if len(net.learned) > 1:
        raise Unsupported("more than one learned function")
    cc = cc or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if not cc:
        raise Unsupported("no C compiler (cc, gcc or clang) on PATH")

    nodes = list(net.node_names)
    bnds = list(net.boundary_names)
    n, nb = len(nodes), len(bnds)
    vidx = {name: i for i, name in enumerate(nodes)}
    vidx.update({name: n + j for j, name in enumerate(bnds)})
    input_idx = {name: i for i, name in enumerate(net.input_names)}
    params = {p.name: p for p in net.params}
    consts = {k: float(np.asarray(v)) for k, v in params_np.items() if np.ndim(v) == 0}

    fn = net.learned[0] if net.learned else None
    targets = {}
    if fn is not None:
        if fn.kind != "mlp" or fn.activation not in ("sigmoid", "tanh"):
            raise Unsupported("the C reference implements MLPs with sigmoid or tanh only")
        for i, t in enumerate(fn.targets):
            if t.kind != "param":
                raise Unsupported("learned heat loads and flows are not in the C reference")
            targets[t.name] = i

    def const(pname):
        kind, v = _slot(net, pname, input_idx, consts)
        if kind != "const":
            raise Unsupported(f"{pname!r} must be constant in the C reference")
        return v

    for nd in net.nodes:
        if not params[nd.capacitance].is_constant:
            raise Unsupported("capacities must be constants")
    links = [(lk.a, lk.b, lk.value, lk.form) for lk in net.links]
    links += [(pe.cold, pe.hot, pe.r_internal, "R") for pe in net.peltiers if pe.r_internal]
    ls, ld = [], []
    for a, b, pname, form in links:
        if pname in targets:
            pos = params[pname].role in ("resistance", "conductance", "capacitance", "time_constant")
            ld.append((vidx[a], vidx[b], targets[pname], int(form == "R"), int(pos), const(pname)))
        else:
            v = const(pname)
            ls.append((vidx[a], vidx[b], 1.0 / v if form == "R" else v))
    if fn is not None and len(ld) != len(targets):
        raise Unsupported("learned targets must be link values")

    p: list[float] = [1.0 / const(nd.capacitance) for nd in net.nodes]
    p += [g for *_, g in ls]
    p += [row[5] for row in ld]
    b_in = []
    for b in net.boundaries:
        kind, v = _slot(net, b.temperature, input_idx, consts)
        b_in.append(v if kind == "input" else -1)
        p.append(0.0 if kind == "input" else v)
    pe_i = []
    for pe in net.peltiers:
        kind, v = _slot(net, pe.current, input_idx, consts)
        pe_i.append(v if kind == "input" else -1)
        p += [const(pe.seebeck), const(pe.resistance), 0.0 if kind == "input" else v]
    f_in, f_G = [], []
    for f in net.fluids:
        mcp = const(f.mdot) * const(f.cp)
        G = -mcp * np.expm1(-const(f.ua) / mcp)
        kind, v = _slot(net, f.inlet, input_idx, consts)
        f_in.append(v if kind == "input" else -1)
        f_G.append(float(G))
        p += [float(G), 0.0 if kind == "input" else v]
    x_kind, x_idx = [], []
    mlp_decl = mlp_body = mlp_set = ""
    nx = no = 0
    if fn is not None:
        for inp in fn.inputs:
            if inp.name in vidx and vidx[inp.name] < n and inp.kind in ("node", "unresolved"):
                x_kind.append(0)
                x_idx.append(vidx[inp.name])
            elif inp.name in input_idx:
                x_kind.append(1)
                x_idx.append(input_idx[inp.name])
            else:
                raise Unsupported(f"MLP input {inp.name!r} (only node temperatures and inputs)")
        arr = {k[len(fn.name) + 1:]: np.asarray(v, dtype=np.float64) for k, v in params_np.items()
               if k.startswith(fn.name + ".")}
        nx, no = len(fn.inputs), len(fn.targets)
        for j in range(nx):
            p += [float(arr["x_mean"][j]), 1.0 / float(arr["x_scale"][j])]
        sizes = [nx, *[int(h) for h in fn.hidden], no]
        decl, body, sets = [], [], []
        prev = "xn"
        for k in range(len(sizes) - 1):
            i_n, o_n = sizes[k], sizes[k + 1]
            decl.append(f"static double W{k}[{i_n * o_n}], b{k}[{o_n}];")
            sets.append(f"    for (int i = 0; i < {i_n * o_n}; i++) W{k}[i] = p[o++];")
            sets.append(f"    for (int i = 0; i < {o_n}; i++) b{k}[i] = p[o++];")
            p += [float(x) for x in arr[f"W{k}"].reshape(-1)]  # row-major (in, out)
            p += [float(x) for x in arr[f"b{k}"].reshape(-1)]
            last = k == len(sizes) - 2
            out = "z" if last else f"h{k}"
            if not last:
                body.append(f"    double h{k}[{o_n}];")
            body.append(f"    for (int j = 0; j < {o_n}; j++) {{ double s = b{k}[j];")
            body.append(f"        for (int i = 0; i < {i_n}; i++) s += {prev}[i] * W{k}[i * {o_n} + j];")
            body.append(f"        {out}[j] = {'s' if last else 'act(s)'}; }}")
            prev = out
        mlp_decl, mlp_body, mlp_set = "\n".join(decl), "\n".join(body), "\n".join(sets)
    act = "sigm(x)" if fn is None or fn.activation == "sigmoid" else "tanh(x)"

    src = _C_TEMPLATE.format(
        NN=n, NB=nb, NU=len(input_idx), NLS=len(ls), NLD=len(ld), NPE=len(net.peltiers), NF=len(net.fluids),
        NX=nx, NO=no, SUB=int(substeps), DT=float(dt), SOFTPLUS4=float(np.log1p(np.exp(4.0))),
        LS_A=_ints(r[0] for r in ls), LS_B=_ints(r[1] for r in ls),
        LD_A=_ints(r[0] for r in ld), LD_B=_ints(r[1] for r in ld), LD_OUT=_ints(r[2] for r in ld),
        LD_ISR=_ints(r[3] for r in ld), LD_POS=_ints(r[4] for r in ld), B_IN=_ints(b_in),
        PE_H=_ints(vidx[pe.hot] for pe in net.peltiers), PE_C=_ints(vidx[pe.cold] for pe in net.peltiers),
        PE_I=_ints(pe_i), F_N=_ints(vidx[f.node] for f in net.fluids), F_IN=_ints(f_in),
        X_KIND=_ints(x_kind), X_IDX=_ints(x_idx), MLP_DECL=mlp_decl, MLP_BODY=mlp_body or "    (void)xn; (void)z;",
        MLP_SET=mlp_set, ACT=act)
    spec = {
        "n": n, "nb": nb, "b_in": b_in, "ls": ls, "ld": ld, "invC_names": [nd.capacitance for nd in net.nodes],
        "pe": [(vidx[pe.hot], vidx[pe.cold], i_in, pe.seebeck, pe.resistance)
               for pe, i_in in zip(net.peltiers, pe_i)],
        "fluids": [(vidx[f.node], G, i_in) for f, G, i_in in zip(net.fluids, f_G, f_in)],
        "consts": consts, "boundary_names": [b.temperature for b in net.boundaries],
        "mlp": None if fn is None else {"name": fn.name, "x_kind": x_kind, "x_idx": x_idx,
                                        "n_layers": len(fn.hidden) + 1, "activation": fn.activation},
        "dt": float(dt), "substeps": int(substeps), "integrator": integrator,
    }
    if integrator == "rk4":
        src = "#define RK4 1\n" + src
    else:
        src = "#define RK4 0\n" + src
    if fn is None:
        src = src.replace("static void mlp(const double *xn, double *z) {\n    (void)xn; (void)z;\n}\n", "")
    c = CRollout(src, np.asarray(p, dtype=np.float64), n, len(input_idx), cc, workdir)
    c.spec = spec
    return c


class CRollout:
    """The compiled C loop. ``rollout(T0 (n,), U (N, n_in)) -> states (N, n)``;
    ``rollout_batch(T0 (B, n), U (B, N, n_in)) -> states (B, N, n)``. ``compile_seconds``: time of ``cc``."""

    FLAGS = ("-O3", "-march=native", "-shared", "-fPIC", "-std=c99")

    def __init__(self, source: str, pvec: np.ndarray, n: int, n_in: int, cc: str, workdir=None):
        import time

        self.source = source
        self.n, self.n_in = n, n_in
        self._tmp = tempfile.TemporaryDirectory(prefix="tnn_c_loop_", dir=workdir)
        d = Path(self._tmp.name)
        (d / "loop.c").write_text(source, encoding="utf-8")
        self.command = [cc, *self.FLAGS, "-o", str(d / "loop.so"), str(d / "loop.c"), "-lm"]
        t = time.perf_counter()
        res = subprocess.run(self.command, capture_output=True, text=True)
        if res.returncode != 0 and "-march=native" in self.command:  # e.g. a compiler without it
            self.command = [c for c in self.command if c != "-march=native"]
            res = subprocess.run(self.command, capture_output=True, text=True)
        self.compile_seconds = time.perf_counter() - t
        if res.returncode != 0:
            raise RuntimeError(f"C compilation failed ({' '.join(self.command)}):\n{res.stderr[-2000:]}")
        self.lib = ctypes.CDLL(str(d / "loop.so"))
        dp = ctypes.POINTER(ctypes.c_double)
        self.lib.set_params.argtypes = [dp]
        self.lib.rollout.argtypes = [ctypes.c_long, dp, dp, dp]
        self.lib.rollout_batch.argtypes = [ctypes.c_long, ctypes.c_long, dp, dp, dp]
        self._p = np.ascontiguousarray(pvec)
        self.lib.set_params(self._p.ctypes.data_as(dp))

    @staticmethod
    def _ptr(a):
        return a.ctypes.data_as(ctypes.POINTER(ctypes.c_double))

    def rollout(self, T0, U, out=None):
        T0 = np.ascontiguousarray(T0, dtype=np.float64)
        U = np.ascontiguousarray(U, dtype=np.float64)
        N = U.shape[0]
        if T0.shape != (self.n,) or U.shape[1:] != (self.n_in,):
            raise ValueError(f"T0 must be ({self.n},) and U (N, {self.n_in}); got {T0.shape}, {U.shape}")
        S = np.empty((N, self.n)) if out is None else out
        self.lib.rollout(N, self._ptr(T0), self._ptr(U), self._ptr(S))
        return S

    def rollout_batch(self, T0, U, out=None):
        T0 = np.ascontiguousarray(T0, dtype=np.float64)
        U = np.ascontiguousarray(U, dtype=np.float64)
        B, N = U.shape[:2]
        if T0.shape != (B, self.n) or U.shape[2:] != (self.n_in,):
            raise ValueError(f"T0 must be (B, {self.n}) and U (B, N, {self.n_in}); got {T0.shape}, {U.shape}")
        S = np.empty((B, N, self.n)) if out is None else out
        self.lib.rollout_batch(B, N, self._ptr(T0), self._ptr(U), self._ptr(S))
        return S

    def close(self):
        self._tmp.cleanup()
