"""Torch rollouts *with gradients* as two compiled scans: the states forward in time, then the adjoint
(reverse-mode) recursion backward in time.

A compiled torch rollout with gradients used to call one compiled integration step per sample and let autograd
record one node per step: per step it paid dynamo's guard check, the compiled graph's Python wrapper and the
autograd engine's node, forward and backward (hundreds of µs per step on a batch of a few dozen windows, against
tens for the arithmetic). torch 2.13's own ``scan`` differentiates neither what its body closes over (the
parameters) nor, when they are passed through its ``xs``, faster than the step-by-step path. Here the discrete
adjoint is written out instead:

* **forward** (:meth:`AdjointRollout.forward`): one compiled ``scan`` of the model's step over the samples
  without autograd, keeping the states ``S_1 … S_M``;
* **backward**: with ``a_M = ∂L/∂S_M`` and ``a_{k-1} = ∂L/∂S_{k-1} + (∂S_k/∂S_{k-1})ᵀ a_k``, the parameters'
  gradient is ``Σ_k (∂S_k/∂θ)ᵀ a_k`` and each sample's context (the input-only part of the right-hand side)
  gets ``(∂S_k/∂c_{k-1})ᵀ a_k``. One compiled reverse ``scan`` runs the recursion; its body is the vector-Jacobian
  product of one step, traced once into a plain graph of tensor operations (``make_fx`` of ``torch.func.vjp``)
  so that inductor compiles it like any other graph. It recomputes each step's stages from the stored state
  (like JAX's ``checkpoint`` of a step) instead of storing them.

The result is exact to round-off (the same operations in another order): the tests compare states and gradients
with JAX and with eager torch. Compiled programs are kept per :class:`AdjointRollout` (one per model, sample
interval, integrator, sub-steps and parameter layout) and per step shape, and are reused for new parameter values,
training steps and windows of any length (the scan's length is not part of a step's shape).

Two processes can share one training's compilation (:data:`SHARED`, set by :mod:`tnn_dsl.fit.compile_ahead`): the
training's own process compiles the forward scan while a helper, running its forward scans uncompiled, compiles the
reverse one into torch's on-disk cache; the training waits for it before its first backward pass and then loads the
very program it would have compiled.
"""

from __future__ import annotations

import types
from typing import Any, Callable, Sequence

from .assembly import _PackedVals, _Prep

__all__ = ["SHARED", "AdjointRollout", "SharedCompilation", "Unsupported", "flatten", "forward_key"]


class SharedCompilation:
    """What this process does around the reverse scans it compiles, when another process shares the work
    (:mod:`tnn_dsl.fit.compile_ahead`, :class:`~tnn_dsl.fit.compile_ahead.CompileBeside`). Process-wide, in
    :data:`SHARED`; every field off by default.

    ``before_backward``: called before the first (compiling) call of each reverse scan — the training's process
    waits there while the helper compiles the same graph, the helper says there that it has begun; ``after_backward``:
    called after that call returned (the helper: the program is in the cache, its work is done);
    ``eager_forward``: forward scans run uncompiled (the helper: it needs their states, not their program, which the
    training compiles itself). The arithmetic of the training's process does not depend on any of them: it runs the
    program it would have compiled, compiled or loaded from the cache."""

    __slots__ = ("before_backward", "after_backward", "eager_forward")

    def __init__(self) -> None:
        self.before_backward: Callable[[], None] | None = None
        self.after_backward: Callable[[], None] | None = None
        self.eager_forward = False


SHARED = SharedCompilation()
"""This process's :class:`SharedCompilation` (all off unless a training shares its compilation)."""


class Unsupported(Exception):
    """The prepared values hold something the adjoint rollout does not handle (the step-by-step path runs)."""


