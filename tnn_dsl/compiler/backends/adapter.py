"""One adapter over the two autodiff backends, used by everything above the compiler.

The trainer, the sensitivity pass, the model doctor, the Kalman filter and the controller write their
numerics once, against the compiled model (:class:`~tnn_dsl.compiler.protocol.CompiledModel`) and this
adapter; only the adapter knows how JAX and torch spell a transform.

=====================  ============================================  ==========================================
operation              JAX                                           torch
=====================  ============================================  ==========================================
``asarray``/``numpy``  ``jnp.asarray`` / ``np.asarray``              ``torch.from_numpy`` / ``.detach().numpy()``
``jit``                ``jax.jit`` (``fallback``: eager on a          the function itself
                       tracer error; ``lean``: XLA's loop emitters,
                       :data:`LEAN_XLA_OPTIONS`)
``no_grad``            the function itself                           ``torch.no_grad()`` around it
``value_and_grad``     ``jax.jit(jax.value_and_grad)``               ``torch.autograd.grad``
``jvp``                ``jax.jvp``                                   ``torch.func.jvp``
``batched_jvp``        ``jax.vmap`` of ``jax.jvp``                   ``torch.func.vmap`` of ``jvp``, else a loop
``batched``            ``jax.vmap``                                  ``torch.func.vmap``, else a loop
``jacobian``           ``jax.jacfwd``                                ``torch.func.jacfwd``, else jvp columns,
                                                                     else reverse mode
``jacobian_fn``        ``jax.jacfwd``                                reverse mode, one pass for a batch of rows
``scan``               ``jax.lax.scan``                              a Python loop, outputs stacked
=====================  ============================================  ==========================================

Arrays are float64 unless the adapter is made with ``dtype="float32"``; integer and boolean numpy arrays
keep their kind.

``Backend("numpy")`` adapts the numpy reference backend for plain simulations (conversions, ``jit`` and ``no_grad``
as the function itself, the operations above the namespace); it has no autodiff, and its transforms raise
:class:`NotImplementedError`. The trainer's nominal run uses it on torch (``fit/trainer.py``).
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
from typing import Any, Callable, Iterator, Sequence

import numpy as np

__all__ = ["Backend", "backend_of", "drop_compiled_caches", "forward_only", "forward_only_active", "lean_programs",
           "lean_programs_active"]

BACKENDS = ("jax", "torch")
"""The autodiff backends (what a user may choose); ``"numpy"`` is accepted too, for simulations only."""

LEAN_XLA_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
"""XLA options of a program compiled with ``Backend.jit(..., lean=True)`` on a CPU: the loop emitters instead of the
MLIR fusion emitters. Measured on the model doctor (issue 18, BENCHMARKS.md "Diagnosis: time and memory"): the
score test's pointwise derivatives of the case study's extended network compiled in 2.7 instead of 4.6 s, the
resident size growing by 46 instead of 214 MB; the fused kernels run up to 1.5× slower on the case study's M3 rollout
(``bench_rollout.py``), so the training's hot programs keep XLA's default."""


_LEAN_PROGRAMS: contextvars.ContextVar[bool] = contextvars.ContextVar("tnn_dsl_lean_programs", default=False)


@contextlib.contextmanager
def lean_programs() -> Iterator[None]:
    """Within the block (in this thread; a thread started inside it does not inherit it), every JAX program
    :meth:`Backend.jit` and :meth:`Backend.value_and_grad` make, and the compiled model's own programs called from
    Python (its rollout too), are compiled with :data:`LEAN_XLA_OPTIONS`: for a caller that trains a model once and
    throws it away, whose peak memory is XLA compiling the training's programs. The model doctor's linear-or-MLP
    check trains two extensions under it (``doctor/mlp_check.py``): on the case study, one thread, its linear and
    MLP trainings peaked at 641 and 673 MB against 681 and 762 MB before (``python benchmarks/bench_diagnose.py``,
    issue 18, BENCHMARKS.md "the diagnosis' peak"). A program compiled before the block keeps its options."""
    token = _LEAN_PROGRAMS.set(True)
    try:
        yield
    finally:
        _LEAN_PROGRAMS.reset(token)


def lean_programs_active() -> bool:
    """Whether this thread is inside :func:`lean_programs`."""
    return _LEAN_PROGRAMS.get()


_FORWARD_ONLY: contextvars.ContextVar[bool] = contextvars.ContextVar("tnn_dsl_forward_only", default=False)


@contextlib.contextmanager
def forward_only() -> Iterator[None]:
    """Within the block (in this thread), JAX programs traced are known to be run forward only, never
    differentiated in reverse mode: the compiled model may then pick the kernels that are faster forward and slower
    to differentiate (``assembly.NODE_MATRIX_MAX``). :meth:`Backend.no_grad` traces its function inside it; the
    model keys its compiled programs by it (``Model._jitted``)."""
    token = _FORWARD_ONLY.set(True)
    try:
        yield
    finally:
        _FORWARD_ONLY.reset(token)


def forward_only_active() -> bool:
    """Whether this thread is inside :func:`forward_only`."""
    return _FORWARD_ONLY.get()


class Backend:
    """The array conversions, the few operations above the model's namespace, and the autodiff
    transforms of one backend. ``Backend("jax")``, ``Backend("torch", "float32")``."""

    def __init__(self, name: str, dtype: str = "float64") -> None:
        if name not in BACKENDS and name != "numpy":
            raise ValueError(f"no autodiff backend {name!r}; use one of {', '.join(BACKENDS)}")
        if dtype not in ("float64", "float32"):
            raise ValueError(f"dtype must be float64 or float32, got {dtype!r}")
        self.name = self.backend = name
        self.dtype_name = dtype
        if name == "jax":
            import jax
            import jax.numpy as jnp

            from . import jax_ops  # noqa: F401 -- float64, and the persistent cache's thresholds (cache_every_program)

            jax.config.update("jax_enable_x64", True)
            self.jax, self.xp = jax, jnp
            self.dtype = jnp.float64 if dtype == "float64" else jnp.float32
        elif name == "numpy":
            self.xp = np
            self.dtype = np.float64 if dtype == "float64" else np.float32
        else:
            import torch

            self.torch = self.xp = torch
            self.dtype = torch.float64 if dtype == "float64" else torch.float32

    def __repr__(self) -> str:
        return f"Backend({self.name!r}, {self.dtype_name!r})"

    # -- conversions ------------------------------------------------------------------------------

    def asarray(self, x: Any) -> Any:
        """A backend array from a numpy array, a list or a number (floats in the adapter's dtype)."""
        if self.name == "torch" and isinstance(x, self.torch.Tensor):
            return x.to(self.dtype) if x.is_floating_point() else x
        x = np.asarray(x)
        if self.name == "numpy":
            return x.astype(self.dtype) if x.dtype.kind == "f" else x
        if self.name == "jax":
            return self.xp.asarray(x, dtype=self.dtype) if x.dtype.kind == "f" else self.xp.asarray(x)
        t = self.torch.from_numpy(np.asarray(x, order="C"))  # (ascontiguousarray would make 0-d arrays 1-d)
        return t.to(self.dtype) if x.dtype.kind == "f" else t

    def tree(self, d: Any) -> Any:
        """:meth:`asarray` over nested dicts, lists and tuples."""
        if isinstance(d, dict):
            return {k: self.tree(v) for k, v in d.items()}
        if isinstance(d, (list, tuple)):
            return [self.tree(v) for v in d]
        return self.asarray(d)

    @staticmethod
    def numpy(x: Any) -> np.ndarray:
        """A float64 numpy array from a backend array (detached from any graph)."""
        if hasattr(x, "detach"):
            x = x.detach().cpu()
        return np.asarray(x, dtype=np.float64)

    def zeros(self, shape: Sequence[int] | int) -> Any:
        return self.xp.zeros(tuple(np.atleast_1d(shape).tolist()) if not isinstance(shape, int) else (shape,),
                             dtype=self.dtype)

    # -- operations not in the model's namespace ----------------------------------------------------

    def exp(self, x: Any) -> Any:
        return self.xp.exp(x)

    def sigmoid(self, x: Any) -> Any:
        if self.name == "numpy":
            return 0.5 + 0.5 * np.tanh(0.5 * x)
        return self.jax.nn.sigmoid(x) if self.name == "jax" else self.torch.sigmoid(x)

    def where(self, c: Any, a: Any, b: Any) -> Any:
        return self.xp.where(c, a, b)

    def abs(self, x: Any) -> Any:
        return self.xp.abs(x)

    def sum(self, x: Any) -> Any:
        return self.xp.sum(x)

    def amax(self, x: Any, axes: int | tuple[int, ...]) -> Any:
        return self.torch.amax(x, dim=axes) if self.name == "torch" else self.xp.max(x, axis=axes)

    def clip_min(self, x: Any, lo: float) -> Any:
        return self.torch.clamp(x, min=lo) if self.name == "torch" else self.xp.clip(x, lo, None)

    def solve(self, a: Any, b: Any) -> Any:
        return self.xp.linalg.solve(a, b)

    # -- transforms ---------------------------------------------------------------------------------

    def _autodiff(self) -> None:
        if self.name == "numpy":
            raise NotImplementedError("the numpy reference backend has no autodiff (derivatives need jax or torch)")

    def jit(self, fn: Callable, *, fallback: bool = False, lean: bool | None = None) -> Callable:
        """``jax.jit(fn)``; torch runs ``fn`` as it is. ``fallback=True``: if JAX cannot trace ``fn`` (a
        Python branch on a traced value), run it eagerly from then on. ``lean=True``: on a CPU, compiled with
        :data:`LEAN_XLA_OPTIONS` (about half the compilation time and a quarter of its memory, kernels up to 1.5×
        slower): for programs called a few hundred times or less, whose compilation outweighs their runs.
        ``lean=None`` (the default): lean inside :func:`lean_programs`; pass ``False`` for a program that may be
        traced inside another one (JAX takes compiler options only at the top level)."""
        if self.name != "jax":
            return fn
        lean = _LEAN_PROGRAMS.get() if lean is None else lean
        jitted = self.jax.jit(fn, compiler_options=self.lean_options() if lean else None)
        if not fallback:
            return jitted
        errors = (self.jax.errors.ConcretizationTypeError, self.jax.errors.TracerBoolConversionError,
                  self.jax.errors.TracerArrayConversionError, self.jax.errors.TracerIntegerConversionError)
        state = {"ok": True}

        def call(*args):
            if state["ok"]:
                try:
                    return jitted(*args)
                except errors:
                    state["ok"] = False
            return fn(*args)

        return call

    def lean_options(self) -> dict[str, Any] | None:
        """:data:`LEAN_XLA_OPTIONS` where JAX compiles for a CPU and the installed XLA knows them, else None (XLA's
        defaults)."""
        if self.name != "jax" or self.jax.default_backend() != "cpu" or not _lean_options_accepted():
            return None
        return dict(LEAN_XLA_OPTIONS)

    def no_grad(self, fn: Callable) -> Callable:
        """``fn`` without building an autodiff graph (torch); JAX builds none anyway, and traces ``fn`` inside
        :func:`forward_only` (``fn`` is never differentiated in reverse mode: a compiled model picks its forward
        kernels)."""
        if self.name == "jax":
            @functools.wraps(fn)  # XLA's logs and profiles name the program after ``fn``
            def traced(*args, **kw):
                with forward_only():
                    return fn(*args, **kw)

            return traced
        if self.name != "torch":
            return fn
        torch = self.torch

        def call(*args, **kw):
            with torch.no_grad():
                return fn(*args, **kw)

        return call

    def value_and_grad(self, f: Callable) -> Callable[..., tuple[float, np.ndarray]]:
        """``g(z_numpy, *args) -> (float, gradient numpy)`` for a scalar ``f(z, *args)``, differentiated in
        its first argument (``args`` are passed through: backend arrays or plain data)."""
        self._autodiff()
        if self.name == "jax":
            vg = self.jax.jit(self.jax.value_and_grad(f),
                              compiler_options=self.lean_options() if _LEAN_PROGRAMS.get() else None)

            def g(z, *args):
                v, gr = vg(self.xp.asarray(z, dtype=self.dtype), *args)
                return float(v), np.asarray(gr, dtype=np.float64)

            return g
        torch = self.torch

        def g(z, *args):
            zt = torch.tensor(np.asarray(z), dtype=self.dtype, requires_grad=True)
            v = f(zt, *args)
            (gr,) = torch.autograd.grad(v, zt)
            return float(v.detach()), gr.detach().cpu().numpy().astype(np.float64)

        return g

    def jvp(self, f: Callable, primals: tuple, tangents: tuple) -> tuple[Any, Any]:
        """``(f(*primals), ∂f·tangents)`` in forward mode."""
        self._autodiff()
        if self.name == "jax":
            return self.jax.jvp(f, tuple(primals), tuple(tangents))
        return self.torch.func.jvp(f, tuple(primals), tuple(tangents))

    def batched_jvp(self, f: Callable, primals: tuple, tangents: tuple) -> Any:
        """The forward derivatives of ``f`` at ``primals`` along a batch of directions: every array of
        ``tangents`` has a leading axis ``m`` (one direction each) → outputs with that leading axis (a
        tuple output gives a tuple). torch falls back to one ``jvp`` per direction where ``f`` cannot be
        vmapped."""
        self._autodiff()
        primals = tuple(primals)

        def one(*t):
            return self.jvp(f, primals, t)[1]

        if self.name == "jax":
            return self.jax.vmap(one)(*tangents)
        torch = self.torch
        try:
            return torch.func.vmap(one)(*tangents)
        except Exception:  # noqa: BLE001 - an op without a batching rule: one direction at a time
            outs = [one(*t) for t in zip(*tangents)]
            if isinstance(outs[0], tuple):
                return tuple(torch.stack([o[i] for o in outs]) for i in range(len(outs[0])))
            return torch.stack(outs)

    def batched(self, f: Callable, chunk: int | None = None) -> Callable:
        """``f`` over a leading batch axis of every argument (outputs stacked likewise). torch falls back to one
        call per batch element where ``f`` cannot be vmapped. ``chunk``: at most that many elements at a time
        (JAX: ``lax.map`` with ``batch_size``, one program; torch: one vectorised call per slice), for a long
        rollout whose intermediates grow with the batch (the doctor's forward-difference Jacobians). An ``f`` that
        runs a model's compiled torch rollout would run it eager under ``vmap``: many parameter sets of such a
        model go through ``Model.rollouts_of``."""
        if self.name == "jax":
            if chunk is None:
                return self.jax.vmap(f)
            return lambda *args: self.jax.lax.map(lambda a: f(*a), args, batch_size=int(chunk))
        if self.name == "numpy":
            return lambda *args: np.stack([f(*a) for a in zip(*args)])
        torch = self.torch

        def whole(*args):
            try:
                return torch.func.vmap(f)(*args)
            except Exception:  # noqa: BLE001 - an op without a batching rule: one element at a time
                return torch.stack([f(*a) for a in zip(*args)])

        if chunk is None:
            return whole

        def sliced(*args):
            n = int(args[0].shape[0])
            return torch.cat([whole(*(a[s: s + chunk] for a in args)) for s in range(0, n, int(chunk))], 0)

        return sliced

    def jacobian(self, fn: Callable, x: Any) -> np.ndarray:
        """Forward-mode Jacobian of ``fn`` (backend vector → backend array) at ``x`` (numpy vector): numpy
        array of shape ``fn(x).shape + (len(x),)``. torch: ``jacfwd``, else one ``jvp`` per column, else
        reverse mode (for ops without forward rules)."""
        self._autodiff()
        xb = self.asarray(np.asarray(x, dtype=float))
        if self.name == "jax":
            # eager, ``fn``'s own compiled programs are compiled again, differentiated, with their own options;
            # inside :func:`lean_programs` the whole derivative is one lean program (compiled at each call)
            jac = self.jit(self.jax.jacfwd(fn)) if _LEAN_PROGRAMS.get() else self.jax.jacfwd(fn)
            return np.asarray(jac(xb), dtype=float)
        torch = self.torch
        try:
            return self.numpy(torch.func.jacfwd(fn)(xb))
        except Exception:  # noqa: BLE001 - vmap-incompatible op in the model: one jvp per column
            pass
        try:
            cols = []
            for k in range(len(x)):
                e = torch.zeros_like(xb)
                e[k] = 1
                cols.append(self.numpy(torch.func.jvp(fn, (xb,), (e,))[1]))
            return np.stack(cols, axis=-1)
        except Exception:  # noqa: BLE001 - no forward-mode rule: reverse mode
            return self.numpy(torch.autograd.functional.jacobian(fn, xb))

    def jacobian_program(self, fn: Callable) -> Callable[[np.ndarray], np.ndarray]:
        """``J(x)``: the forward-mode Jacobian of ``fn`` (backend vector → backend array) at a numpy vector ``x``,
        as a numpy array of shape ``fn(x).shape + (len(x),)``, for many calls at different ``x``: JAX traces and
        compiles ``jacfwd(fn)`` once (:meth:`jacobian` traces it at each call); torch as :meth:`jacobian`."""
        self._autodiff()
        if self.name != "jax":
            return lambda x: self.jacobian(fn, x)
        jac = self.jit(self.jax.jacfwd(fn))
        return lambda x: np.asarray(jac(self.asarray(np.asarray(x, dtype=float))), dtype=float)

    def jacobian_fn(self, f: Callable, n_out: int, *, batched: bool = True) -> Callable:
        """``J(x, *rest) = ∂f(x, *rest)/∂x (n_out, n)`` as a backend function (used inside filters).

        JAX: ``jax.jacfwd``. torch: reverse mode — ``batched``: one forward pass over ``n_out`` copies of
        ``x`` and one backward pass (row ``i`` of the gradient of ``Σ_i f(X_i)_i``; ``f`` must accept a
        leading batch axis), else one backward pass per output. (``torch.func.jacfwd`` gives the same
        numbers, but its per-operation overhead makes a 5000-step filter about 20× slower on small
        networks.)"""
        self._autodiff()
        if self.name == "jax":
            return self.jax.jacfwd(f)
        torch = self.torch

        def jac(x, *rest):
            with torch.enable_grad():
                if batched:
                    X = x.detach().unsqueeze(0).expand(n_out, x.shape[0]).clone().requires_grad_(True)
                    Y = f(X, *rest)
                    (g,) = torch.autograd.grad(torch.diagonal(Y).sum(), X)
                    return g
                xr = x.detach().clone().requires_grad_(True)
                y = f(xr, *rest)
                rows = [torch.autograd.grad(y[i], xr, retain_graph=i < n_out - 1)[0] for i in range(n_out)]
                return torch.stack(rows)

        return jac

    def scan(self, body: Callable, carry: Any, xs: tuple) -> tuple[Any, Any]:
        """``jax.lax.scan(body, carry, xs)``: ``body(carry, x_k) -> (carry, y_k)`` over the leading axis of
        every array in ``xs``; returns ``(carry, ys)`` with the ``y_k`` stacked (a tuple of arrays for a
        tuple ``y_k``). torch and numpy: a Python loop."""
        if self.name == "jax":
            return self.jax.lax.scan(body, carry, xs)
        stack = self.torch.stack if self.name == "torch" else np.stack
        outs = []
        for k in range(int(xs[0].shape[0])):
            carry, y = body(carry, tuple(a[k] for a in xs))
            outs.append(y)
        if outs and isinstance(outs[0], tuple):
            return carry, tuple(stack([o[i] for o in outs]) for i in range(len(outs[0])))
        return carry, stack(outs)


@functools.cache
def _lean_options_accepted() -> bool:
    """Whether the installed XLA compiles a program with :data:`LEAN_XLA_OPTIONS` (an option it does not know is an
    error at compile time: a later jaxlib may drop it); probed once per process on a one-element program."""
    import jax
    import jax.numpy as jnp

    try:
        jax.jit(lambda x: x + 1.0, compiler_options=dict(LEAN_XLA_OPTIONS))(jnp.zeros(1)).block_until_ready()
    except Exception:  # noqa: BLE001 -- jaxlib's error types vary by version; any failure means: keep the defaults
        return False
    return True


def drop_compiled_caches(backend: str) -> bool:
    """Empty every cache of compiled programs the process holds for ``backend`` (``"jax"``: ``jax.clear_caches()``;
    others: nothing). Returns whether anything was done. Every jitted function in the process, the caller's own
    included, compiles again on its next call: only a job that owns its process (the ``tnnc`` command line) should
    do this. JAX keeps programs a job has let go in its caches (tens of MB on the model doctor; issue 18)."""
    if backend != "jax":
        return False
    import jax

    jax.clear_caches()
    return True


def backend_of(model: Any) -> Backend:
    """The adapter for a compiled model's backend and dtype."""
    return Backend(model.backend, getattr(model, "dtype", "float64"))
