"""The assembly of a compiled network's right-hand side (:class:`_Assembly`, the base of
:class:`~tnn_dsl.compiler.core._Core`): what is evaluated per call, per sample or per right-hand side, the
item closures that evaluate parameters and learned functions in topological order, and the constant matrices
(incidence, scatter, lag and sensor maps, the blocks of the one T-linear product). Numbers are SI, K."""

from __future__ import annotations

import numpy as np

from ..ir import POSITIVE_ROLES
from . import learned as _learned
from . import physics as _physics
from . import sparse as _sparse
from .expressions import compile_expr
from .plan import _Plan
from .sparse import Coo

__all__ = ["_Assembly", "_Prep", "_Env", "SPARSE_MIN_STATES", "PACKED_KEY"]


class _Prep:
    __slots__ = ("vals", "z", "arrays", "scales", "yscale", "fnlin", "M_nn", "M_bn", "Mr_nn", "Mr_bn", "cQ",
                 "Tb", "g_static_d", "invC", "inv_tau", "offsets", "diag_static", "diag_rad", "lin_fluid",
                 "tnom", "tscale", "L", "Lsl")


class _Env:
    __slots__ = ("vals", "z", "T", "u", "cx", "pre")

    def __init__(self, vals, z, T, u, cx=None, pre=None):
        self.vals = vals
        self.z = z
        self.T = T
        self.u = u
        self.cx = cx  # {fn: input-only part of the normalised input} when precomputed
        self.pre = pre  # {fn: first-layer pre-activation} for functions folded into the T-linear product


PACKED_KEY = "const:packed"
"""Parameter-table key of the constants packed into one vector (``Model`` does this at the boundary of a jitted
call on large networks: one array instead of one argument per constant, whose count makes XLA's compile time
grow faster than linearly)."""


class _PackedVals(dict):
    """Parameter values by name where the constants live in one packed vector: a constant is sliced out only
    when something reads it by name (``vals[name]``); vectorised code gathers from :attr:`packed` instead.
    Derived values are stored as in a plain dict. ``copy()`` keeps the packing."""

    __slots__ = ("packed", "index")

    def __init__(self, packed, index: dict[str, int], items=()):
        super().__init__(items)
        self.packed = packed
        self.index = index

    def __missing__(self, name):
        i = self.index.get(name)
        if i is None:
            raise KeyError(name)
        v = self.packed[i]
        self[name] = v
        return v

    def __contains__(self, name) -> bool:
        return dict.__contains__(self, name) or name in self.index

    def get(self, name, default=None):
        return self[name] if name in self else default

    def copy(self) -> _PackedVals:
        return _PackedVals(self.packed, self.index, dict.items(self))


def _noop_item(prep, env):
    return None


def _first_layer(fn, arrays):
    """``(W, b)`` of the first (linear) layer of a ``linear`` or ``mlp`` learned function."""
    return (arrays["W"], arrays["b"]) if fn.kind == "linear" else (arrays["W0"], arrays["b0"])


def _apply_from_first(xp, fn, arrays, pre):
    """The raw output ``z`` of a ``linear``/``mlp`` function from its first layer's pre-activation
    ``pre = xn @ W0 + b0`` (the rest of :func:`tnn_dsl.compiler.learned.apply_normalised`)."""
    if fn.kind == "linear":
        return pre
    act = _learned.activation(xp, fn.activation)
    n_layers = len(fn.hidden) + 1
    h = pre
    for k in range(1, n_layers):
        h = xp.matmul(act(h), arrays[f"W{k}"]) + arrays[f"b{k}"]
    return h


def _diag(xp, M, n):
    if isinstance(M, _sparse.SparseMatrix):
        return M.diagonal(n)
    idx = np.arange(n)
    return M[idx, idx] if xp.name != "torch" else M.diagonal()


def _incidence(group, n: int, nb: int) -> tuple[Coo, Coo]:
    """Scatter ``D (n + nb, k)`` and gather ``Inc (k, n)`` matrices of a group of two-ended elements."""
    D = Coo((n + nb, len(group)))
    Inc = Coo((len(group), n))
    for k, (_, a, b, *_r) in enumerate(group):
        ia = a[1] if a[0] == "n" else n + a[1]
        ib = b[1] if b[0] == "n" else n + b[1]
        D.add(ib, k, 1.0)
        D.add(ia, k, -1.0)
        if a[0] == "n":
            Inc.add(k, a[1], 1.0)
        if b[0] == "n":
            Inc.add(k, b[1], -1.0)
    return D, Inc