def flatten(tree: Any) -> tuple[list, Callable[[Sequence], Any], tuple]:
    """``(tensors, rebuild, key)`` of prepared values (:class:`~tnn_dsl.compiler.assembly._Prep`, dicts, lists,
    tuples; other leaves kept as they are): ``rebuild(new_tensors)`` is the same structure with the tensors
    replaced in order, ``key`` a hashable description of the structure, of every non-tensor leaf and of each
    tensor's shape, dtype and whether it requires a gradient (two calls with equal keys can share compiled code).
    Raises :class:`Unsupported` for the packed parameter table of large networks."""
    import torch

    tensors: list = []
    objects: list = []

    def enc(o):
        if isinstance(o, torch.Tensor):
            tensors.append(o)
            return ("T", tuple(o.shape), str(o.dtype), bool(o.requires_grad))
        if isinstance(o, _Prep):
            return ("P", tuple((s, enc(getattr(o, s))) for s in _Prep.__slots__ if hasattr(o, s)))
        if isinstance(o, _PackedVals):
            raise Unsupported("packed parameter table")
        if type(o) is dict:
            return ("D", tuple((k, enc(v)) for k, v in o.items()))
        if type(o) in (list, tuple):
            return ("L" if type(o) is list else "U", tuple(enc(v) for v in o))
        if o is None or type(o) in (bool, int, float, str):
            return ("V", o)
        if isinstance(o, (dict, list, tuple)):
            raise Unsupported(type(o).__name__)
        objects.append(o)
        return ("O", id(o))

    spec = enc(tree)
    objs = list(objects)

    def rebuild(new: Sequence):
        it = iter(new)
        ob = iter(objs)

        def dec(s):
            kind = s[0]
            if kind == "T":
                return next(it)
            if kind == "P":
                p = _Prep()
                for slot, sub in s[1]:
                    setattr(p, slot, dec(sub))
                return p
            if kind == "D":
                return {k: dec(v) for k, v in s[1]}
            if kind in ("L", "U"):
                items = [dec(v) for v in s[1]]
                return items if kind == "L" else tuple(items)
            if kind == "V":
                return s[1]
            return next(ob)
        return dec(spec)

    return tensors, rebuild, spec


def _flat_context(ctx: dict) -> tuple[tuple, list]:
    """``(keys, arrays)`` of a rollout context (``{"s": {...}, "v": {...}, "u": array}``) in a fixed order."""
    keys = tuple([("s", k) for k in ctx["s"]] + [("v", k) for k in ctx["v"]] + [("u", None)])
    return keys, [ctx["u"] if b is None else ctx[a][b] for a, b in keys]


def _context(keys: tuple, arrays: Sequence) -> dict:
    c: dict = {"s": {}, "v": {}}
    for (a, b), v in zip(keys, arrays):
        if b is None:
            c["u"] = v
        else:
            c[a][b] = v
    return c


def _differentiable(t) -> bool:
    return t.dtype.is_floating_point or t.dtype.is_complex


