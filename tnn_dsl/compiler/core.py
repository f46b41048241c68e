"""The right-hand side of a compiled network (:class:`_Core`, on top of :class:`~.assembly._Assembly`):
``prepare(params)`` once per call (values, static matrices, the T-linear matrix), then per sample the
input-only context ``rhs_u`` and per evaluation ``rhs_T``; ``outputs`` and ``heat_flows`` for readings and
inspection. Shapes: ``T (..., n_states)`` K, ``u (..., n_inputs)`` SI, heat W, rates K/s."""

from __future__ import annotations

import functools

import numpy as np

from . import learned as _learned
from . import physics as _physics
from . import sparse as _sparse
from .assembly import PACKED_KEY, _Assembly, _diag, _Env, _first_layer, _PackedVals, _Prep
from .backends.adapter import forward_only_active

__all__ = ["_Core"]


def _unit(n: int, i: int) -> np.ndarray:
    """The unit vector ``e_i`` of length ``n`` (a point heat flow onto node ``i``)."""
    e = np.zeros(n)
    e[i] = 1.0
    return e


class _Core(_Assembly):
    """The plan bound to an array namespace: ``prepare(params)`` once per call, then ``rhs``,
    ``outputs``, ``heat_flows`` with the prepared values."""

    # -- prepare ---------------------------------------------------------------------------------

    def prepare(self, params) -> _Prep:
        """Everything constant over one call (a rollout, a steady state): parameter values, learned-function
        arrays, the static conductance and radiation matrices, constant heat, inverses and the T-linear
        matrix ``L``."""
        prep = self._prepare_values(params)
        cQ = self._static_conductances(prep)
        cQ = self._static_radiation(prep, cQ)
        prep.cQ = self._static_loads(prep, cQ)
        self._inverses(prep)
        self._T_linear_matrix(prep)
        return prep

    def _prepare_values(self, params) -> _Prep:
        """Parameter values, learned-function arrays and the static items, evaluated once."""
        xp, P = self.xp, self.plan
        prep = _Prep()
        prep.scales = {k[6:]: xp.asarray(v) for k, v in params.items() if k.startswith("scale:")}
        prep.arrays = {}
        prep.yscale = {}
        for fn in P.net.learned:
            arrs = {k: xp.asarray(params[f"{fn.name}.{k}"]) for k in _learned.array_shapes(
                fn, len(fn.inputs), len(fn.targets))}
            prep.arrays[fn.name] = arrs
            prep.yscale[fn.name] = arrs["y_scale"]  # indexed where used: views of it would be aliasing graph inputs
        packed = params.get(PACKED_KEY)
        if packed is not None:  # constants packed into one vector (large networks, see Model._packed)
            vals = _PackedVals(xp.asarray(packed), self.const_index)
        else:
            vals = {p.name: xp.asarray(params[p.name]) for p in P.net.params if p.is_constant}
        prep.tnom, prep.tscale = {}, {}
        for fname, (names, _) in self._vec_fns.items():
            prep.tnom[fname] = xp.stack([vals[nm] for nm in names], axis=-1)
            if any(nm in prep.scales for nm in names):
                prep.tscale[fname] = xp.stack([prep.scales.get(nm, 1.0) for nm in names], axis=-1)
            else:
                prep.tscale[fname] = None
        env = _Env(vals, {}, None, None)
        prep.fnlin = {}
        for it in P.static_order:
            self._items[it](prep, env)
        prep.vals = env.vals
        prep.z = env.z
        for fn in P.net.learned:
            if not P.static[("f", fn.name)]:
                prep.fnlin[fn.name] = self._fnlin(fn, prep)
        return prep

    def _static_conductances(self, prep):
        """Static boundaries, the static conductance matrix (links and linear fluids) and its constant heat
        (W per node, or None)."""
        xp, P = self.xp, self.plan
        n, nb = P.n, P.nb
        vals = prep.vals
        fscale = functools.partial(self._flow_scaled, prep)
        # boundaries
        if nb and self.bnd_static:
            prep.Tb = xp.stack([vals[P.bnd_param[b]] for b in P.bnds], axis=-1) if nb else None
        else:
            prep.Tb = None
        cQ = None
        # static links (+ linear fluids on the diagonal)
        prep.M_nn = prep.M_bn = None
        if self.has_links_s:
            M = None
            if self.links_s:
                g = self._gathered_conductances(prep, self.links_s)
                if g is None:
                    g = xp.stack([fscale(k, self._g(vals, p, form)) for k, _, _, p, form in self.links_s], axis=-1)
                if self.sparse:
                    M = _sparse.weighted(xp, *self.C_ls, g, (n + nb, n))
                else:
                    M = _physics.conductance_matrix(xp, xp.asarray(self.D_ls), g, xp.asarray(self.I_ls))
            lin = []
            for f in self.fluids_lin:
                G = fscale(f"{f.name}.Q", _physics.fluid_conductance(xp, vals[f.mdot], vals[f.cp], vals[f.ua]))
                lin.append((f, G))
                i = P.node_idx[f.node]
                if self.sparse:
                    term = _sparse.SparseMatrix(xp, np.asarray([i]), np.asarray([i]),
                                                -xp.stack([xp.asarray(G) * 1.0], axis=-1), (n + nb, n))
                    M = term if M is None else _sparse.add(xp, M, term)
                else:
                    E = np.zeros((n + nb, n))
                    E[i, i] = -1.0
                    term = xp.asarray(E) * G
                    M = term if M is None else M + term
                if P.is_static(f.inlet):
                    q = xp.asarray(_unit(n, i)) * (G * vals[f.inlet])
                    cQ = q if cQ is None else cQ + q
            prep.lin_fluid = lin
            prep.M_nn, prep.M_bn = self._split_vertex_rows(M)
            prep.diag_static = _diag(xp, prep.M_nn, n)
            if nb and self.bnd_static:
                q = self._mm(prep.Tb, prep.M_bn)
                cQ = q if cQ is None else cQ + q
                prep.M_bn = None
        else:
            prep.lin_fluid = []
            prep.diag_static = None
        return cQ

    def _gathered(self, prep, names):
        """``stack([vals[q] for q in names])`` as one gather from the packed constants, when the values are
        packed (:data:`PACKED_KEY`) and every name is a plain constant without a ``scale:``; else None."""
        vals = prep.vals
        if not isinstance(vals, _PackedVals) or any(q not in self.const_index or q in prep.scales for q in names):
            return None
        return _sparse._take(self.xp, vals.packed, np.asarray([self.const_index[q] for q in names], dtype=np.int64))

    def _gathered_conductances(self, prep, links):
        """The conductances ``(k,)`` W/K of a group of links by gathers from the packed constants (``1/R`` for
        the links written as resistances), or None (see :meth:`_gathered`)."""
        if any(k in prep.scales for k, *_ in links):
            return None
        raw = self._gathered(prep, [lk[3] for lk in links])
        if raw is None:
            return None
        is_r = np.asarray([lk[4] == "R" for lk in links])
        if not is_r.any():
            return raw
        xp = self.xp
        r_idx, g_idx = np.nonzero(is_r)[0], np.nonzero(~is_r)[0]
        parts = [1.0 / _sparse._take(xp, raw, r_idx)]
        if g_idx.size:
            parts.append(_sparse._take(xp, raw, g_idx))
        order = np.argsort(np.concatenate([r_idx, g_idx]), kind="stable")
        return _sparse._take(xp, xp.concat(parts, axis=-1), order)

    def _split_vertex_rows(self, M):
        """``(M[:n], M[n:] or None)`` of a vertex-by-node matrix (dense or sparse)."""
        n, nb = self.plan.n, self.plan.nb
        if self.sparse:
            return M.select_rows(0, n), (M.select_rows(n, n + nb) if nb else None)
        return M[:n], (M[n:] if nb else None)

    def _static_radiation(self, prep, cQ):
        """The static radiation matrix (and its constant heat from constant boundaries)."""
        xp, P = self.xp, self.plan
        n, nb = P.n, P.nb
        vals = prep.vals
        fscale = functools.partial(self._flow_scaled, prep)
        # static radiation
        prep.Mr_nn = prep.Mr_bn = prep.diag_rad = None
        if self.rads_s:
            c = xp.stack([fscale(k, _physics.radiation_coefficient(vals[a], vals[e], vals[f]))
                          for k, _, _, (a, e, f) in self.rads_s], axis=-1)
            if self.sparse:
                M = _sparse.weighted(xp, *self.C_rs, c, (n + nb, n))
            else:
                M = _physics.conductance_matrix(xp, xp.asarray(self.D_rs), c, xp.asarray(self.I_rs))
            prep.Mr_nn, prep.Mr_bn = self._split_vertex_rows(M)
            prep.diag_rad = 4.0 * _diag(xp, prep.Mr_nn, n)
            if nb:
                if self.bnd_static:
                    q = self._mm(prep.Tb**4, prep.Mr_bn)
                    cQ = q if cQ is None else cQ + q
                    prep.Mr_bn = None
        return cQ

    def _static_loads(self, prep, cQ):
        """Static sources and static learned heat loads added to the constant heat."""
        xp, P = self.xp, self.plan
        n = P.n
        vals = prep.vals
        fscale = functools.partial(self._flow_scaled, prep)
        # static sources and static learned heat loads
        for s in self.sources_s:
            q = xp.asarray(_unit(n, P.node_idx[s.node])) * fscale(f"{s.name}.Q", vals[s.value])
            cQ = q if cQ is None else cQ + q
        for node, (fn, i) in P.heat_loads.items():
            if P.static[("f", fn.name)]:
                v = fscale(f"Q[{node}]", self._heat_load(prep, prep.z, fn, i))
                q = xp.asarray(_unit(n, P.node_idx[node])) * v
                cQ = q if cQ is None else cQ + q
        return cQ

    def _inverses(self, prep) -> None:
        """Static ``1/C``, ``1/τ`` and sensor offsets."""
        xp, P = self.xp, self.plan
        vals = prep.vals
        if self.C_static:
            C = self._gathered(prep, [nd.capacitance for nd in P.net.nodes])
            if C is None:
                C = xp.stack([vals[nd.capacitance] for nd in P.net.nodes], axis=-1)
            prep.invC = 1.0 / C
        else:
            prep.invC = None
        if self.nl and self.tau_static:
            prep.inv_tau = 1.0 / xp.stack([vals[s.lag] for s in P.lagged], axis=-1)
        else:
            prep.inv_tau = None
        if self.off_static and P.net.sensors:
            prep.offsets = xp.stack([vals[s.offset] if s.offset else 0.0 for s in P.net.sensors], axis=-1)
        else:
            prep.offsets = None

    def _T_linear_matrix(self, prep) -> None:
        """``L``: the blocks of the one T-linear product of each right-hand side (see ``_first_layer_blocks``)."""
        xp, P = self.xp, self.plan
        prep.g_static_d = None
        prep.L, prep.Lsl = None, {}
        if self._L_blocks:
            parts, start = [], 0
            for key, width in self._L_blocks:
                if key == "M":
                    parts.append(prep.M_nn)
                elif key == "D":
                    parts.append(self.Dd_n)
                elif key == "S":
                    parts.append(self.Sl_n)
                else:
                    fname = key[2:]
                    W, _ = _first_layer(P.fns[fname], prep.arrays[fname])
                    parts.append(self._first_layer_block(prep.fnlin[fname][0], W, fname))
                prep.Lsl[key] = (start, start + width)
                start += width
            if len(parts) == 1:
                prep.L = parts[0]
            elif self.sparse:
                prep.L = _sparse.concat_columns(xp, parts)
            else:
                prep.L = xp.concat(parts, axis=-1)

    def _first_layer_block(self, A_T, W, fname):
        """The block ``A_T[:n] @ W0`` of a learned function folded into the T-linear product: dense, or (sparse
        models) only the rows of the nodes the function reads."""
        xp, P = self.xp, self.plan
        n = P.n
        if not self.sparse:
            return xp.matmul(A_T[:n], W)
        rows = np.asarray(sorted({P.node_idx[nm] for kd, nm in P.fn_inputs[fname] if kd == "node"}), dtype=np.int64)
        B = xp.matmul(A_T[_sparse._index(xp, rows)], W)  # (len(rows), width)
        width = int(xp.shape(B)[-1])
        return _sparse.SparseMatrix(xp, np.repeat(rows, width), np.tile(np.arange(width), len(rows)),
                                    xp.concat([B[i] for i in range(len(rows))], axis=-1), (n, width))

    def _fnlin(self, fn, prep):
        """Matrices that gather and normalise a dynamic function's inputs: ``xn = T @ A_T + u @ A_u +
        bias + stack(input-only params) @ A_pu + stack(state-dependent params) @ A_pT``."""
        xp, P = self.xp, self.plan
        arrs = prep.arrays[fn.name]
        ins = P.fn_inputs[fn.name]
        k = len(ins)
        inv = 1.0 / arrs["x_scale"]
        ST = np.zeros((P.ns, k))
        SU = np.zeros((len(P.inputs), k))
        static_vals: dict[int, str] = {}
        dyn_pu, dyn_pT = [], []
        SPu_rows, SPT_rows = [], []
        for j, (kind, name) in enumerate(ins):
            if kind == "node":
                ST[P.node_idx[name], j] = 1.0
            elif kind == "input":
                SU[P.input_idx[name], j] = 1.0
            elif P.is_static(name):
                static_vals[j] = name
            else:
                row = np.zeros(k)
                row[j] = 1.0
                if P.tdep[("p", name)]:
                    dyn_pT.append(name)
                    SPT_rows.append(row)
                else:
                    dyn_pu.append(name)
                    SPu_rows.append(row)
        bias = -arrs["x_mean"] * inv
        if static_vals:
            sv = [prep.vals[static_vals[j]] if j in static_vals else 0.0 for j in range(k)]
            bias = bias + xp.stack(sv, axis=-1) * inv
        A_T = xp.asarray(ST) * inv if ST.any() else None
        A_u = xp.asarray(SU) * inv if SU.any() else None
        A_pu = xp.asarray(np.asarray(SPu_rows)) * inv if dyn_pu else None
        A_pT = xp.asarray(np.asarray(SPT_rows)) * inv if dyn_pT else None
        return (A_T, A_u, bias, dyn_pu, A_pu, dyn_pT, A_pT)

    # -- the right-hand side ------------------------------------------------------------------------

    def rhs(self, prep, T, u, with_diag=False):
        """``dT/dt (..., n_states)`` K/s; with ``with_diag`` also the diagonal of the linear part (1/s)."""
        return self.rhs_T(prep, self.rhs_u(prep, u), T, with_diag)

    def rhs_u(self, prep, u) -> dict:
        """The input-only part of the right-hand side for inputs ``u (..., n_inputs)`` (any leading axes, e.g.
        a whole input sequence ``(..., N, n_inputs)``): a dict with ``"s"`` (input-only parameter values,
        shape ``u.shape[:-1]``), ``"v"`` (vectors ``(..., k)``: ``"q"`` heat (W) and ``"d"`` coefficients (W/K)
        of the affine node terms ``q + d·T``, ``"Tb"`` boundary temperatures and their products with the
        gather matrices, ``"cx:<fn>"`` input-only part of a learned function's normalised input,
        ``"z:<fn>"`` outputs of input-only learned functions) and ``"u"``. ``rhs_T`` reads one sample of it."""
        xp, P = self.xp, self.plan
        env = _Env(prep.vals.copy(), dict(prep.z), None, u)
        for item in self._u_items:
            item(prep, env)
        vals = env.vals
        vec: dict = {}
        bshape = tuple(xp.shape(u)[:-1])

        def per_sample(v):  # every context array carries the samples' leading axes
            return xp.broadcast_to(v, (*bshape, *xp.shape(v)[-1:]))

        for fname in self._u_fnames:
            vec[f"z:{fname}"] = per_sample(env.z[fname])
        for fname in self._t_fnames:
            cx = self._fn_cx(prep, env, fname)
            if fname in self._fold:  # the input-only part of the first layer's pre-activation
                W, b = _first_layer(P.fns[fname], prep.arrays[fname])
                vec[f"cxw:{fname}"] = per_sample(xp.matmul(cx, W) + b)
            else:
                vec[f"cx:{fname}"] = per_sample(cx)
        Tb = None
        if P.nb and self.tb_u:
            Tb = self._Tb(prep, vals)
            if prep.Tb is None:  # input-dependent boundaries: broadcast to the samples
                Tb = xp.broadcast_to(Tb, (*bshape, P.nb))
                if self._Tb_in_ctx:
                    vec["Tb"] = Tb
                if self.links_d:
                    vec["tbD"] = self._mm(Tb, self.Dd_b)
                if self.rads_d:
                    vec["tbR"] = self._mm(Tb**4, self.Dr_b)
                if self.nl and self.lag_from_bnd:
                    vec["tbL"] = self._mm(Tb, self.Sl_b)
        q = None

        def add(a, b):
            return b if a is None else a + b

        if self._links_d_u:  # input-only dynamic conductances (W/K), one row per sample
            vec["gD"] = per_sample(self._links_d_conductances(prep, vals))
            if self._in_matrix() and P.nb:
                # their boundary ends are input-only too: that heat joins the affine heat q (rhs_T forms the node
                # matrix from gD alone)
                tbD = vec.pop("tbD", None)
                if tbD is None and prep.Tb is not None:
                    tbD = self._mm(prep.Tb, self.Dd_b)
                if tbD is not None:
                    q = add(q, self._mm(vec["gD"] * tbD, self.Id))
        if Tb is not None and prep.Tb is None:
            if prep.M_bn is not None:
                q = add(q, self._mm(Tb, prep.M_bn))
            if prep.Mr_bn is not None:
                q = add(q, self._mm(Tb**4, prep.Mr_bn))
        if self.Eq is not None:
            qs, ds = self._affine_flows(prep, env, Tb)
            q = add(q, self._mm(xp.broadcast_to(xp.stack(qs, axis=-1), (*bshape, len(qs))), self.Eq))
            if ds:
                vec["d"] = self._mm(xp.broadcast_to(xp.stack(ds, axis=-1), (*bshape, len(ds))), self.Ed)
        if q is not None:
            vec["q"] = per_sample(q if prep.cQ is None else q + prep.cQ)
        scal = {k: xp.broadcast_to(vals[k], bshape) for k in self._ctx_s}
        return {"s": scal, "v": vec, "u": u}

    def _affine_flows(self, prep, env, Tb) -> tuple[list, list]:
        """The input-only point flows in affine form: their heat ``q`` (W) and coefficients ``d`` (W/K) of
        ``q + d·T`` (Peltier sides, non-linear fluids with input-only coefficients, linear fluids with an
        input-only inlet, input-only sources and learned heat loads), in the rows of ``Eq``/``Ed``."""
        vals = env.vals
        qs, ds = [], []
        for pe, h, c in self.pe_aff:
            I, S, R = vals[pe.current], vals[pe.seebeck], vals[pe.resistance]
            # Q_hot = S·T_hot·I + ½R I² (eq. 2.12–2.13) = d·T + q; a boundary side is a known temperature
            q_h, q_c = _physics.peltier_heat_flows(S, R, I, 0.0, 0.0)
            SI = S * I
            sh = prep.scales.get(f"{pe.name}.Q_hot")
            sc = prep.scales.get(f"{pe.name}.Q_cold")
            dh, dc = SI, -SI
            if h[0] == "b":
                q_h = q_h + SI * Tb[..., h[1]]
            if c[0] == "b":
                q_c = q_c - SI * Tb[..., c[1]]
            if sh is not None:
                q_h, dh = q_h * sh, dh * sh
            if sc is not None:
                q_c, dc = q_c * sc, dc * sc
            qs += [q_h, q_c]
            ds += [dh, dc]
        for f in self.fnl_aff:
            G = self._flow_scaled(prep, f"{f.name}.Q", self._fluid_G(vals, f))
            qs.append(G * vals[f.inlet])
            ds.append(-G)
        qs += self._driven_flows(prep, vals, env.z, self.flin_u, self.src_u, self.hl_u)
        return qs, ds

    def ctx_at(self, ctx, k):
        """Sample ``k`` of a sequence context from :meth:`rhs_u` (inputs ``(..., N, n_inputs)``)."""
        return {"s": {name: v[..., k] for name, v in ctx["s"].items()},
                "v": {name: v[..., k, :] for name, v in ctx["v"].items()},
                "u": ctx["u"][..., k, :]}

    def rhs_T(self, prep, ctx, T, with_diag=False):
        """The right-hand side from one sample's input-only context (:meth:`rhs_u`) and ``T (..., n_states)``."""
        xp, P = self.xp, self.plan
        n = P.n
        vec = ctx["v"]
        u = ctx["u"]
        vals = prep.vals.copy()
        vals.update(ctx["s"])
        z = dict(prep.z)
        cx = None
        if self._u_fnames or self._t_fnames:
            for fname in self._u_fnames:
                z[fname] = vec[f"z:{fname}"]
            cx = {fname: vec[f"cx:{fname}"] for fname in self._t_fnames if fname not in self._fold}
        Tn = T[..., :n] if self.nl else T
        TL = self._mm(Tn, prep.L) if prep.L is not None else None

        def block(key):
            a, b = prep.Lsl[key]
            return TL if (a, b) == (0, xp.shape(TL)[-1]) else TL[..., a:b]

        pre = {fname: vec[f"cxw:{fname}"] + block(f"f:{fname}") for fname in self._fold} if self._fold else None
        env = _Env(vals, z, T, u, cx, pre)
        for item in self._t_items:
            item(prep, env)
        dyn_b = not self.tb_u  # boundary terms not folded into the context
        Tb = vec.get("Tb")
        if Tb is None and P.nb and (dyn_b or prep.Tb is not None):
            Tb = self._Tb(prep, vals)
        dQ = vec.get("q", prep.cQ)
        diag = prep.diag_static if with_diag else None

        def add(a, b):
            return b if a is None else a + b

        in_matrix = self._in_matrix()
        if in_matrix:
            # the node matrix with the input-only links in place, one product (assembly.NODE_MATRIX_MAX)
            gD = vec["gD"]
            A = prep.M_nn
            for k, P_k in enumerate(self.P_links):
                t = gD[..., k, None, None] * P_k
                A = t if A is None else A + t
            dQ = add(dQ, (Tn[..., :, None] * A).sum(-2))  # (its boundaries are input-only: links_in_matrix)
        elif prep.M_nn is not None:
            dQ = add(dQ, block("M"))
            if dyn_b and prep.M_bn is not None:
                dQ = add(dQ, self._mm(Tb, prep.M_bn))
        d = vec.get("d")
        if d is not None:
            dQ = add(dQ, Tn * d)
            if with_diag:
                diag = add(diag, d)
        if prep.Mr_nn is not None:
            Tn3 = Tn * Tn * Tn
            dQ = add(dQ, self._mm(Tn3 * Tn, prep.Mr_nn))
            if dyn_b and prep.Mr_bn is not None:
                dQ = add(dQ, self._mm(Tb**4, prep.Mr_bn))
            if with_diag:
                diag = add(diag, Tn3 * prep.diag_rad)
        if in_matrix:
            if with_diag:
                diag = add(diag, self._mm(vec["gD"], self.Ad_neg))
        elif self.links_d:
            q, dg = self._dynamic_links(prep, vals, env, vec, block("D"), Tb, with_diag)
            dQ = add(dQ, q)
            if with_diag:
                diag = add(diag, dg)
        if self.rads_d:
            q, dg = self._dynamic_radiation(prep, vals, vec, Tn, Tb, with_diag)
            dQ = add(dQ, q)
            if with_diag:
                diag = add(diag, dg)
        if self.n_point:
            q, dg = self._point_flows_T(prep, env, Tn, Tb, with_diag)
            dQ = add(dQ, q)
            if with_diag and dg is not None:
                diag = add(diag, dg)
        if dQ is None:
            dQ = Tn * 0.0
        invC = prep.invC if prep.invC is not None else 1.0 / xp.stack(
            [vals[nd.capacitance] for nd in P.net.nodes], axis=-1)
        dT = dQ * invC
        if with_diag:
            diag = (Tn * 0.0 if diag is None else diag) * invC
        if self.nl:
            dT, diag = self._with_lags(prep, vals, vec, T, dT, diag, block("S"), Tb, with_diag)
        return (dT, diag) if with_diag else dT

    def _dynamic_links(self, prep, vals, env, vec, TL_D, Tb, with_diag):
        """Heat (W per node) through links with dynamic conductances, and their diagonal (or None)."""
        P = self.plan
        diag = None
        lv = self._links_vec
        if "gD" in vec:  # input-only: made with the sample's context (rhs_u)
            g = vec["gD"]
        elif lv is not None and not any(k in prep.scales for k in self._links_d_keys):
            Vs = [env.z[("V", f)] for f in lv[0]]
            V = Vs[0] if len(Vs) == 1 else self.xp.concat(Vs, axis=-1)
            if lv[1] is not None:
                V = V[..., lv[1]]
            g = 1.0 / V if lv[2] == "R" else V
        else:
            g = self._links_d_conductances(prep, vals)
        dX = TL_D
        if P.nb:
            tbD = vec.get("tbD")
            dX = dX + (tbD if tbD is not None else self._mm(Tb, self.Dd_b))
        dQ = self._mm(g * dX, self.Id)
        if with_diag:
            diag = self._mm(g, self.Ad_neg)
        return dQ, diag

    def _in_matrix(self) -> bool:
        """The input-only links go in place in the node matrix (``links_in_matrix``) in this trace: only one run
        forward (:func:`~.backends.adapter.forward_only`); differentiated in reverse, the matrix form was the slower
        (the doctor's MLP check trained 20 % slower with it)."""
        return self.links_in_matrix and forward_only_active()

    def _links_d_conductances(self, prep, vals):
        """The dynamic links' conductances ``(..., n_links_d)`` W/K from parameter values ``vals`` (any leading
        axes: one sample in ``rhs_T``, a whole sequence in ``rhs_u``)."""
        return self.xp.stack([self._flow_scaled(prep, k, self._g(vals, p, form))
                              for k, _, _, p, form in self.links_d], axis=-1)

    def _dynamic_radiation(self, prep, vals, vec, Tn, Tb, with_diag):
        """Heat (W per node) through radiation with dynamic coefficients, and its diagonal (or None)."""
        xp, P = self.xp, self.plan
        diag = None
        c = xp.stack([self._flow_scaled(prep, k, _physics.radiation_coefficient(vals[a], vals[e], vals[f]))
                      for k, _, _, (a, e, f) in self.rads_d], axis=-1)
        dX = self._mm(Tn**4, self.Dr_n)
        if P.nb:
            tbR = vec.get("tbR")
            dX = dX + (tbR if tbR is not None else self._mm(Tb**4, self.Dr_b))
        dQ = self._mm(c * dX, self.Ir)
        if with_diag:
            diag = Tn**3 * self._mm(c, self.Ar_neg4)
        return dQ, diag

    def _point_flows_T(self, prep, env, Tn, Tb, with_diag):
        """State-dependent point flows (Peltier sides, fluids, sources, heat loads) scattered onto the nodes,
        and their diagonal terms (or None)."""
        xp, P = self.xp, self.plan
        vals = env.vals
        diag = None
        pts = []
        dterms = []
        for pe, h, c in self.pe_gen:
            qh, qc, SI = self._peltier(prep, env, pe, h, c, Tn, Tb)
            pts += [qh, qc]
            if with_diag:
                dterms += [self._diag_term(prep, f"{pe.name}.Q_hot", SI),
                           self._diag_term(prep, f"{pe.name}.Q_cold", -SI)]
        for f in self.fnl_gen:
            G = self._fluid_G(vals, f)
            q = G * (vals[f.inlet] - Tn[..., P.node_idx[f.node]])
            pts.append(self._flow_target(prep, env, f"{f.name}.Q", q))
            if with_diag:
                dterms.append(self._diag_term(prep, f"{f.name}.Q", -G))
        pts += self._driven_flows(prep, vals, env.z, self.flin_t, self.src_t, self.hl_t)
        dQ = self._mm(xp.stack(pts, axis=-1), self.Pm)
        if with_diag and dterms:
            diag = self._mm(xp.stack(dterms, axis=-1), self.Pd)
        return dQ, diag

    def _with_lags(self, prep, vals, vec, T, dT, diag, TL_S, Tb, with_diag):
        """Append the lag states' rates ``(T_source − T_s)/τ`` (and their diagonal ``−1/τ``)."""
        xp, P = self.xp, self.plan
        n = P.n
        inv_tau = prep.inv_tau if prep.inv_tau is not None else 1.0 / xp.stack(
            [vals[s.lag] for s in P.lagged], axis=-1)
        src = TL_S
        if self.lag_from_bnd:
            tbL = vec.get("tbL")
            src = src + (tbL if tbL is not None else self._mm(Tb, self.Sl_b))
        dTl = (src - T[..., n:]) * inv_tau
        dT = xp.concat([xp.broadcast_to(dT, (*xp.shape(dTl)[:-1], n)), dTl], axis=-1)
        if with_diag:
            diag = xp.concat([xp.broadcast_to(diag, xp.shape(dT[..., :n])),
                              xp.broadcast_to(-inv_tau, xp.shape(dTl))], axis=-1)
        return dT, diag

    # -- outputs and flows ------------------------------------------------------------------------

    def outputs(self, prep, T, u):
        """Sensor readings ``(..., n_outputs)`` K for states ``T (..., n_states)``."""
        xp, P = self.xp, self.plan
        if not P.net.sensors:
            return T[..., :0]
        y = self._mm(T, self.Sy)
        vals = None
        if self._out_items or self.y_from_bnd:
            vals = self.values(prep, T, u, self._out_items).vals
        if self.y_from_bnd:
            y = y + self._mm(self._Tb(prep, vals), self.Sy_b)
        off = prep.offsets if prep.offsets is not None else xp.stack(
            [vals[s.offset] if s.offset else 0.0 for s in P.net.sensors], axis=-1)
        return y + off

    def heat_flows(self, prep, T, u) -> dict:
        """Every flow (W) by name, element by element (for inspection; see the module docstring)."""
        xp, P = self.xp, self.plan
        env = self.values(prep, T, u)
        vals = env.vals
        Tn = T[..., : P.n]
        Tb = self._Tb(prep, vals)
        out = {}
        for k, a, b, p, form in P.links:
            g = self._flow_scaled(prep, k, self._g(vals, p, form))
            out[k] = _physics.link_heat_flow(g, self._vt(a, Tn, Tb), self._vt(b, Tn, Tb))
        for k, a, b, (ar, e, f) in P.rads:
            q = _physics.radiation_heat_flow(vals[ar], vals[e], vals[f], self._vt(a, Tn, Tb), self._vt(b, Tn, Tb))
            out[k] = self._flow_scaled(prep, k, q)
        for pe, h, c in P.peltiers:
            qh, qc, _ = self._peltier(prep, env, pe, h, c, Tn, Tb)
            out[f"{pe.name}.Q_hot"], out[f"{pe.name}.Q_cold"] = qh, qc
        for f in P.fluids:
            q = _physics.fluid_heat_flow(xp, vals[f.mdot], vals[f.cp], vals[f.ua], vals[f.inlet],
                                         Tn[..., P.node_idx[f.node]])
            out[f"{f.name}.Q"] = self._flow_target(prep, env, f"{f.name}.Q", q)
        for s in P.net.sources:
            out[f"{s.name}.Q"] = self._flow_scaled(prep, f"{s.name}.Q", vals[s.value])
        for node, (fn, i) in P.heat_loads.items():
            out[f"Q[{node}]"] = self._flow_scaled(prep, f"Q[{node}]", self._heat_load(prep, env.z, fn, i))
        shape = xp.shape(Tn)[:-1]
        return {k: xp.broadcast_to(xp.asarray(v) if isinstance(v, float) else v, shape) for k, v in out.items()}