def _neg_abs(coo: Coo, factor: float) -> Coo:
    """``−factor·|M|`` entry by entry (the diagonal maps of links and radiation)."""
    out = Coo(coo.shape)
    for r, c, v in zip(coo.rows, coo.cols, coo.vals):
        out.add(r, c, -factor * abs(v))
    return out


def _conductance_structure(group, n: int) -> tuple[np.ndarray, ...]:
    """The non-zeros, sorted by column, of ``D·diag(g)·Inc`` (see
    :func:`~tnn_dsl.compiler.physics.conductance_matrix`) for a group of two-ended elements, as
    ``(rows, cols, coef, which)``: entry ``e`` is ``coef_e · g[which_e]`` at vertex row ``rows_e``
    (boundaries after the nodes) and node column ``cols_e``; at most 4 per element."""
    rows, cols, coef, which = [], [], [], []
    for k, (_, a, b, *_r) in enumerate(group):
        va = a[1] if a[0] == "n" else n + a[1]
        vb = b[1] if b[0] == "n" else n + b[1]
        for v, sd in ((vb, 1.0), (va, -1.0)):
            for end, si in ((a, 1.0), (b, -1.0)):
                if end[0] == "n":
                    rows.append(v)
                    cols.append(end[1])
                    coef.append(sd * si)
                    which.append(k)
    cols_a = np.asarray(cols, dtype=np.int64)
    order = np.argsort(cols_a, kind="stable")  # sorted by column once here, not in every prepare
    return (np.asarray(rows, dtype=np.int64)[order], cols_a[order], np.asarray(coef, dtype=float)[order],
            np.asarray(which, dtype=np.int64)[order])


def _split_rows(coo: Coo, n: int) -> tuple[Coo, Coo]:
    """Rows ``:n`` (nodes) and ``n:`` (boundaries) of a vertex matrix."""
    top, bottom = Coo((n, coo.shape[1])), Coo((coo.shape[0] - n, coo.shape[1]))
    for r, c, v in zip(coo.rows, coo.cols, coo.vals):
        (top.add(r, c, v) if r < n else bottom.add(r - n, c, v))
    return top, bottom


def _rows_matrix(rows, n: int) -> Coo:
    """The matrix ``(len(rows), n)`` scattering point flows onto their nodes (boundary rows stay 0)."""
    M = Coo((len(rows), n))
    for k, v in enumerate(rows):
        if v[0] == "n":
            M.add(k, v[1], 1.0)
    return M


SPARSE_MIN_STATES = 200
"""Networks with at least this many states are compiled with sparse matrices (:mod:`.sparse`) unless told
otherwise. Below it one dense product per matrix is the faster form, above it the O(n²) products dominate: on
plate meshes (benchmarks/bench_scaling.py, BENCHMARKS.md "Network size") dense is faster at 100 nodes on both
backends (JAX 4.6 against 7.6 µs per RK4 step, torch 69 against 94) and slower at 306 (33 against 23, 161
against 133)."""

NODE_MATRIX_MAX = 512
"""The largest ``n² · (n_links + 1)`` (``n`` nodes, ``n_links`` links whose conductances depend on the inputs alone)
for which a dense JAX model, in a program traced forward only (``Backend.no_grad``: the doctor's simulations and
difference Jacobians), forms each right-hand side's node matrix ``M + Σ_k g_k(u) P_k`` in place (``P_k`` the
constant outer product of link ``k``'s gather and scatter columns) and takes one product with the temperatures,
instead of gathering the links' temperature differences, scaling them by their conductances and scattering the heat
back. The gather–scatter form puts two dependent reductions in a step where XLA's loop fusion then recomputes the
step's whole stage expression for every element of the second (the case study with ``R_hp2(u1)``: 8 loop fusions a
step, 8.5 ms a rollout of 14 401 samples against 3.4 ms without the link; 5.0 ms in place). Differentiated in reverse
the in-place matrix was the slower (a training 20 % slower), so gradients keep the gather–scatter form; its work
grows as ``n²`` per link, hence the bound (issue 18, BENCHMARKS.md 2026-12-05)."""