class AdjointRollout:
    """The compiled forward and adjoint scans of one model's step.

    ``stepper(prep, traced) -> step(T, c)``: the model's integration step over one sample interval at prepared
    values ``prep`` (``traced``: for ``torch.compile``, where many sub-steps become a ``scan``); ``name``: a label
    unique to the model (torch keeps compiled code per code object; one per model keeps models apart);
    ``on_failure(exc)``: called when the compiled backward fails (torch cannot compile here), after which this
    rollout's gradients are computed by running the traced vector-Jacobian product step by step, uncompiled;
    ``options``: inductor's options for both scans (``torch.compile(options=...)``)."""

    def __init__(self, stepper: Callable, name: str, on_failure: Callable[[Exception], None] | None = None,
                 options: dict | None = None):
        self.stepper = stepper
        self.name = name
        self.on_failure = on_failure
        self.options = dict(options or {})
        self.compiled_backward = True
        self._fwd: dict = {}
        self._bwd: dict = {}
        self._bwd_first: set = set()  # the reverse scans not called yet (their first call compiles them)

    # -- the public call ----------------------------------------------------------------------------------
    def __call__(self, prep: Any, T0, ctx: dict):
        """The states after ``T0 (..., n_states)`` K for every sample of ``ctx`` (time-major: samples on axis 0 of
        every array), ``(M, ..., n_states)``; differentiable with respect to the tensors of ``prep``, ``T0`` and
        the context. Raises :class:`Unsupported` for prepared values it cannot flatten."""
        p, rebuild, pkey = flatten(prep)
        ckeys, cvals = _flat_context(ctx)
        key = (pkey, ckeys, tuple((tuple(c.shape[1:]), str(c.dtype), bool(c.requires_grad)) for c in cvals),
               tuple(T0.shape), str(T0.dtype), bool(T0.requires_grad))
        return _AdjointFn.apply(self, key, rebuild, ckeys, len(p), T0, *p,
                                *[c if c.is_contiguous() else c.contiguous() for c in cvals])

    # -- forward -------------------------------------------------------------------------------------------
    def states(self, prep: Any, T0, ctx: dict):
        """The states after ``T0 (B, n_states)`` K for every sample of ``ctx`` (time-major, ``(M, B, ...)``),
        ``(M, B, n_states)``, without gradients: the forward scan a training compiles, so that a model's free
        runs (validation, the burn-in's batched Jacobian) reuse the training's compiled graph instead of
        compiling graphs of their own (:meth:`forward`). Raises :class:`Unsupported` for prepared values it
        cannot flatten."""
        p, rebuild, pkey = flatten(prep)
        ckeys, cvals = _flat_context(ctx)
        return self.forward(pkey, rebuild, ckeys, p, T0, [c if c.is_contiguous() else c.contiguous() for c in cvals])

    def forward(self, pkey, rebuild, ckeys, p, T0, cvals):
        """The states ``(M, ..., n_states)`` K after ``T0`` without autograd: the compiled forward scan (compiled
        on first use). One graph serves every rollout length and every batch of two or more sequences (both
        axes dynamic from the first call), with or without gradients wanted: its key holds the prepared
        values' structure and the arrays' other axes, not ``requires_grad`` (:func:`forward_key`)."""
        import torch
        from torch._higher_order_ops import scan

        if SHARED.eager_forward and cvals:
            return _forward_loop(self.stepper(rebuild(list(p)), False), ckeys, T0, cvals)
        fkey, dynamic = forward_key(pkey, ckeys, cvals, T0)
        fn = self._fwd.get(fkey)
        if fn is None:
            stepper = self.stepper
            scalars = scalar_slots(p)

            def roll(p, T0, cvals):
                step = stepper(rebuild(scalars_back(p, scalars)), True)

                def body(T, cv):
                    Tn = step(T, _context(ckeys, cv))
                    return Tn, Tn.clone()
                return scan(body, T0, list(cvals))[1]
            fn = self._fwd[fkey] = CompiledScan(roll, f"tnn_adjoint_fwd_{self.name}_{len(self._fwd)}", self.options)
        cvals = [c.detach() for c in cvals]
        T0 = T0.detach().contiguous()
        for c in cvals:  # one compiled graph for every rollout length ...
            torch._dynamo.maybe_mark_dynamic(c, 0)
        for d in range(dynamic):  # ... and every batch of two or more
            torch._dynamo.maybe_mark_dynamic(T0, d)
            for c in cvals:
                torch._dynamo.maybe_mark_dynamic(c, 1 + d)
        with torch.no_grad():
            return fn(scalars_as_vectors(p), T0, cvals)

    # -- backward ------------------------------------------------------------------------------------------
    def _vjp_graph(self, rebuild, ckeys, p, T0, cvals, wrt):
        """One step's vector-Jacobian product as a plain graph: ``(p, T, c, a) -> (dp, dT, dc)`` for the
        differentiable prepared tensors and context arrays (``wrt``: their indices)."""
        import torch
        from torch.fx.experimental.proxy_tensor import make_fx

        stepper = self.stepper
        ip, ic = wrt

        def vjp_step(p, T, c, a):
            def f(pd, T, cd):
                pp, cc = list(p), list(c)
                for i, t in zip(ip, pd):
                    pp[i] = t
                for i, t in zip(ic, cd):
                    cc[i] = t
                return stepper(rebuild(pp), False)(T, _context(ckeys, cc))
            _, pull = torch.func.vjp(f, [p[i] for i in ip], T, [c[i] for i in ic])
            dp, dT, dc = pull(a)
            return list(dp), dT, list(dc)

        with torch.no_grad():
            return make_fx(vjp_step)([t.detach() for t in p], T0.detach(), [c[0].detach() for c in cvals],
                                     T0.detach())

    def backward(self, key, rebuild, ckeys, p, T0, S, cvals, G, wanted: Sequence[bool] | None = None):
        """``(dT0, dp, dc)``: the gradients of ``Σ G·S`` with respect to ``T0``, the tensors of ``p`` and the context
        arrays (``(M, ...)``) that autograd asks for (``wanted``: one flag per tensor of ``p`` then of ``cvals``, the
        autograd function's ``needs_input_grad``; default every floating-point one); ``None`` for the rest.

        Only those are differentiated: of a training's prepared tensors most are constants (M2 of the case study:
        5 of 43 need a gradient, and 3 of its 5 context arrays), and a vector-Jacobian product over all of them
        carried a running sum per constant through the reverse scan and wrote a context gradient per sample that
        autograd then dropped (issue 18)."""
        import torch
        from torch._higher_order_ops import scan

        if wanted is None:
            wanted = [True] * (len(p) + len(cvals))
        ip = tuple(i for i, t in enumerate(p) if _differentiable(t) and wanted[i])
        ic = tuple(i for i, c in enumerate(cvals) if _differentiable(c) and wanted[len(p) + i])
        key = (key, ip, ic)
        entry = self._bwd.get(key)
        if entry is None:
            gm = self._vjp_graph(rebuild, ckeys, p, T0, cvals, (ip, ic))
            scalars = scalar_slots(p)

            def rev(p, Sprev, cvals, G):
                p = scalars_back(p, scalars)
                def body(carry, x):
                    a, acc = carry
                    Sp, cv, g = x
                    dp, dT, dc = gm(p, Sp, cv, a + g)
                    return (dT, [s + d for s, d in zip(acc, dp)]), list(dc)
                init = (torch.zeros_like(Sprev[0]), [torch.zeros_like(p[i]) for i in ip])
                return scan(body, init, (Sprev, list(cvals), G), reverse=True)
            entry = self._bwd[key] = (gm, CompiledScan(rev, f"tnn_adjoint_bwd_{self.name}_{len(self._bwd)}",
                                                       self.options), scalars)
            self._bwd_first.add(key)
        gm, fn, scalars = entry
        with torch.no_grad():
            Sprev = torch.cat([T0.detach()[None], S[:-1]], 0)
            args = (scalars_as_vectors(p), Sprev, [c.detach() for c in cvals], G.contiguous())
            for a in (Sprev, *args[2], args[3]):
                torch._dynamo.maybe_mark_dynamic(a, 0)
            out = None
            # one step (a rollout of two samples): the Python loop is one call of the traced step. torch 2.13's
            # compiled reverse scan of length one, on a batch of one, added a context array's gradient (1, 1) to
            # a 0-d parameter's (the test chain's R_b_amb off by 17 %, tests/test_torch_adjoint.py)
            if self.compiled_backward and Sprev.shape[0] > 1:
                first = key in self._bwd_first
                if first and SHARED.before_backward is not None:
                    SHARED.before_backward()
                try:
                    out = fn(*args)
                except Exception as e:  # noqa: BLE001 - compiler infrastructure, not the user's model
                    self.compiled_backward = False
                    if self.on_failure is not None:
                        self.on_failure(e)
                self._bwd_first.discard(key)
                if first and out is not None and SHARED.after_backward is not None:
                    SHARED.after_backward()
            if out is None:
                out = _reverse_loop(gm, scalars_back(args[0], scalars), *args[1:], ip)
            (dT0, dpd), dcs = out
        dp: list = [None] * len(p)
        for i, g in zip(ip, dpd):
            dp[i] = g
        dc: list = [None] * len(cvals)
        for i, g in zip(ic, dcs):
            dc[i] = g
        return dT0, dp, dc


def forward_key(pkey: tuple, ckeys: tuple, cvals: Sequence, T0) -> tuple[tuple, int]:
    """``(key, n_dynamic)`` of a forward scan: the prepared values' structure (:func:`flatten`'s key without the
    tensors' ``requires_grad``), the context's keys, and every array's dtype and shape without the time axis
    (dynamic) and without the batch axes where they are dynamic. The batch axes (``T0``'s leading ones, the
    context's after time) are dynamic when every array holds them in full and none is of size one (torch
    specialises sizes 0 and 1): ``n_dynamic`` of them, else 0 and the key holds the shapes as they are."""
    nb = T0.ndim - 1
    batch = tuple(T0.shape[:nb])
    full = all(tuple(c.shape[1:1 + nb]) == batch for c in cvals)
    n_dynamic = nb if nb and full and min(batch) >= 2 else 0
    key = (_without_grad(pkey), ckeys, tuple((tuple(c.shape[1 + n_dynamic:]), str(c.dtype)) for c in cvals),
           tuple(T0.shape[n_dynamic:]), str(T0.dtype), n_dynamic)
    return key, n_dynamic


def _without_grad(spec):
    """:func:`flatten`'s key with every tensor's ``requires_grad`` left out."""
    if type(spec) is not tuple or not spec:
        return spec
    if spec[0] == "T" and len(spec) == 4:
        return spec[:3]
    return tuple(_without_grad(s) for s in spec)