class _Assembly:
    """The plan bound to an array namespace ``xp``: built once per compiled model, in named steps."""

    def __init__(self, plan: _Plan, xp, sparse: bool = False):
        self.plan = plan
        self.xp = xp
        self.sparse = bool(sparse)
        """Whether the constant matrices are :class:`~.sparse.SparseMatrix` (gather/scatter) or dense."""
        self.const_names = [p.name for p in plan.net.params if p.is_constant]
        """The constant parameters in the order of the packed vector (:data:`PACKED_KEY`)."""
        self.const_index = {nm: i for i, nm in enumerate(self.const_names)}
        self._vectorised_functions()
        self._item_closures()
        self._static_elements()
        self._incidence_matrices()
        self._input_only_split()
        self._affine_terms()
        self._point_flows()
        self._context_needs()
        self._vectorised_links()
        self._lag_and_sensor_maps()
        self._first_layer_blocks()

    def _vectorised_functions(self) -> None:
        """Learned functions whose targets are all constant parameters of one positivity: their targets are
        evaluated as one vector (a few array ops instead of a handful per target)."""
        P = self.plan
        self._vec_fns: dict[str, tuple[list[str], bool]] = {}
        for fn in P.net.learned:
            names = [t.name for t in fn.targets]
            if not names or any(t.kind != "param" for t in fn.targets) or len(set(names)) != len(names):
                continue
            if any(P.param_targets.get(nm, (None,))[0] is not fn for nm in names):
                continue
            if not all(P.params[nm].is_constant for nm in names):
                continue
            pos = {P.params[nm].role in POSITIVE_ROLES for nm in names}
            if len(pos) == 1:
                self._vec_fns[fn.name] = (names, pos.pop())
        self._vec_targets = {nm for names, _ in self._vec_fns.values() for nm in names}

    def _item_closures(self) -> None:
        """One closure per parameter and learned function, evaluated in topological order."""
        P, xp = self.plan, self.xp

        def ref(name):
            if name in P.params:
                return lambda env: env.vals[name]
            i = P.input_idx[name]
            return lambda env: env.u[..., i]

        def temp(node):
            if node in P.node_idx:
                i = P.node_idx[node]
                return lambda env: env.T[..., i]
            bp = P.bnd_param[node]
            return lambda env: env.vals[bp]

        self._items = {}
        for p in P.net.params:
            if p.is_constant:  # the value comes from the parameter table, not from the IR literal
                expr_fn = (lambda name: lambda env: env.vals[name])(p.name)
            else:
                expr_fn = compile_expr(p.expr, xp, ref, temp)
            self._items[("p", p.name)] = self._param_item(p, expr_fn)
        for fn in P.net.learned:
            self._items[("f", fn.name)] = self._fn_item(fn)
        self._dyn_items = [self._items[it] for it in P.dyn_order]
        self._mono = {fn.name: _learned.monomial_index(len(fn.inputs), int(fn.degree or 2))
                      for fn in P.net.learned if fn.kind == "poly"}

    def _static_elements(self) -> None:
        """Which links, radiation, fluids, sources, boundaries, capacities, lags and offsets are static."""
        P = self.plan
        self.links_s = [lk for lk in P.links if P.is_static(lk[3])]
        self.links_d = [lk for lk in P.links if not P.is_static(lk[3])]
        self.rads_s = [r for r in P.rads if all(P.is_static(q) for q in r[3])]
        self.rads_d = [r for r in P.rads if not all(P.is_static(q) for q in r[3])]
        self.fluids_lin = [f for f in P.fluids if f"{f.name}.Q" not in P.flow_targets
                           and all(P.is_static(q) for q in (f.mdot, f.cp, f.ua))]
        self.fluids_nl = [f for f in P.fluids if f not in self.fluids_lin]
        self.sources_s = [s for s in P.net.sources if P.is_static(s.value)]
        self.sources_d = [s for s in P.net.sources if not P.is_static(s.value)]
        self.bnd_static = all(P.is_static(P.bnd_param[b]) for b in P.bnds)
        self.C_static = all(P.is_static(nd.capacitance) for nd in P.net.nodes)
        self.tau_static = all(P.is_static(s.lag) for s in P.lagged)
        self.off_static = all(s.offset is None or P.is_static(s.offset) for s in P.net.sensors)

    def _mat(self, coo: Coo):
        """A constant matrix as the model keeps it: dense backend array, or sparse for large networks."""
        return _sparse.as_matrix(self.xp, coo, self.sparse)

    def _mm(self, x, M):
        """``x @ M`` for a dense or sparse constant matrix ``M``."""
        return _sparse.matmul(self.xp, x, M)

    def _incidence_matrices(self) -> None:
        """Scatter/gather matrices of the static and dynamic links and radiation; for static links and
        radiation the structure of their conductance matrices (values come in ``prepare``)."""
        P = self.plan
        n, nb = P.n, P.nb
        if self.sparse:
            self.C_ls = _conductance_structure(self.links_s, n)
            self.C_rs = _conductance_structure(self.rads_s, n)
        else:
            D, Inc = _incidence(self.links_s, n, nb)
            self.D_ls, self.I_ls = D.dense(), Inc.dense()  # numpy (used in prepare)
            D, Inc = _incidence(self.rads_s, n, nb)
            self.D_rs, self.I_rs = D.dense(), Inc.dense()
        D, Inc = _incidence(self.links_d, n, nb)
        Dn, Db = _split_rows(D, n)
        self.Dd_n, self.Dd_b, self.Id = self._mat(Dn), self._mat(Db), self._mat(Inc)
        self.Ad_neg = self._mat(_neg_abs(Inc, 1.0))
        D, Inc = _incidence(self.rads_d, n, nb)
        Dn, Db = _split_rows(D, n)
        self.Dr_n, self.Dr_b, self.Ir = self._mat(Dn), self._mat(Db), self._mat(Inc)
        self.Ar_neg4 = self._mat(_neg_abs(Inc, 4.0))
        self.has_links_s = bool(self.links_s) or bool(self.fluids_lin)

    def _input_only_split(self) -> None:
        """Input-only vs state-dependent work. Items that do not read a node temperature (directly or through
        other items) depend on the inputs alone; ``rhs_u`` evaluates them once per sample (a rollout does it
        for the whole input sequence at once, outside the time loop) together with every heat flow whose
        coefficients are input-only, reduced to an affine form ``q + d·T`` per node. ``rhs_T`` then does only
        the state-dependent work per right-hand-side evaluation."""
        P = self.plan
        td = P.tdep
        self._u_items = [self._items[it] for it in P.dyn_order if not td[it]]
        self._t_items = [self._items[it] for it in P.dyn_order if td[it]]
        self._u_pnames = [nm for kd, nm in P.dyn_order if kd == "p" and not td[(kd, nm)]]
        self._u_fnames = [nm for kd, nm in P.dyn_order if kd == "f" and not td[(kd, nm)]]
        self._t_fnames = [nm for kd, nm in P.dyn_order if kd == "f" and td[(kd, nm)]]

        self.tb_u = not any(td[("p", P.bnd_param[b])] for b in P.bnds)  # boundary temperatures input-only
        ft = P.flow_targets
        self.pe_aff = [(pe, h, c) for pe, h, c in P.peltiers
                       if f"{pe.name}.Q_hot" not in ft and f"{pe.name}.Q_cold" not in ft
                       and not any(td[("p", q)] for q in (pe.current, pe.seebeck, pe.resistance))
                       and (self.tb_u or (h[0] == "n" and c[0] == "n"))]
        self.pe_gen = [x for x in P.peltiers if x not in self.pe_aff]
        self.fnl_aff = [f for f in self.fluids_nl if f"{f.name}.Q" not in ft
                        and not any(td[("p", q)] for q in (f.mdot, f.cp, f.ua, f.inlet))]
        self.fnl_gen = [f for f in self.fluids_nl if f not in self.fnl_aff]
        self.flin_u = [f for f in self.fluids_lin if not P.is_static(f.inlet) and not td[("p", f.inlet)]]
        self.flin_t = [f for f in self.fluids_lin if not P.is_static(f.inlet) and td[("p", f.inlet)]]
        self.src_u = [s for s in self.sources_d if not td[("p", s.value)]]
        self.src_t = [s for s in self.sources_d if td[("p", s.value)]]
        self.hl_u = [(node, fn, i) for node, (fn, i) in P.heat_loads.items()
                     if not P.static[("f", fn.name)] and not td[("f", fn.name)]]
        self.hl_t = [(node, fn, i) for node, (fn, i) in P.heat_loads.items() if td[("f", fn.name)]]

    def _affine_terms(self) -> None:
        """Rows of the input-only affine terms ``q`` (W) and ``d`` (W/K) and their nodes."""
        P = self.plan
        n, nb = P.n, P.nb
        qrows, drows = [], []
        for pe, h, c in self.pe_aff:
            qrows += [h, c]
            drows += [h, c]
        for f in self.fnl_aff:
            qrows.append(("n", P.node_idx[f.node]))
            drows.append(("n", P.node_idx[f.node]))
        qrows += [("n", P.node_idx[f.node]) for f in self.flin_u]
        qrows += [("n", P.node_idx[s.node]) for s in self.src_u]
        qrows += [("n", P.node_idx[node]) for node, _, _ in self.hl_u]
        self.Eq = self._mat(_rows_matrix(qrows, n)) if qrows else None
        self.Ed = self._mat(_rows_matrix(drows, n)) if drows else None
        self.has_ctx_q = bool(qrows) or (not self.bnd_static and self.tb_u and nb > 0
                                         and (bool(self.links_s) or bool(self.rads_s)))

    def _point_flows(self) -> None:
        """Point flows evaluated per right-hand side (state-dependent), their nodes and diagonal terms."""
        P = self.plan
        n = P.n
        rows = []
        for pe, h, c in self.pe_gen:
            rows.append(h)
            rows.append(c)
        rows += [("n", P.node_idx[f.node]) for f in self.fnl_gen]
        rows += [("n", P.node_idx[f.node]) for f in self.flin_t]
        rows += [("n", P.node_idx[s.node]) for s in self.src_t]
        rows += [("n", P.node_idx[node]) for node, _, _ in self.hl_t]
        self.n_point = len(rows)
        self.Pm = self._mat(_rows_matrix(rows, n))
        # diagonal terms (expeuler) of the state-dependent Peltier sides and non-linear fluids
        drows = []
        for pe, h, c in self.pe_gen:
            drows += [h, c]
        drows += [("n", P.node_idx[f.node]) for f in self.fnl_gen]
        self.Pd = self._mat(_rows_matrix(drows, n))

    def _context_needs(self) -> None:
        """The input-only parameters that the state-dependent work reads from the per-sample context."""
        P = self.plan
        td = P.tdep
        need = set()
        for it in P.dyn_order:
            if td[it]:
                need |= {nm for kd, nm in P.deps[it] if kd == "p"}
        # links whose conductances all depend on the inputs alone (a resistance learned as a function of a command):
        # their conductance vector is part of the per-sample context (``rhs_u``, ``"gD"``), made once per sample
        # instead of once per right-hand-side evaluation (a reciprocal, a stack and a scalar slice per link per
        # stage). On the doctor's case study one such resistance took a JAX rollout of 14 401 samples from 3.4 to
        # 9.6 ms, 8.2 ms with the conductances made here, 5.0 ms with them put in place in the node matrix of a small
        # model (``links_in_matrix``, NODE_MATRIX_MAX; the least of 30 calls; BENCHMARKS.md, 2026-12-05).
        u_names = set(self._u_pnames)
        self._links_d_u = bool(self.links_d) and all(lk[3] in u_names for lk in self.links_d)
        if not self._links_d_u:
            need |= {lk[3] for lk in self.links_d}
        need |= {q for r in self.rads_d for q in r[3]}
        need |= {q for pe, _, _ in self.pe_gen for q in (pe.current, pe.seebeck, pe.resistance)}
        need |= {q for f in self.fnl_gen for q in (f.mdot, f.cp, f.ua, f.inlet)}
        if not self.C_static:
            need |= {nd.capacitance for nd in P.net.nodes}
        if not self.tau_static:
            need |= {s.lag for s in P.lagged}
        if not self.tb_u:
            need |= {P.bnd_param[b] for b in P.bnds}
        self._ctx_s = [nm for nm in self._u_pnames if nm in need]

    def _vectorised_links(self) -> None:
        """Links whose conductances are all targets of vectorised, state-dependent learned functions (one or
        several) of one form: their conductance vector is one gather of the functions' target vectors put end to
        end, instead of a slice and a division per link (on XLA's CPU each of those a kernel of its own in the time
        loop, four times a step with RK4: the doctor's second-round network of the case study, two such functions,
        went from 30 kernels a step to 14 and from 4.0 to 2.7 µs a step, the outputs the same to the bit; issue
        18)."""
        P = self.plan
        td = P.tdep
        self._links_vec = None
        self._links_d_keys = [lk[0] for lk in self.links_d]
        if self.links_d:
            ps = [lk[3] for lk in self.links_d]
            forms = {lk[4] for lk in self.links_d}
            owners = [P.param_targets[q][0].name if q in self._vec_targets else None for q in ps]
            if None not in owners and len(forms) == 1:
                fnames = list(dict.fromkeys(owners))  # in the order of their first link
                if all(td[("f", f)] for f in fnames):
                    offset, at = {}, 0
                    for f in fnames:
                        offset[f] = at
                        at += len(self._vec_fns[f][0])
                    idx = [offset[f] + self._vec_fns[f][0].index(q) for f, q in zip(owners, ps)]
                    self._links_vec = (tuple(fnames), None if idx == list(range(at)) else idx, forms.pop())
        self._Tb_in_ctx = P.nb > 0 and self.tb_u and any(h[0] == "b" or c[0] == "b" for _, h, c in self.pe_gen)

    def _lag_and_sensor_maps(self) -> None:
        """Lag states (sources from nodes or boundaries) and the sensor map; items the outputs need."""
        P = self.plan
        n, nb = P.n, P.nb
        nl = len(P.lagged)
        Sl_n = Coo((n, nl))
        Sl_b = Coo((nb, nl))
        for k, s in enumerate(P.lagged):
            if s.node in P.node_idx:
                Sl_n.add(P.node_idx[s.node], k, 1.0)
            else:
                Sl_b.add(P.bnd_idx[s.node], k, 1.0)
        self.nl = nl
        self.Sl_n, self.Sl_b, self.lag_from_bnd = self._mat(Sl_n), self._mat(Sl_b), Sl_b.any()
        Sy = Coo((P.ns, len(P.net.sensors)))
        Sy_b = Coo((nb, len(P.net.sensors)))
        lag_k = {s.name: k for k, s in enumerate(P.lagged)}
        for j, s in enumerate(P.net.sensors):
            if s.name in lag_k:
                Sy.add(n + lag_k[s.name], j, 1.0)
            elif s.node in P.node_idx:
                Sy.add(P.node_idx[s.node], j, 1.0)
            else:
                Sy_b.add(P.bnd_idx[s.node], j, 1.0)
        self.Sy, self.Sy_b, self.y_from_bnd = self._mat(Sy), self._mat(Sy_b), Sy_b.any()
        need = set()
        if not self.off_static:
            need |= {("p", s.offset) for s in P.net.sensors if s.offset}
        if self.y_from_bnd and not self.bnd_static:
            need |= {("p", P.bnd_param[b]) for b in P.bnds}
        anc = P.ancestors(need)
        self._out_items = [self._items[it] for it in P.dyn_order if it in anc]

    def _first_layer_blocks(self) -> None:
        """One T-linear product per right-hand side.

        Every product of the node temperatures by a matrix that is
        constant over a rollout — the static conductance matrix, the gather of dynamic links' endpoints, the
        lag sources, and the first layer of state-dependent linear/MLP functions (their input gather and
        normalisation folded into the weights, ``A_T·W0``; the input-only part ``cx·W0 + b0`` comes from
        rhs_u, once per sample) — is one matmul ``Tn @ L`` by a matrix ``L`` assembled once per call in
        ``prepare``, whose column blocks are sliced apart (on CPU each small product is a kernel launch)."""
        P, n, nl = self.plan, self.plan.n, self.nl
        td = P.tdep
        self._fold = []
        for fname in self._t_fnames:
            fn = P.fns[fname]
            ins = P.fn_inputs[fname]
            if fn.kind not in ("mlp", "linear") or not any(kd == "node" for kd, _ in ins):
                continue
            if any(kd == "param" and not P.is_static(nm) and td[("p", nm)] for kd, nm in ins):
                continue  # a state-dependent parameter input: the generic path
            self._fold.append(fname)
        blocks = []
        # links whose conductances depend on the inputs alone, in a small dense JAX model: a program traced forward
        # only (Backend.no_grad) forms the node matrix M + Σ g_k P_k in place in each right-hand side
        # (NODE_MATRIX_MAX) and reads neither block of L (XLA drops them)
        nd = len(self.links_d)
        self.links_in_matrix = (self.xp.name == "jax" and self._links_d_u and not self.sparse
                                and n * n * (nd + 1) <= NODE_MATRIX_MAX and (self.tb_u or not P.nb))
        self.P_links = []
        if self.links_in_matrix:
            D, Inc = _incidence(self.links_d, n, P.nb)
            Dn = D.dense()[:n]
            Id = Inc.dense()
            self.P_links = [self.xp.asarray(np.outer(Dn[:, k], Id[k])) for k in range(nd)]
        if self.has_links_s:
            blocks.append(("M", n))
        if self.links_d:
            blocks.append(("D", nd))
        if nl:
            blocks.append(("S", nl))
        for fname in self._fold:
            fn = P.fns[fname]
            width = int(fn.hidden[0]) if fn.kind == "mlp" and fn.hidden else len(fn.targets)
            blocks.append((f"f:{fname}", width))
        self._L_blocks = blocks

    # -- item closures ---------------------------------------------------------------------------

    def _param_item(self, p, expr_fn):
        xp = self.xp
        name = p.name
        target = self.plan.param_targets.get(name)
        positive = p.role in POSITIVE_ROLES
        if name in self._vec_targets:  # set by its function's item (vectorised)
            return _noop_item
        if target is None and p.is_constant:
            def item_c(prep, env):  # the value is in env.vals already: only a scale changes it (packed
                s = prep.scales.get(name)  # constants stay unread, see _PackedVals)
                if s is not None:
                    env.vals[name] = env.vals[name] * s
            return item_c
        if target is None:
            def item(prep, env):
                v = expr_fn(env)
                s = prep.scales.get(name)
                env.vals[name] = v if s is None else v * s
            return item
        fn, i = target
        fname = fn.name

        def item_t(prep, env):
            v = expr_fn(env)
            v = _learned.target_value(xp, env.z[fname][..., i], v, positive, prep.yscale[fname][i])
            s = prep.scales.get(name)
            env.vals[name] = v if s is None else v * s
        return item_t

    def _fn_item(self, fn):
        xp = self.xp
        fname = fn.name

        def item(prep, env):
            pre = env.pre.get(fname) if env.pre is not None else None
            if pre is not None:  # first layer folded into rhs_T's one T-linear product (see _Core.__init__)
                z = _apply_from_first(xp, fn, prep.arrays[fname], pre)
            elif fname in prep.fnlin:  # dynamic: matmul gather + normalisation prepared once
                A_T, A_u, bias, dyn_pu, A_pu, dyn_pT, A_pT = prep.fnlin[fname]
                cx = env.cx.get(fname) if env.cx is not None else None
                if cx is None:  # the input-only part
                    cx = self._fn_cx(prep, env, fname)
                xn = cx
                if A_T is not None:
                    xn = xn + xp.matmul(env.T, A_T)
                if dyn_pT:
                    xn = xn + xp.matmul(xp.stack([env.vals[q] for q in dyn_pT], axis=-1), A_pT)
                z = _learned.apply_normalised(xp, fn, prep.arrays[fname], xn, self._mono.get(fname))
            else:  # static: all inputs are static parameters
                arrays = prep.arrays[fname]
                ins = self.plan.fn_inputs[fname]
                if ins:
                    x = xp.stack([env.vals[q] for _, q in ins], axis=-1)
                    xn = _learned.normalise(x, arrays)
                else:
                    xn = None
                z = _learned.apply_normalised(xp, fn, prep.arrays[fname], xn, self._mono.get(fname))
            env.z[fname] = z
            if vec is not None:
                V = _learned.target_value(xp, z, prep.tnom[fname], positive, prep.arrays[fname]["y_scale"])
                sv = prep.tscale[fname]
                if sv is not None:
                    V = V * sv
                env.z[("V", fname)] = V
                for i, nm in enumerate(names):
                    env.vals[nm] = V[..., i]

        vec = self._vec_fns.get(fname)
        names, positive = vec if vec is not None else ((), False)
        return item

    def _fn_cx(self, prep, env, fname):
        """The input-only part of a dynamic function's normalised input: ``bias + u @ A_u + stack(input-only
        parameters) @ A_pu`` (``(..., n_in)``, or the bias alone)."""
        xp = self.xp
        A_T, A_u, bias, dyn_pu, A_pu, dyn_pT, A_pT = prep.fnlin[fname]
        cx = bias
        if A_u is not None:
            cx = cx + xp.matmul(env.u, A_u)
        if dyn_pu:
            cx = cx + xp.matmul(xp.stack([env.vals[q] for q in dyn_pu], axis=-1), A_pu)
        return cx

    # -- shared helpers ----------------------------------------------------------------------------

    @staticmethod
    def _g(vals, p, form):
        return 1.0 / vals[p] if form == "R" else vals[p]

    def _heat_load(self, prep, z, fn, i):
        return _learned.target_value(self.xp, z[fn.name][..., i], 0.0, False, prep.yscale[fn.name][i], fn.replace)

    def _flow_target(self, prep, env, key, q):
        t = self.plan.flow_targets.get(key)
        if t is not None:
            fn, i = t
            q = _learned.target_value(self.xp, env.z[fn.name][..., i], q, False, prep.yscale[fn.name][i], fn.replace)
        s = prep.scales.get(key)
        return q if s is None else q * s

    @staticmethod
    def _vt(v, Tn, Tb):
        return Tn[..., v[1]] if v[0] == "n" else Tb[..., v[1]]

    def values(self, prep, T, u, items=None) -> _Env:
        env = _Env(prep.vals.copy(), dict(prep.z), T, u)
        for item in (self._dyn_items if items is None else items):
            item(prep, env)
        return env

    def _Tb(self, prep, vals):
        P = self.plan
        if not P.nb:
            return None
        if prep.Tb is not None:
            return prep.Tb
        return self.xp.stack([vals[P.bnd_param[b]] for b in P.bnds], axis=-1)

    def _peltier(self, prep, env, pe, h, c, Tn, Tb):
        vals = env.vals
        I, S, R = vals[pe.current], vals[pe.seebeck], vals[pe.resistance]
        qh, qc = _physics.peltier_heat_flows(S, R, I, self._vt(h, Tn, Tb), self._vt(c, Tn, Tb))
        return (self._flow_target(prep, env, f"{pe.name}.Q_hot", qh),
                self._flow_target(prep, env, f"{pe.name}.Q_cold", qc), S * I)

    def _fluid_G(self, vals, f):
        return _physics.fluid_conductance(self.xp, vals[f.mdot], vals[f.cp], vals[f.ua])

    def _flow_scaled(self, prep, key, q):
        s = prep.scales.get(key)
        return q if s is None else q * s

    def _driven_flows(self, prep, vals, z, fluids, sources, loads) -> list:
        """Heat flows (W) that enter a node's balance as a plain term: the inlet part ``G·T_in`` of the
        ``fluids`` whose conductance is linear (``prep.lin_fluid``), the ``sources`` and the learned heat
        ``loads`` ``(node, fn, i)``, each scaled by its ``scale:`` key."""
        out = []
        if fluids:
            lin_G = {f.name: G for f, G in prep.lin_fluid}
            out += [lin_G[f.name] * vals[f.inlet] for f in fluids]
        out += [self._flow_scaled(prep, f"{s.name}.Q", vals[s.value]) for s in sources]
        out += [self._flow_scaled(prep, f"Q[{node}]", self._heat_load(prep, z, fn, i)) for node, fn, i in loads]
        return out

    def _diag_term(self, prep, key, d):
        t = self.plan.flow_targets.get(key)
        if t is not None and t[0].replace:
            return d * 0.0
        return self._flow_scaled(prep, key, d)