def scalar_slots(p: Sequence) -> tuple[int, ...]:
    """The positions of the 0-d tensors among the prepared tensors ``p``."""
    return tuple(i for i, t in enumerate(p) if t.ndim == 0)


def scalars_as_vectors(p: Sequence) -> list:
    """``p`` detached and copied, every 0-d tensor as a vector of one (a compiled scan's inputs). torch's dynamo
    gives each 0-d CPU tensor input a symbolic value, which inductor then cannot turn back into a tensor: it
    restarts its analysis with them fixed, tracing the whole graph twice (``TORCH_LOGS=+dynamo``: "Restarting
    analysis due to …_tensorify_python_scalars"). A vector of one is an ordinary input."""
    return [t.detach().clone().reshape(1) if t.ndim == 0 else t.detach().clone() for t in p]


def scalars_back(p: Sequence, slots: tuple[int, ...]) -> list:
    """:func:`scalars_as_vectors` undone inside the graph: the tensors at ``slots`` back to 0-d."""
    return [t.reshape(()) if i in slots else t for i, t in enumerate(p)]


def _forward_loop(step, ckeys: tuple, T0, cvals):
    """The forward scan of :meth:`AdjointRollout.forward` as a Python loop of the untraced step (no compiler, no
    autograd): ``(M, ..., n_states)``. A helper that compiles only the reverse scan (:data:`SHARED`) reaches it
    sooner this way than through the ``scan`` operator run eagerly (2.3 against 3.9 s from the case study's M2
    training start, 2026-12-08)."""
    import torch

    with torch.no_grad():
        T, S = T0.detach(), []
        for k in range(cvals[0].shape[0]):
            T = step(T, _context(ckeys, [c[k] for c in cvals]))
            S.append(T)
        return torch.stack(S, 0)


def _reverse_loop(gm, p, Sprev, cvals, G, ip):
    """The reverse scan of :meth:`AdjointRollout.backward` as a Python loop of the traced step (no compiler)."""
    import torch

    a = torch.zeros_like(Sprev[0])
    acc = [torch.zeros_like(p[i]) for i in ip]
    dcs: list = []
    for k in range(Sprev.shape[0] - 1, -1, -1):
        dp, a, dc = gm(p, Sprev[k], [c[k] for c in cvals], a + G[k])
        acc = [s + d for s, d in zip(acc, dp)]
        dcs.append(dc)
    stacked = [torch.stack([d[j] for d in reversed(dcs)], 0) for j in range(len(dcs[0]))] if dcs else []
    return (a, acc), stacked


class CompiledScan:
    """``torch.compile(fn, fullgraph=True, options=options)`` under a code object of its own called ``name``,
    falling back to inductor's Python wrapper when a compilation with the C++ wrapper (``options`` holding
    ``cpp_wrapper``) fails: torch 2.13's C++ wrapper declares one buffer twice in some reverse scans (a float32
    chain network's: ``conflicting declaration 'auto buf35'``), which the Python wrapper compiles. Compilation
    happens on a call (the first, or one with new shapes), so that is where the fallback is taken: whatever the
    C++ attempt raised, the call is run once more through the Python wrapper, which serves every later call;
    ``fallback`` holds the C++ attempt's error. A failure after that is raised to the caller."""

    def __init__(self, fn, name: str, options: dict | None = None):
        import torch

        self.fn, self.name, self.options = fn, name, dict(options or {})
        self.fallback: str | None = None
        self._compiled = torch.compile(_named(fn, name), fullgraph=True, options=dict(self.options))

    def __call__(self, *args):
        try:
            return self._compiled(*args)
        except Exception as e:  # noqa: BLE001 - compiler infrastructure, not the user's model
            if not self.options.get("cpp_wrapper") or self.fallback is not None:
                raise
            import torch

            self.fallback = f"{type(e).__name__}: {str(e)[:300]}"
            py_options = {k: v for k, v in self.options.items() if not k.startswith("cpp_wrapper")}
            self._compiled = torch.compile(_named(self.fn, self.name + "_py"), fullgraph=True, options=py_options)
            return self._compiled(*args)
        finally:
            _forget_vec_isa_probe(self.options)


def _forget_vec_isa_probe(options: dict) -> None:
    """After a call that may have compiled with ``cpp.vec_isa_ok = False`` (the model's ``TORCH_VECTORIZE`` off):
    forget inductor's per-process list of the machine's vector instruction sets if it was made under that option
    (empty). torch 2.13 caches the list (``cpu_vec_isa.valid_vec_isa_list``) under whatever ``vec_isa_ok`` the
    first compilation of the process had; left empty, a later vectorised graph of the same process (the user's own
    ``torch.compile``) that inductor loads from its on-disk cache is built without its instruction set's flags and
    fails (``'at::vec' has not been declared``). An empty list is cheap to make again; a full one is kept."""
    if options.get("cpp.vec_isa_ok") is not False:
        return
    try:
        from torch._inductor import cpu_vec_isa
    except ImportError:  # pragma: no cover - another torch layout
        return
    probe = getattr(cpu_vec_isa, "valid_vec_isa_list", None)
    if probe is None or not hasattr(probe, "cache_clear") or probe.cache_info().currsize == 0:
        return
    if not probe():
        probe.cache_clear()


def _named(fn, name: str):
    """``fn`` with a code object of its own called ``name`` (torch keeps compiled code per code object)."""
    code = fn.__code__.replace(co_name=name)
    return types.FunctionType(code, fn.__globals__, name, None, fn.__closure__)


def _autograd_function():
    import torch

    class _Fn(torch.autograd.Function):
        @staticmethod
        def forward(ctx, runner, key, rebuild, ckeys, n_p, T0, *flat):
            p, cvals = list(flat[:n_p]), list(flat[n_p:])
            S = runner.forward(key[0], rebuild, ckeys, p, T0, cvals)
            ctx.save_for_backward(T0, S, *flat)
            ctx.runner, ctx.key, ctx.rebuild, ctx.ckeys, ctx.n_p = runner, key, rebuild, ckeys, n_p
            return S

        @staticmethod
        def backward(ctx, G):
            if torch.is_grad_enabled():  # create_graph=True: a second derivative would silently miss the rollout
                raise NotImplementedError(
                    "second derivatives through a compiled torch rollout are not supported (received a backward "
                    "pass with create_graph=True); compile the model with torch_compile=False, or use JAX")
            T0, S, *flat = ctx.saved_tensors
            n_p = ctx.n_p
            dT0, dp, dc = ctx.runner.backward(ctx.key, ctx.rebuild, ctx.ckeys, list(flat[:n_p]), T0, S,
                                              list(flat[n_p:]), G, wanted=ctx.needs_input_grad[6:])
            return (None, None, None, None, None, dT0, *dp, *dc)

    return _Fn


class _LazyFn:
    """The autograd function, defined on first use (torch is imported only by torch models)."""

    _fn = None

    def apply(self, *args):
        if _LazyFn._fn is None:
            _LazyFn._fn = _autograd_function()
        return _LazyFn._fn.apply(*args)


_AdjointFn = _LazyFn()
