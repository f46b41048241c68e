"""Compile a :class:`~tnn_dsl.ir.network.Network` into a :class:`Model` on JAX, PyTorch (or numpy).

The model is the thesis's state-space form (eq. 2.4/2.10, written per node)

    C_i dT_i/dt = Σ_links g·(T_j − T_i) + Σ_radiation σεAF(T_j⁴ − T_i⁴) + Q_peltier + Q_fluid + Q_sources
                  + Q_learned,          τ_s dT_s/dt = T_node − T_s   (lagged sensors)

with parameters from the one flat table (``Network.params``) and learned functions (``_learned``).

How the per-step work is kept small (the design, in one place):

* Parameters are classified once: **static** (a constant, or derived only from constants) or **dynamic**
  (depends on an input, a node temperature or a learned function of them). Static values are computed
  once per call (``prepare``), dynamic ones every right-hand-side evaluation, in a topological order.
* All links with static conductance (and fluids with static ``ṁ cp (1 − a)`` and no learned flow) are
  pre-multiplied into one conductance matrix, so their whole contribution is one matmul ``T @ M``;
  constant boundaries and constant heat loads fold into a constant vector. Links and radiation with
  dynamic coefficients use gather/scatter matrices (two matmuls); point flows (Peltier sides, fluids,
  sources, learned heat loads) are stacked and scattered by one matmul.
* Learned-function inputs are gathered and normalised by matmuls with matrices prepared once.

Parameter-table keys: every constant parameter (``"C_ph"``), every learned array (``"f1.W0"``), and
optionally ``"scale:<param>"`` / ``"scale:<flow>"`` multipliers (see :attr:`Model.scale_keys`).
Flow names: ``"<link>.Q"`` (into the link's ``a``), ``"<radiation>.Q"`` (into ``a``), ``"<pe>.Q_hot"``,
``"<pe>.Q_cold"``, ``"<pe>.Q_internal"`` (conducted from the hot into the cold side), ``"<fluid>.Q"``
(into its node), ``"<source>.Q"``, ``"Q[<node>]"`` (a learned heat load).
"""

from __future__ import annotations

import contextlib
import math
import os
import platform
import types
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import numpy as np

from ..core import Diagnostic, TnnError
from ..core.collector import collector_paused
from ..ir import POSITIVE_ROLES, Network
from . import learned as _learned
from .assembly import PACKED_KEY, SPARSE_MIN_STATES
from .backends import get_xp
from .core import _Core
from .integrators import INTEGRATORS, StepSizeWarning, check_step, euler, expeuler, rk4
from .krylov import KRYLOV_MAXITER, KRYLOV_TOL, torch_solve
from .plan import NOMINAL_T, T_SCALE, _Plan

LEAN_PROGRAMS = ("steady", "rhs", "outputs", "heat_flows")
"""The model's own JAX programs compiled with XLA's lean options when called from Python (``Backend.jit(...,
lean=True)``): point evaluations and the steady state's Newton iteration, called a few times each, whose compilation
outweighs their runs. The steady state's first call (trace, lowering, compilation) on the case study's M3 took
1.35 instead of 1.58 s, on M1 0.96 instead of 1.34 s (medians of three, alternating, 2026-11-28), the same
temperatures to the bit and the later calls within noise (0.7–1.5 ms, mostly Python). The rollout keeps the default:
the program a caller loops over (model-predictive control, a user's own fit), whose fused kernels run up to 1.5×
faster."""


@dataclass(frozen=True)
class ParamSpec:
    """One array of the model's parameter table.

    ``kind``: ``"physical"`` (a constant parameter, shape ``()``, SI), ``"weights"`` (a learned function's
    trainable array) or ``"stat"`` (a learned function's normalisation). ``trainable``: ``free``
    constants that are not learned targets, and weights of non-frozen functions. ``positive``: the
    parameter's role must stay positive (R, G, C, τ). ``lower``/``upper``: SI bounds of a ``free``
    parameter. ``role``: the parameter's role (``"generic"`` for learned arrays)."""

    name: str
    shape: tuple[int, ...]
    kind: str
    trainable: bool
    positive: bool
    lower: float | None
    upper: float | None
    role: str


# ---------------------------------------------------------------------------------------------
# The model
# ---------------------------------------------------------------------------------------------


TORCH_GRAD_CHUNK = 1
"""Sample intervals (divided by the sub-steps) unrolled in one compiled graph by a torch rollout with gradients on
the step-by-step path (``TORCH_ADJOINT = False``, or the packed parameters of a large network;
:meth:`Model._compiled_torch_chunks`); 1 compiles each step apart (:meth:`Model._compiled_torch_step`). Measured
on the case study M3, RK4 (``python benchmarks/bench_rollout.py --quick --only jax,torchc --torch-grad-chunk K``,
2026-11-26, one run per K, batch of 16 windows × 250 steps): forward+gradient 29.4 / 23.1 / 21.6 / 19.4 µs per
window-step for K = 1 / 2 / 4 / 8 (JAX 3.1–4.1), single sequence 364 / 270 / 265 / 204 µs per step, but the
gradient graph's compilation took 17–24 s (K = 2), 28–46 s (K = 4) and 72–108 s (K = 8). At most 1.5× faster for
minutes of compilation per shape, and still 5× JAX: not the default."""

TORCH_ADJOINT = True
"""A torch rollout with gradients and ``torch_compile=True`` runs as a compiled forward ``scan`` and a compiled
adjoint ``scan`` (:meth:`Model._torch_adjoint_rollout`, :mod:`tnn_dsl.compiler.torch_adjoint`) instead of one
compiled call and one autograd node per step. ``False``: the step-by-step path (:data:`TORCH_GRAD_CHUNK`)."""

TORCH_CHUNK = 1
"""Samples per iteration of the compiled torch rollout's ``scan`` on a single sequence without gradient
(:meth:`Model._compiled_torch_rollout`). With inductor's Python wrapper (:data:`TORCH_CPP_WRAPPER` off) 4 paid:
case study M3, RK4, 2000 steps (2026-11-26): 13.7 µs/step with 4, 20.7 with 1, 13.6 with 8, compile time growing
with it (7 s, 18 s, 36 s). With the C++ wrapper (2026-11-27, Intel Xeon, 5000 steps): 8.8 µs/step with 1, 8.1
with 4, 8.1 with 8, after 8.9 s, 18.7 s and 38.9 s of compilation (inductor's cache warm): 1. ``python
benchmarks/bench_rollout.py --only jax,torchc --torch-chunk K`` measures it with the model's own code."""

TORCH_CPP_WRAPPER = True
"""torch's compiled scans (the forward one of :meth:`Model._compiled_torch_rollout`, and the forward and adjoint
ones of :mod:`.torch_adjoint`) are built with inductor's C++ wrapper (:func:`inductor_options`): the loop over
the samples, the body's buffer allocations (one per intermediate result of the step, ~90 per iteration of 4 steps
on M3) and its kernel calls run in C++ instead of a Python function per iteration; wrapper and kernels are built
apart (``cpp_wrapper_build_separate``: as one translation unit M2's reverse scan took 31 s to build). Case study
M3, RK4, single sequence of 5000 steps, each compiled cold (an empty inductor cache; 2026-11-27, Intel Xeon):
8.4 against 14.8 µs/step (JAX 1.35–1.49), compiled in 15.3 against 23.9 s. Training: BENCHMARKS.md
"Training time" (``python benchmarks/bench_train.py``, and ``python benchmarks/bench_rollout.py --only
jax,torchc --torch-python-wrapper --torch-chunk 4`` for the Python wrapper's rollouts). ``False``: inductor's
Python wrapper (with :data:`TORCH_CHUNK` = 4 samples per iteration then paying)."""


TORCH_VECTORIZE = False
"""Whether inductor may generate SIMD (``at::vec``) kernels for the compiled scans. Off (``cpp.vec_isa_ok = False``
for these graphs only): their tensors are small (a handful of states, 24–256 windows), and writing each kernel
twice, scalar and vectorised, was most of inductor's code generation. Cold compiles, Intel Xeon, 2026-11-27
(BENCHMARKS.md, "Rollout cost: reading and proposals"): M2's five graphs 36.1 → 23.0 s, M2 within 10 % of its
final MAE after 53 → 39 s, M3 169 → 131 s (``python benchmarks/bench_train.py``); batched forward + gradient 2.75
→ 2.84 µs per window-step, batched forward 0.79 → 0.96, single sequence 9.6 → 9.2 µs/step (``python
benchmarks/bench_rollout.py --only jax,torchc``, one after the other). :class:`~.torch_adjoint.CompiledScan` keeps
the option from leaking into the process's other graphs. ``True``: SIMD kernels, :data:`TORCH_SIMD_BITS` wide, for
every compiled scan; ``False``: only for the rollouts with gradients that repay them (an MLP's network, large
batches: :data:`TORCH_SIMD_MIN_WINDOW_STEPS`). The environment variable ``TNN_TORCH_SIMD`` (``1``/``0``: everywhere,
nowhere) overrides both (:func:`_torch_vectorize`).

Since the small products run batch-last (:func:`~.backends.torch_ops.fused_matmul`, 2026-12-03) the SIMD kernels
run along the windows and ``True`` is the faster runtime, but not the faster training from a cold start: case study
M3, 256 windows × 390 samples, forward + gradient 6.63 against 10.3 µs per window-step (JAX 4.03: 1.65× against
2.56×), after 96 against 31 s of compiling the batch's two scans (``python benchmarks/bench_rollout.py --only
jax,torchc,torchv``, 02:50–02:54 UTC); training to within 10 % of the final validation MAE, cold inductor cache
(``python benchmarks/bench_train.py --only m2 m3 --backends torch-compiled [--torch-vectorize]``, 02:55–03:12 UTC):
M2 106 against 62 s, M3 253 against 230 s, of it compiling 75 against 35 and 101 against 37 s (M3 less its
compilation 153 against 193 s). Worth turning on for long trainings, fleets of one template, or where inductor's
on-disk cache already holds the network's scans (BENCHMARKS.md, "SIMD kernels along the windows")."""


TORCH_SIMD_MIN_BATCH = 16
"""With :data:`TORCH_VECTORIZE` off and ``TNN_TORCH_SIMD`` unset, a rollout with gradients of a network holding an
MLP with a smooth activation, of at least this many sequences at once (a training's windows, several units fitted
together) and at least :data:`TORCH_SIMD_MIN_WINDOW_STEPS` samples in all, compiles its two scans with SIMD
kernels; other rollouts stay scalar. The SIMD kernels run along the windows (four float64 values per operation at
:data:`TORCH_SIMD_BITS`), so fewer windows leave the vectors mostly empty."""

TORCH_SIMD_MIN_WINDOW_STEPS = 65_536
"""The samples of a rollout with gradients, all its sequences together, from which its scans get SIMD kernels
(:data:`TORCH_SIMD_MIN_BATCH`; ``None``: never by size). What SIMD kernels save grows with the samples a call
integrates, what they cost to compile does not; and they save where the step evaluates an MLP's sigmoid, tanh,
softplus or SiLU, which the scalar kernels compute one value at a time through the C library. Measured on the AMD
host, 2026-12-07:

- forward + gradient per window-step, case study M3, windows of 390 samples, scalar against SIMD, each pair in one
  process (``python benchmarks/bench_rollout.py --only jax,torchc,torchv --batch B --steps B*390 --no-write``,
  01:21–01:28 UTC): 24 windows 7.41 against 6.44 µs (9 ms a call), 64 windows 5.56 against 4.52 (26 ms), 256
  windows 5.23 against 3.67 (156 ms a call; JAX 2.06: 2.54× against 1.78×), for about 30 s more compiling;
- trainings on a 24 h record (144 windows of 600 samples, 86 400 a call), cold inductor cache, ``python
  benchmarks/bench_train.py --only mN --backends torch-compiled --train-hours 24 --no-write`` with SIMD kernels
  and then under ``TNN_TORCH_SIMD=0`` (01:40–02:06 UTC): M3 (sigmoid MLP) within 10 % of its final MAE after 373
  against 459 s, 455 against 580 s in all, compiling 59.1 against 26.5 s; M2 (no MLP) 118 against 93 s, compiling
  43.2 against 20.2 s, the rest 74 against 73 s: no gain to repay the compiling.

The case study's own trainings (24 windows of 600 samples, 14 400 in all) stay scalar."""


TORCH_SIMD_BITS = 256
"""The vector width in bits of the compiled scans' SIMD kernels where :data:`TORCH_VECTORIZE` is on (x86-64 only;
elsewhere inductor's choice): AVX2's. On an AVX-512 host inductor's own choice processes 16 float64 values per
vector operation (two registers); over the batch axis (:func:`~.backends.torch_ops.fused_matmul`) the loops of 24–256
windows then end in long masked tails. Case study M3, 256 windows × 390 samples, forward + gradient, one process
(``python benchmarks/profile_torch_adjoint_split.py --vectorize``, then with ``--inductor-option cpp.simdlen=256``,
one after the other, 2026-12-03 02:01–02:06 UTC, Intel Xeon with AVX-512): the forward and the backward 6.7–7.4 µs
per window-step with 256 bits against 7.6–8.9 with inductor's 512."""

TORCH_PARAM_BATCH = 16
"""Parameter sets per call of the compiled, vmapped step's scan of :meth:`Model.rollouts_of` (torch 2.13 compiles it
for one batch size; more sets run in chunks, fewer are padded). ``python benchmarks/profile_param_batch.py --sizes 8
16`` (case study M1, 14 401 samples; 2026-12-03 17:06 UTC, the Intel host in a slow hour): one compiled rollout 173
ms; 27.0 ms a set in chunks of 8 (6.4×), 16.9 ms in chunks of 16 (10.3×), each graph compiled in 11–14 s. The
doctor's Jacobians take 13–17 sets (forward differences) or 25–33 (central): 16 runs them in one or two calls."""


TORCH_CACHE_SCANS = True
"""Let torch's compiled-graph caches (inductor's FX graph cache and AOT autograd's, in memory and on disk under
``TORCHINDUCTOR_CACHE_DIR``) keep the compiled scans. torch 2.13 bypasses both for any graph holding a higher-order
operator unless it is marked cacheable (``unsafe_marked_cacheable_functions``): every process compiled every scan
afresh, however often the same network had been compiled before. For ``scan`` the mark is safe: the body is a
submodule of the graph, and the cache key holds its code, its constants' values and the inputs' shapes and dtypes
(``tests/test_torch_compile_cache.py``: a body's constant or captured float changed between two processes is a
miss, a tensor input's value is not part of the key, and the reused program computes the new values). Measured
(``python benchmarks/profile_torch_training.py m2 --epochs 2`` twice with one ``TORCHINDUCTOR_CACHE_DIR``,
2026-12-02, Intel Xeon): the second process compiled M2's forward and adjoint scans in 3.4 and 1.3 s against
6.5 and 5.8 s (dynamo still traces; inductor and the C++ compiler are skipped). ``False``: no caching."""


def _torch_vectorize(batch: int | None = None, samples: int | None = None, smooth_mlp: bool = False) -> bool:
    """Whether a compiled scan gets SIMD kernels: the environment variable ``TNN_TORCH_SIMD`` (``1``: always,
    ``0``: never) where set, else :data:`TORCH_VECTORIZE`, else whether a rollout of ``batch`` sequences of
    ``samples`` samples each of a network with an MLP of a smooth activation (``smooth_mlp``) reaches
    :data:`TORCH_SIMD_MIN_BATCH` and :data:`TORCH_SIMD_MIN_WINDOW_STEPS` (``None`` for a scan compiled for no
    particular size: scalar). Read when a scan is looked up or compiled, so a process (``tnnc train --backend torch
    --torch-compile`` under ``TNN_TORCH_SIMD=1``) can turn them on without code."""
    env = os.environ.get("TNN_TORCH_SIMD", "").strip()
    if env not in ("", "0", "1"):
        raise TnnError([Diagnostic(f"TNN_TORCH_SIMD must be 0 or 1, got {env!r}",
                                   hint="unset it for the default (SIMD kernels for the trainings of networks with "
                                        f"an MLP on at least {TORCH_SIMD_MIN_BATCH} windows and "
                                        f"{TORCH_SIMD_MIN_WINDOW_STEPS} samples a step), 1 for SIMD kernels "
                                        "everywhere, 0 for none")])
    if env:
        return env == "1"
    if TORCH_VECTORIZE:
        return True
    if (not smooth_mlp or batch is None or samples is None or TORCH_SIMD_MIN_BATCH is None
            or TORCH_SIMD_MIN_WINDOW_STEPS is None):
        return False
    return batch >= TORCH_SIMD_MIN_BATCH and batch * samples >= TORCH_SIMD_MIN_WINDOW_STEPS


def inductor_options(simd: bool | None = None) -> dict:
    """``torch.compile(options=...)`` of the compiled scans (:data:`TORCH_CPP_WRAPPER`, :data:`TORCH_CACHE_SCANS`);
    SIMD kernels where ``simd`` (``None``: :func:`_torch_vectorize` for no particular batch)."""
    opts: dict = {"cpp_wrapper": True, "cpp_wrapper_build_separate": True} if TORCH_CPP_WRAPPER else {}
    if TORCH_CACHE_SCANS:
        import torch

        opts["unsafe_marked_cacheable_functions"] = {"torch.ops.higher_order.scan": torch.__version__}
    if not (_torch_vectorize() if simd is None else simd):
        opts["cpp.vec_isa_ok"] = False  # part of inductor's cache key; see torch_adjoint.CompiledScan for its probe
    elif platform.machine().lower() in ("x86_64", "amd64"):
        opts["cpp.simdlen"] = TORCH_SIMD_BITS
    return opts


def _needs_grad(params, T0, inputs) -> bool:
    """Whether a torch rollout builds an autograd graph: gradients are enabled and a parameter, ``T0`` or an
    input requires one (a rollout outside ``torch.no_grad()`` with nothing to differentiate takes the
    forward path)."""
    import torch

    if not torch.is_grad_enabled():
        return False
    return any(getattr(v, "requires_grad", False) for v in (*params.values(), T0, inputs))


def _functorch_active() -> bool:
    """Whether a ``torch.func`` transform (``jvp``, ``vmap``, ``jacfwd``) is tracing the current call: a graph
    compiled by ``torch.compile`` cannot be called from inside one, so such rollouts run eager (the burn-in fit
    of an initial state takes forward-mode derivatives of a short rollout)."""
    import torch

    return bool(torch._C._are_functorch_transforms_active())


def _eager_steps(backend: str, grad: bool) -> contextlib.AbstractContextManager:
    """Around the eager step-by-step loop of a rollout: ``torch.inference_mode()`` where torch differentiates
    nothing (no gradient recorded, no ``torch.func`` transform tracing), else nothing. Each of a step's few dozen
    small operations then skips autograd's bookkeeping (version counters, view tracking): TCLab's eager step 111–114
    → 92–96 µs, M3's 613–620 → 483–511 µs (issue 18, BENCHMARKS.md "torch's eager steps without autograd's
    bookkeeping"). Only the loop's own temporaries and states are made there, never a cached array; the states are
    stacked outside it into an ordinary tensor, so nothing the rollout returns is an inference tensor."""
    if backend != "torch" or grad or _functorch_active():
        return contextlib.nullcontext()
    import torch

    return torch.inference_mode()


def _time_major(ctx: dict) -> dict:
    """A rollout context (:meth:`_Core.rhs_u`: time on the last axis of ``s`` leaves, next to last of ``v`` and
    ``u``) with time on axis 0 of every array (torch's ``scan``)."""
    import torch

    return {"s": {k: torch.movedim(v, -1, 0) for k, v in ctx["s"].items()},
            "v": {k: torch.movedim(v, -2, 0) for k, v in ctx["v"].items()}, "u": torch.movedim(ctx["u"], -2, 0)}


class SampleSteps(NamedTuple):
    """:meth:`Model.sample_steps`: one record's model prepared for stepping it one sample at a time.
    ``step(T (..., n_states) K, k) -> T`` K after sample ``k``'s interval (its inputs held);
    ``outputs(T, u)`` K and ``rhs(T, u)`` K/s with the parameters prepared once; ``step_all(T (N, n_states))``:
    every sample's step at once, row ``k`` from ``T[k]`` over sample ``k``'s interval."""

    step: Callable[[Any, Any], Any]
    outputs: Callable[[Any, Any], Any]
    rhs: Callable[[Any, Any], Any]
    step_all: Callable[[Any], Any]


class TorchCompileWarning(UserWarning):
    """``torch.compile`` was asked for but failed; the torch model runs eager."""


JACOBIAN_REL_STEP = 1e-4
"""Central differences of the right-hand side (:func:`_difference_jacobian`): each temperature is moved by
``JACOBIAN_REL_STEP · max(1, |T|)`` (0.03 K at room temperature); the quotient is exact to round-off for a network
linear in the temperatures and within ``O(step²)`` otherwise (radiation about 1e-8 relative; the case study's M5, two
MLPs of the temperatures, 2e-6). Newton's iterations converge to the same steady state with it (M5: torch's within
2e-15 K of JAX's, which uses the exact Jacobian)."""


def _difference_jacobian(f, T, u):
    """``∂f/∂T (..., n, n)`` of a torch right-hand side ``f(T (..., n), u (..., m)) -> (..., n)`` by central
    differences, all ``2·n`` moved states in one call of ``f``: the steady state's Newton iterations on torch took
    9 ms a Jacobian by ``torch.func.jacfwd`` (its transforms' dispatch) against 0.2 ms for one eager call of the
    case study's M5 right-hand side on fourteen states (2026-12-02, issue 18)."""
    import torch

    n = T.shape[-1]
    h = JACOBIAN_REL_STEP * torch.clamp(T.abs(), min=1.0)  # (..., n)
    E = torch.diag_embed(h)  # (..., n, n): row j moves state j
    X = torch.cat([T.unsqueeze(-2) + E, T.unsqueeze(-2) - E], -2)  # (..., 2n, n)
    U = torch.broadcast_to(u.unsqueeze(-2), (*X.shape[:-1], u.shape[-1]))
    F = f(X, U)  # (..., 2n, n)
    step = torch.diagonal(X[..., :n, :] - X[..., n:, :], dim1=-2, dim2=-1)  # 2h as represented
    return ((F[..., :n, :] - F[..., n:, :]) / step.unsqueeze(-1)).transpose(-1, -2)


class Model:
    """A compiled network (see docs/architecture.md, "The compiled model"). Build with :func:`compile`.

    Shapes: ``T (..., n_states)`` K, ``u (..., n_inputs)`` SI (temperature inputs in K), outputs
    ``(..., n_outputs)`` K. Leading axes broadcast (batches of windows)."""

    def __init__(self, net: Network, backend: str = "jax", dtype: str = "float64", torch_compile: bool = False,
                 sparse: bool | None = None) -> None:
        if not isinstance(net, Network):
            raise TypeError(f"compile() needs a tnn_dsl.Network, got {type(net).__name__}")
        self.network = net
        self.backend = backend
        self.dtype = dtype
        self.torch_compile = bool(torch_compile) and backend == "torch"
        """Whether torch rollouts run through ``torch.compile`` (see :func:`compile`)."""
        self.xp = get_xp(backend, dtype)
        self._plan = _Plan(net)
        self.sparse = self._plan.ns >= SPARSE_MIN_STATES if sparse is None else bool(sparse)
        """Whether the constant matrices are kept sparse (gather/scatter, O(nodes + links) per step; see
        :mod:`tnn_dsl.compiler.sparse`) rather than dense (one product each, O(n²))."""
        self._core = _Core(self._plan, self.xp, self.sparse)
        P = self._plan
        self.state_names = P.state_names
        self.input_names = tuple(P.inputs)
        self.output_names = tuple(s.name for s in net.sensors)
        self.scale_keys = P.scale_keys
        self.flow_names = tuple(P.flow_keys)
        self.param_specs = self._specs()
        self._jit_cache: dict = {}
        self._nominal_np = None
        self._tau = None
        self._compile_failed = False

    def compile_torch_rollouts(self) -> bool:
        """Turn on compiled torch rollouts (``torch_compile``) for this model from now on, unless torch failed to
        compile here before (that warned once; the model stays eager). Returns whether they are on; always
        ``False`` on another backend."""
        if self.backend == "torch" and not self._compile_failed:
            self.torch_compile = True
        return self.torch_compile

    def _compiling_failed(self, e: Exception) -> None:
        """torch could not compile here (inductor needs a C++ compiler): warn once, run eager from here on."""
        self.torch_compile = False
        self._compile_failed = True
        warnings.warn(f"torch.compile failed ({type(e).__name__}: {str(e)[:200]}); the model runs eager from here "
                      "on", TorchCompileWarning, stacklevel=5)

    # -- parameters ------------------------------------------------------------------------------

    def _specs(self) -> dict[str, ParamSpec]:
        P = self._plan
        specs: dict[str, ParamSpec] = {}
        for p in self.network.params:
            if p.is_constant:
                specs[p.name] = ParamSpec(
                    p.name, (), "physical", bool(p.free) and p.name not in P.param_targets,
                    p.role in POSITIVE_ROLES, p.lower, p.upper, p.role)
        for fn in self.network.learned:
            for k, (shape, kind) in _learned.array_shapes(fn, len(fn.inputs), len(fn.targets)).items():
                name = f"{fn.name}.{k}"
                specs[name] = ParamSpec(name, shape, kind, kind == "weights" and not fn.frozen, False, None, None,
                                        "generic")
        return specs

    def _init_numpy(self, seed: int = 0) -> dict[str, np.ndarray]:
        P = self._plan
        rng = np.random.default_rng(seed)
        out: dict[str, np.ndarray] = {p.name: np.asarray(float(p.value)) for p in self.network.params if p.is_constant}
        for fn in self.network.learned:
            arrs = _learned.init_arrays(fn, len(fn.inputs), len(fn.targets), rng)
            out.update({f"{fn.name}.{k}": v for k, v in arrs.items()})
        # default normalisation from nominal values (targets equal their nominal at z = 0)
        nominal = self._nominal_values(out)
        for fn in self.network.learned:
            xm, xs = [], []
            for kind, name in P.fn_inputs[fn.name]:
                if kind == "node" or (kind == "input" and self.network.inputs[P.input_idx[name]].is_temperature):
                    xm.append(NOMINAL_T)
                    xs.append(T_SCALE)
                elif kind == "input":
                    xm.append(0.0)
                    xs.append(1.0)
                else:
                    v = float(np.mean(nominal.get(name, 0.0)))
                    xm.append(v)
                    xs.append(abs(v) if v != 0 and math.isfinite(v) else 1.0)
            ys = []
            for t in fn.targets:
                if t.kind == "param":
                    v = float(np.mean(nominal.get(t.name, 1.0)))
                    ys.append(abs(v) if v != 0 and math.isfinite(v) else 1.0)
                else:
                    ys.append(1.0)
            out[f"{fn.name}.x_mean"] = np.asarray(xm, dtype=float).reshape(len(fn.inputs))
            out[f"{fn.name}.x_scale"] = np.asarray(xs, dtype=float).reshape(len(fn.inputs))
            out[f"{fn.name}.y_scale"] = np.asarray(ys, dtype=float)
        return out

    def _numpy_core(self) -> "_Core":
        """The model's plan on numpy (nominal values, time constants), assembled once: on a 10 000-node plate an
        assembly takes about a second, and the first rollout used to build two."""
        if self.backend == "numpy":
            return self._core
        core = self._jit_cache.get("numpy_core")
        if core is None:
            core = self._jit_cache["numpy_core"] = _Core(self._plan, get_xp("numpy"), self.sparse)
        return core

    def _nominal_values(self, params_np) -> dict[str, Any]:
        """Parameter values at the nominal point (T = 298.15 K, inputs 0 or 298.15 K) with numpy."""
        core = self._numpy_core()
        prep = core.prepare(params_np)
        T = np.full(self._plan.ns, NOMINAL_T)
        env = core.values(prep, T, self._nominal_u())
        return {k: np.asarray(v) for k, v in env.vals.items()}

    def _nominal_u(self):
        return np.asarray([NOMINAL_T if i.is_temperature else 0.0 for i in self.network.inputs], dtype=float)

    def init_params(self, seed: int = 0) -> dict:
        """The parameter table: constants at their SI values, learned arrays initialised (``seed``)."""
        with collector_paused():  # one array per constant: 40 000 on a 10 000-node plate (see core.collector)
            return self.from_numpy(self._init_numpy(seed))

    def to_numpy(self, params: Mapping[str, Any]) -> dict[str, np.ndarray]:
        """Backend arrays → float64 numpy arrays (copies)."""
        return {k: np.array(self.xp.to_numpy(v), dtype=np.float64) for k, v in params.items()}

    def from_numpy(self, arrays: Mapping[str, Any]) -> dict:
        """numpy arrays (or floats) → backend arrays in the model's dtype."""
        keys, arrs = [], []
        for k, v in arrays.items():
            a = np.asarray(v, dtype=np.float64)
            spec = self.param_specs.get(k)
            if spec is not None and tuple(a.shape) != tuple(spec.shape):
                raise TnnError(f"parameter {k!r} has shape {a.shape}, the model expects {spec.shape}")
            keys.append(k)
            arrs.append(a)
        return dict(zip(keys, self.xp.asarrays(arrs)))

    def _packed(self, params):
        """On a sparse model: the parameter table with its constants packed into one vector
        (:data:`~tnn_dsl.compiler.assembly.PACKED_KEY`). JAX: a jitted call takes one array instead of one
        argument per constant (with tens of thousands of them XLA's compile time grows faster than linearly:
        4 min for 40 000). torch: one stack per call instead of one per group of links. The last vector is
        reused while the same arrays come back (JAX arrays are immutable; a torch tensor also by its version
        counter, and never when autograd records). Dense models, and tables already packed, are returned as
        they are."""
        names = self._core.const_names
        if self.backend == "numpy" or not self.sparse or not names or PACKED_KEY in params:
            return params
        vs = [params[k] for k in names]
        last = self._jit_cache.get("packed")  # the last table's values (kept alive, so `is` is safe) and vector
        if self.backend == "jax":
            import jax
            import jax.numpy as jnp

            if last is not None and all(a is b for a, b in zip(last[0], vs)):
                packed = last[1]
            elif any(isinstance(v, jax.core.Tracer) for v in vs):
                packed = jnp.stack([jnp.asarray(v, dtype=self.xp.dtype) for v in vs])
            else:
                packed = jnp.asarray(np.asarray(jax.device_get(vs), dtype=np.float64), dtype=self.xp.dtype)
                self._jit_cache["packed"] = (vs, packed)
        else:
            import torch

            recording = torch.is_grad_enabled() and any(getattr(v, "requires_grad", False) for v in vs)
            versions = [getattr(v, "_version", None) for v in vs]
            if (not recording and last is not None and all(a is b for a, b in zip(last[0], vs))
                    and last[2] == versions):
                packed = last[1]
            else:
                packed = torch.stack([self.xp.asarray(v).reshape(()) for v in vs])
                if not recording:
                    self._jit_cache["packed"] = (vs, packed, versions)
        index = self._core.const_index
        out = {k: v for k, v in params.items() if k not in index}
        out[PACKED_KEY] = packed
        return out

    def pack_params(self, params: Mapping[str, Any]) -> dict:
        """The parameter table with its constants packed into one vector (key ``"const:packed"``) on a sparse
        model, for callers that ``jit`` their own functions of the table (one argument instead of one per
        constant: XLA's compile time grows faster than linearly in their number). Every method of the model
        takes either form; a dense model's table is returned as it is. Change constants in the unpacked table
        and pack again: a packed table ignores constants set by name next to the vector."""
        self._check(params)
        return self._packed(params)

    def _check(self, params):
        if PACKED_KEY in params:
            index = self._core.const_index
            missing = [k for k in self.param_specs if k not in params and k not in index]
        else:
            missing = [k for k in self.param_specs if k not in params]
        if missing:
            raise TnnError(
                [Diagnostic(f"the parameter table lacks {', '.join(repr(m) for m in missing[:8])}"
                            + (f" and {len(missing) - 8} more" if len(missing) > 8 else ""),
                            hint="start from model.init_params() and change values in place")])
        bad = [k for k in params if k.startswith("scale:") and k not in self._scale_set]
        if bad:
            raise TnnError([Diagnostic(f"unknown scale key {bad[0]!r}",
                                       hint="scale keys are 'scale:<parameter>' or 'scale:<flow>'; "
                                            "see model.scale_keys")])

    @property
    def _scale_set(self):
        s = getattr(self, "_scale_set_cache", None)
        if s is None:
            s = self._scale_set_cache = set(self.scale_keys)
        return s

    def _prepare(self, params):
        self._check(params)
        return self._core.prepare(self._packed(params))

    # -- time constants --------------------------------------------------------------------------

    def time_constants(self, params: Mapping[str, Any] | None = None) -> dict[str, float]:
        """``{state: τ}`` (s) = ``−1/d`` from the diagonal of the linear part at the nominal point
        (default parameters unless given as numpy-convertible ``params``); ``inf`` where d ≥ 0."""
        p_np = self._init_numpy(0) if params is None else self.to_numpy(params)
        core = self._numpy_core()
        prep = core.prepare(p_np)
        T = np.full(self._plan.ns, NOMINAL_T)
        _, d = core.rhs(prep, T, self._nominal_u(), with_diag=True)
        d = np.broadcast_to(np.asarray(d, dtype=float), (self._plan.ns,))
        return {name: (-1.0 / di if di < 0 else math.inf) for name, di in zip(self.state_names, d)}

    def fastest_time_constant(self) -> tuple[float, str]:
        """``(τ_min (s), state name)`` at nominal parameters (cached)."""
        if self._tau is None:
            tc = self.time_constants()
            name = min(tc, key=tc.get)
            self._tau = (tc[name], name)
        return self._tau

    # -- evaluation ------------------------------------------------------------------------------

    def _arr(self, x):
        return self.xp.asarray(x)

    def rhs(self, params: Mapping[str, Any], T: Any, u: Any) -> Any:
        """``dT/dt (..., n_states)`` K/s for ``T (..., n_states)`` K and ``u (..., n_inputs)`` SI."""
        if self.backend == "jax":
            self._check(params)
            return self._run_jitted("rhs", (), self._packed(params), self._arr(T), self._arr(u))
        return self._core.rhs(self._prepare(params), self._arr(T), self._arr(u))

    def outputs(self, params: Mapping[str, Any], T: Any, u: Any) -> Any:
        """Sensor readings ``(..., n_outputs)`` K (node or lag state + offset)."""
        if self.backend == "jax":
            self._check(params)
            return self._run_jitted("outputs", (), self._packed(params), self._arr(T), self._arr(u))
        return self._core.outputs(self._prepare(params), self._arr(T), self._arr(u))

    def heat_flows(self, params: Mapping[str, Any], T: Any, u: Any) -> dict:
        """Every link/component flow (W) by name (see :attr:`flow_names`), shape ``T.shape[:-1]``."""
        if self.backend == "jax":
            self._check(params)
            return self._run_jitted("heat_flows", (), self._packed(params), self._arr(T), self._arr(u))
        return self._core.heat_flows(self._prepare(params), self._arr(T), self._arr(u))

    def rhs_and_diag(self, params: Mapping[str, Any], T: Any, u: Any) -> tuple[Any, Any]:
        """``(dT/dt, d)``: the right-hand side and the diagonal of its linear part (1/s), as used by
        ``expeuler``."""
        return self._core.rhs(self._prepare(params), self._arr(T), self._arr(u), with_diag=True)

    def _run_jitted(self, what: str, static: tuple, *args):
        """The compiled program :meth:`_jitted` ``(what, *static)`` on ``args``: with XLA's lean options
        (``Backend.jit(..., lean=True)``) for the point evaluations and the steady state called from Python, the
        default where the call is traced inside another program (JAX takes compiler options only at the top
        level; the enclosing program's options apply); every program called from Python inside
        :func:`~.backends.adapter.lean_programs`."""
        import jax

        from .backends.adapter import lean_programs_active

        lean = what in LEAN_PROGRAMS and not any(isinstance(a, jax.core.Tracer)
                                                  for a in jax.tree_util.tree_leaves(args))
        if not lean and lean_programs_active():
            # inside the trainer's loss (a trace whose arguments may all be constants) the enclosing program's
            # options apply; JAX refuses options on a nested program
            clean = getattr(getattr(getattr(jax, "_src", None), "core", None), "trace_state_clean", None)
            lean = clean is not None and bool(clean())
        return self._jitted(what, *static, lean=lean)(*args)

    def _jitted(self, what, *static, lean: bool = False):
        from .backends.adapter import forward_only_active

        # traced forward only (Backend.no_grad): the core may pick forward kernels (assembly.NODE_MATRIX_MAX), so a
        # program of its own
        key = (what, *static, "forward_only", lean) if forward_only_active() else (what, *static, lean)
        f = self._jit_cache.get(key)
        if f is None:
            from .backends.adapter import Backend

            jit = Backend("jax").jit
            core = self._core
            if what == "rollout":
                dt, integrator, substeps = static

                def rollout(p, T0, U):
                    return self._rollout_impl(p, T0, U, dt, integrator, substeps)

                f = jit(rollout, lean=lean)
            elif what == "steady":
                max_iter, tol = static

                def steady_state(p, u, T0):
                    return self._steady_impl(p, u, T0, max_iter, tol)

                f = jit(steady_state, lean=lean)
            else:
                method = getattr(core, what)

                def point(p, T, u):
                    return method(self._prepare(p), T, u)

                point.__name__ = point.__qualname__ = what
                f = jit(point, lean=lean)
            self._jit_cache[key] = f
        return f

    # -- rollout -------------------------------------------------------------------------------------

    def rollout(self, params: Mapping[str, Any], T0: Any, inputs: Any, dt: float, integrator: str = "rk4",
                substeps: int | None = None) -> tuple[Any, Any]:
        """Simulate from ``T0 (..., n_states)`` K with ``inputs (..., N, n_inputs)`` held over each interval
        of ``dt`` seconds. Returns ``(states (..., N, n_states), outputs (..., N, n_outputs))`` with
        ``states[..., 0, :] = T0`` and ``outputs[..., k, :]`` the sensors at ``states[k]``, ``inputs[k]``.

        ``integrator``: ``"euler"`` (eq. 4.7), ``"rk4"`` or ``"expeuler"`` (stiff-stable). With
        ``substeps=None`` explicit methods sub-step automatically (and warn) when ``dt`` exceeds their
        stability limit for the network's fastest time constant at nominal parameters."""
        if integrator not in INTEGRATORS:
            raise TnnError([Diagnostic(f"unknown integrator {integrator!r}",
                                       hint="use one of: " + ", ".join(INTEGRATORS))])
        tau, where = self.fastest_time_constant()
        dt = float(dt)
        sub = check_step(integrator, dt, tau, substeps, where)
        T0 = self._arr(T0)
        inputs = self._arr(inputs)
        ns, ni = len(self.state_names), len(self.input_names)
        if self.xp.shape(T0)[-1:] != (ns,):
            raise TnnError(f"T0 must have shape (..., {ns}) (states: {', '.join(self.state_names)}), "
                           f"got {self.xp.shape(T0)}")
        if len(self.xp.shape(inputs)) < 2 or self.xp.shape(inputs)[-1] != ni:
            raise TnnError(f"inputs must have shape (..., N, {ni}) (inputs: {', '.join(self.input_names)}), "
                           f"got {self.xp.shape(inputs)}")
        with collector_paused():  # tracing a large network's first call walks a million live objects otherwise
            if self.backend == "jax":
                self._check(params)
                return self._run_jitted("rollout", (dt, integrator, sub), self._packed(params), T0, inputs)
            return self._rollout_impl(params, T0, inputs, dt, integrator, sub)

    def rollouts_of(self, params_list: Sequence[Mapping[str, Any]], T0: Any, inputs: Any, dt: float,
                    integrator: str = "rk4", substeps: int | None = None) -> tuple[Any, Any]:
        """One simulation per parameter set of ``params_list`` (``B`` of them), each from its row of ``T0 (B,
        n_states)`` K, all over the same ``inputs (N, n_inputs)``: ``(states (B, N, n_states), outputs (B, N,
        n_outputs))``, each row what :meth:`rollout` gives for its parameters (no gradients).

        torch with compiled rollouts runs them as one compiled ``scan`` over the samples whose step is
        ``torch.func.vmap``-ed over the parameter sets (:meth:`_compiled_torch_param_batch`): the per-step cost of the
        compiled scan (its C++ wrapper's call, the kernels' launches: ~10 µs a step on the case study) is paid once
        for the batch, not once per set. Elsewhere (JAX, numpy, eager torch) one :meth:`rollout` per set; JAX code
        vmaps :meth:`rollout` itself. The model doctor's difference Jacobians on torch (``doctor.engine``) run
        through here."""
        tau, where = self.fastest_time_constant()
        dt = float(dt)
        sub = check_step(integrator, dt, tau, substeps, where)
        T0 = self._arr(T0)
        inputs = self._arr(inputs)
        B, ns, ni = len(params_list), len(self.state_names), len(self.input_names)
        if tuple(self.xp.shape(T0)) != (B, ns):
            raise TnnError(f"T0 must have shape ({B}, {ns}) (one row per parameter set; states: "
                           f"{', '.join(self.state_names)}), got {self.xp.shape(T0)}")
        if len(self.xp.shape(inputs)) != 2 or self.xp.shape(inputs)[-1] != ni:
            raise TnnError(f"inputs must have shape (N, {ni}) (inputs: {', '.join(self.input_names)}), "
                           f"got {self.xp.shape(inputs)}")
        N = self.xp.shape(inputs)[0]
        if (self.backend == "torch" and self.torch_compile and N > 1 and B > 0 and not _functorch_active()
                and not any(_needs_grad(p, T0, inputs) for p in params_list)):
            import torch

            with collector_paused():
                preps = [self._prepare(p) for p in params_list]
                rest = self._compiled_torch_param_batch(preps, T0, inputs[: N - 1], dt, integrator, sub)
                if rest is not None:
                    states = torch.cat([T0[:, None, :], rest], 1)
                    outputs = torch.stack([self._core.outputs(pr, states[b], inputs) for b, pr in enumerate(preps)])
                    return states, outputs
        runs = [self.rollout(p, T0[b], inputs, dt, integrator, sub) for b, p in enumerate(params_list)]
        if not runs:
            return (self.xp.zeros((0, N, ns)), self.xp.zeros((0, N, len(self.output_names))))
        return self.xp.stack([r[0] for r in runs]), self.xp.stack([r[1] for r in runs])

    def sample_steps(self, params: Mapping[str, Any], inputs: Any, dt: float, integrator: str = "rk4",
                     substeps: int | None = None) -> "SampleSteps":
        """The model over one record, prepared once for a filter that steps it one sample at a time: the
        parameters' preparation and the input-only part of the right-hand side for every sample of ``inputs (N,
        n_inputs)`` are computed here, not once per sample (:meth:`rollout` of one interval does both on each call:
        ~0.5 ms of Python per call in eager torch). Returns a :class:`SampleSteps`: ``step(T (..., n_states), k)``
        is ``rollout(params, T, inputs[[k, k]], dt, ...)``'s second state (the same operations), ``outputs(T,
        u)`` and ``rhs(T, u)`` as :meth:`outputs` and :meth:`rhs`. ``substeps`` as resolved by the caller
        (``check_step``); differentiable in reverse and forward mode (``torch.func.jvp``). torch's compiled
        models step through their compiled step where gradients are wanted outside a ``torch.func`` transform,
        as :meth:`rollout` does, unless ``step(T, k, eager=True)`` (a compiled graph has no second derivatives)."""
        tau, where = self.fastest_time_constant()
        dt = float(dt)
        sub = check_step(integrator, dt, tau, substeps, where)
        inputs = self._arr(inputs)
        prep = self._prepare(params)
        core, xp = self._core, self.xp
        ctx = core.rhs_u(prep, inputs)
        if self.backend == "torch":
            def split(v, ax):  # contiguous samples: a compiled step is specialised on strides
                return xp.moveaxis(v, ax, 0).contiguous().unbind(0)
        else:
            def split(v, ax):
                return [xp.take(v, k, axis=ax) for k in range(xp.shape(v)[ax])]
        # the context split into samples from the second step on; the first takes its sample alone (a filter that
        # steps every sample at once, step_all, steps one sample for its Jacobian: torch's unbind of Bacher &
        # Madsen's 1691 samples and its reverse cost ~6 ms of such an evaluation's ~52, 2026-12-06).
        # rows: [] before the first step, [None] after it, [(s_l, v_l, u_l)] once split
        rows: list = []
        stepper = self._stepper(prep, dt, integrator, sub)
        compiled = self._compiled_torch_step(prep, dt, integrator, sub) if self.torch_compile else None

        def step(T, k, eager=False):
            k = int(k)
            if not rows:
                rows.append(None)
                c = {"s": {name: split(v[..., k:k + 1], -1)[0] for name, v in ctx["s"].items()},
                     "v": {name: split(v[..., k:k + 1, :], -2)[0] for name, v in ctx["v"].items()},
                     "u": split(ctx["u"][..., k:k + 1, :], -2)[0]}
            else:
                if rows[0] is None:
                    rows[0] = ({name: split(v, -1) for name, v in ctx["s"].items()},
                               {name: split(v, -2) for name, v in ctx["v"].items()}, split(ctx["u"], -2))
                s_l, v_l, u_l = rows[0]
                c = {"s": {name: a[k] for name, a in s_l.items()}, "v": {name: a[k] for name, a in v_l.items()},
                     "u": u_l[k]}
            if not eager and compiled is not None and _needs_grad(params, T, inputs) and not _functorch_active():
                return compiled(T, c)
            return stepper(T, c)

        def step_all(T):  # T (N, n_states): sample k's step from row k, all at once
            return stepper(T, ctx)

        return SampleSteps(step, lambda T, u: core.outputs(prep, T, u), lambda T, u: core.rhs(prep, T, u), step_all)

    def steps_of_rows(self, params: Mapping[str, Any], T: Any, inputs: Any, dt: float, integrator: str = "rk4",
                      substeps: int | None = None) -> Any:
        """Row ``k`` of ``T (N, n_states)`` K stepped over one sample interval of ``dt`` s with ``inputs[k]`` (N,
        n_inputs) held: ``(N, n_states)`` K, each row what :meth:`rollout` makes of that state and sample (the same
        step, ``substeps`` resolved as it resolves them), all rows at once and independently — no time loop. For a
        caller that linearises a simulated trajectory sample by sample (the model doctor's score test,
        ``doctor.engine``); differentiable in forward and reverse mode on both backends (torch eager)."""
        tau, where = self.fastest_time_constant()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", StepSizeWarning)  # the rollout of these states has said so already
            sub = check_step(integrator, float(dt), tau, substeps, where)
        prep = self._prepare(params)
        return self._stepper(prep, float(dt), integrator, sub)(T, self._core.rhs_u(prep, inputs))

    def _stepper(self, prep, dt, integrator, sub, core=None, traced=False):
        """``step(T, ctx) -> T_next`` over one sample interval; ``ctx`` is one sample of
        :meth:`_Core.rhs_u` (the input-only work is done once per sample, not per stage). ``core``: the
        model's own unless given (the compiled torch rollout traces a core on :class:`FusedTorchXP`);
        ``traced``: the step is traced by ``torch.compile`` (more than 4 sub-steps become a ``scan``)."""
        core = self._core if core is None else core
        xp = core.xp
        h = dt / sub
        if integrator == "expeuler":
            def one(T, c):
                return expeuler(lambda x: core.rhs_T(prep, c, x, with_diag=True), T, h, xp)
        else:
            method = euler if integrator == "euler" else rk4

            def one(T, c):
                return method(lambda x: core.rhs_T(prep, c, x), T, h)
        if sub == 1:
            return one
        if self.backend == "jax" and sub > 4:
            import jax

            def many(T, c):
                return jax.lax.fori_loop(0, sub, lambda i, x: one(x, c), T)
            return many
        if self.backend == "torch" and sub > 4 and traced:
            from torch._higher_order_ops import scan

            def many_scan(T, c):  # traced for torch.compile: one sub-step body, not ``sub`` copies of it
                import torch

                def body(x, _):
                    x = one(x, c)
                    return x, x.sum()
                return scan(body, T, torch.zeros(sub, dtype=T.dtype))[0]
            return many_scan

        def many_py(T, c):
            for _ in range(sub):
                T = one(T, c)
            return T
        return many_py

    def _fused_core(self):
        """The model's plan on :class:`~tnn_dsl.compiler.backends.torch_ops.FusedTorchXP` (small products as
        multiply-and-sum), for the rollouts traced by ``torch.compile``; built once."""
        core = self._jit_cache.get("fused_core")
        if core is None:
            from .backends.torch_ops import FusedTorchXP

            core = self._jit_cache["fused_core"] = _Core(self._plan, FusedTorchXP(self.dtype), self.sparse)
        return core

    def _compiled_torch_step(self, prep, dt, integrator, sub):
        """``step(T, ctx)`` as in :meth:`_stepper`, run through ``torch.compile`` (one graph per sample
        interval, ``prep`` an input so that new parameters reuse it): the step-by-step path of torch rollouts
        *with gradients* where :meth:`_torch_adjoint_rollout` does not run (``TORCH_ADJOINT = False``, the packed
        parameters of large networks). (torch 2.13's own ``scan`` does not support gradients with respect to what
        its body closes over — here the parameters — and, measured on the test networks, returned one
        parameter's gradient for another's.) The compiled function
        is kept per ``(dt, integrator, sub)``; torch recompiles it for new shapes (dynamic after the second). If
        torch cannot compile here (inductor needs a C++ compiler), the model warns once and runs eager."""
        import torch

        key = ("torch_step", dt, integrator, sub)
        compiled = self._jit_cache.get(key)
        if compiled is None:
            def full_step(prep, T, c):
                return self._stepper(prep, dt, integrator, sub)(T, c)
            # torch keeps compiled code per code object, with a limit on variants: a code object of this
            # model's own keeps models apart (and one model's shapes from exhausting another's limit)
            code = full_step.__code__.replace(co_name=f"tnn_step_{id(self):x}_{len(self._jit_cache)}")
            full_step = types.FunctionType(code, full_step.__globals__, code.co_name, None, full_step.__closure__)
            compiled = torch.compile(full_step, fullgraph=True)
            self._jit_cache[key] = compiled
        eager = self._stepper(prep, dt, integrator, sub)

        def step(T, c):
            if self.torch_compile:
                try:
                    return compiled(prep, T, c)
                except Exception as e:  # noqa: BLE001 - compiler infrastructure, not the user's model
                    self._compiling_failed(e)
            return eager(T, c)
        return step

    def _compiled_torch_chunks(self, prep, T0, ctx, dt, integrator, sub, chunk):
        """The states after ``T0 (..., n_states)`` for every sample of ``ctx`` (:meth:`_Core.rhs_u` of the
        rollout's samples but the last, time on its last axis (``s``) or next to last (``v``, ``u``)), ``(..., M,
        n_states)``, with gradients: ``chunk`` sample intervals unrolled in one compiled graph, called once per
        ``chunk`` samples (the per-call cost of a compiled graph, ~60 µs, paid once per chunk instead of once per
        step; autograd records one node per chunk). The samples are padded to a multiple of ``chunk`` with the
        last one (those states are dropped, so they add nothing to any gradient). Kept per ``(dt, integrator,
        sub, chunk)``; ``None`` after a warning if torch cannot compile here."""
        import torch

        key = ("torch_chunk", dt, integrator, sub, chunk)
        compiled = self._jit_cache.get(key)
        if compiled is None:
            def chunk_steps(prep, T, c):  # c: every leaf with the chunk's samples on axis 0
                step = self._stepper(prep, dt, integrator, sub)
                outs = []
                for k in range(chunk):
                    T = step(T, {"s": {n: a[k] for n, a in c["s"].items()},
                                 "v": {n: a[k] for n, a in c["v"].items()}, "u": c["u"][k]})
                    outs.append(T)
                return torch.stack(outs, 0)
            code = chunk_steps.__code__.replace(co_name=f"tnn_chunk_{id(self):x}_{len(self._jit_cache)}")
            chunk_steps = types.FunctionType(code, chunk_steps.__globals__, code.co_name, None,
                                             chunk_steps.__closure__)
            compiled = self._jit_cache[key] = torch.compile(chunk_steps, fullgraph=True)
        M = ctx["u"].shape[-2]
        n_chunks = -(-M // chunk)
        pad = n_chunks * chunk - M

        def split(v, ax):  # time-major, padded, (n_chunks, chunk, ...): each chunk a contiguous block
            v = torch.movedim(v, ax, 0)
            if pad:
                v = torch.cat([v, v[-1:].expand(pad, *v.shape[1:])], 0)
            return v.reshape(n_chunks, chunk, *v.shape[1:]).contiguous().unbind(0)

        s_l = {k: split(v, -1) for k, v in ctx["s"].items()}
        v_l = {k: split(v, -2) for k, v in ctx["v"].items()}
        u_l = split(ctx["u"], -2)
        T = T0
        outs = []
        try:
            for i in range(n_chunks):
                ys = compiled(prep, T, {"s": {n: a[i] for n, a in s_l.items()},
                                        "v": {n: a[i] for n, a in v_l.items()}, "u": u_l[i]})
                T = ys[-1]
                outs.append(ys)
        except Exception as e:  # noqa: BLE001 - compiler infrastructure, not the user's model
            self._compiling_failed(e)
            return None
        return torch.movedim(torch.cat(outs, 0)[:M], 0, -2)

    def _adjoint_runner(self, dt, integrator, sub, unbatched, batch: int | None = None, samples: int | None = None,
                        reuse: bool = False):
        """The :class:`~tnn_dsl.compiler.torch_adjoint.AdjointRollout` of this model's step, kept per ``(dt, integrator,
        sub, unbatched)`` and whether its kernels are SIMD (:func:`_torch_vectorize` of the rollout's ``batch`` of
        sequences, their ``samples`` and whether the network has an MLP); traced on :class:`FusedTorchXP`. Its compiled
        forward scan serves both the rollouts with gradients (:meth:`_torch_adjoint_rollout`) and those without
        (:meth:`_forward_scan`, with ``reuse``: a runner of the other kind already made is taken rather than a new graph
        compiled, unless ``TNN_TORCH_SIMD`` chooses the kind; a free run alone, paid for once, does not repay the SIMD
        kernels' longer compiling, so it gets none of its own)."""
        from .torch_adjoint import AdjointRollout

        smooth_mlp = any(fn.kind == "mlp" and fn.activation != "relu" for fn in self.network.learned)
        simd = _torch_vectorize(batch, samples, smooth_mlp)
        key = ("torch_adjoint", dt, integrator, sub, unbatched, TORCH_CPP_WRAPPER, simd, TORCH_SIMD_BITS)
        if reuse and key not in self._jit_cache and not os.environ.get("TNN_TORCH_SIMD", "").strip():
            other = (*key[:6], not simd, TORCH_SIMD_BITS)
            if other in self._jit_cache:
                key, simd = other, not simd
        runner = self._jit_cache.get(key)
        if runner is None:
            core = self._fused_core()

            def stepper(prep, traced):
                return self._stepper(prep, dt, integrator, sub, core, traced=traced)

            def failed(e):
                warnings.warn(f"torch.compile failed in a rollout's backward pass ({type(e).__name__}: "
                              f"{str(e)[:200]}); its gradients are computed uncompiled", TorchCompileWarning,
                              stacklevel=2)
            runner = self._jit_cache[key] = AdjointRollout(stepper, f"{id(self):x}_{len(self._jit_cache)}", failed,
                                                           options=inductor_options(simd))
        return runner

    def _forward_scan(self, prep, T0, inputs, dt, integrator, sub):
        """The states after ``T0 (..., n_states)`` (already broadcast to the rollout's batch), ``(..., M,
        n_states)`` for the ``M`` samples of ``inputs (..., M, n_inputs)``, without gradients, through the forward
        scan that a training with gradients compiles (:meth:`_adjoint_runner`; its batch and length axes are
        dynamic): a model's validation runs, its burn-in's batched Jacobian and its free runs then compile nothing
        of their own after a training (M2 of the case study compiled four graphs for a training, two of them for
        its validation; BENCHMARKS.md, "Training time"). A single sequence runs as a batch of two (it twice: torch
        specialises a batch of one), the inputs broadcast to the batch, the input-only context (:meth:`_Core.rhs_u`)
        computed before the scan. Raises :class:`~tnn_dsl.compiler.torch_adjoint.Unsupported` for the packed
        parameter table of large networks."""
        import torch

        single = T0.ndim == 1
        if single:
            T0 = T0.expand(2, T0.shape[-1])
        batch = tuple(T0.shape[:-1])
        U = torch.broadcast_to(inputs, (*batch, *inputs.shape[-2:]))
        runner = self._adjoint_runner(dt, integrator, sub, False, reuse=True)  # SIMD only if a training made it
        S = runner.states(prep, T0, _time_major(self._core.rhs_u(prep, U)))
        S = torch.movedim(S, 0, -2)
        return S[0] if single else S

    def _torch_adjoint_rollout(self, prep, T0, ctx, dt, integrator, sub):
        """The states after ``T0 (..., n_states)`` for every sample of ``ctx`` (:meth:`_Core.rhs_u` of the
        rollout's samples but the last), ``(..., M, n_states)``, with gradients, through
        :class:`~tnn_dsl.compiler.torch_adjoint.AdjointRollout`: one compiled ``scan`` forward, one compiled
        adjoint ``scan`` backward (no per-step call, no per-step autograd node). Kept per ``(dt, integrator, sub,
        batched)``; traced on :class:`FusedTorchXP`. ``None`` for the packed parameter table
        of large networks (the step-by-step path runs), and after a warning if torch cannot compile here."""
        import torch

        from .torch_adjoint import Unsupported

        runner = self._adjoint_runner(dt, integrator, sub, T0.ndim == 1, batch=math.prod(T0.shape[:-1]),
                                      samples=ctx["u"].shape[-2])
        try:
            S = runner(prep, T0, _time_major(ctx))
        except Unsupported:
            return None
        except Exception as e:  # noqa: BLE001 - compiler infrastructure, not the user's model
            self._compiling_failed(e)
            return None
        return torch.movedim(S, 0, -2)

    def _compiled_torch_rollout(self, prep, T0, inputs, dt, integrator, sub):
        """The states after ``T0 (..., n_states)`` (already broadcast to the rollout's batch), ``(..., M,
        n_states)`` for the ``M`` samples of ``inputs (..., M, n_inputs)`` (all but the last of the rollout's),
        through ``torch.compile`` of one ``scan`` over the samples (torch's ``scan`` higher-order operator). With
        :data:`TORCH_ADJOINT` on and :data:`TORCH_CHUNK` 1 that scan is the one rollouts with gradients compile
        (:meth:`_forward_scan`); otherwise, and for a large network's packed parameter table, one of its own: one
        compiled graph per rollout instead of a Python loop of per-step calls, so the per-call cost of a compiled
        graph (guards, wrapper, buffers: tens of µs) is paid once per rollout, not once per step. The input-only
        context (:meth:`_Core.rhs_u`) is computed inside the graph from the raw inputs (no gradient flows through
        the scanned arrays; only ``prep``, an input of the graph, carries the parameters).

        On a single sequence each scan iteration advances :data:`TORCH_CHUNK` samples, with a batch axis one; the
        body is traced on :class:`FusedTorchXP` (small products as multiply-and-sum). Compiled graphs
        (:class:`~.torch_adjoint.CompiledScan`, inductor's C++ wrapper unless it fails to build) are kept per
        ``(dt, integrator, sub, chunk, batched, C++ wrapper, the prepared values' structure)`` and reused for new
        parameter values, which enter flat (0-d ones as vectors of one); the scan's length is dynamic from the first
        call, other new shapes recompile (dynamic after the second). Returns ``None``
        after a warning (and the model runs eager from then on) if torch cannot compile here (inductor needs a C++
        compiler)."""
        import torch

        from .torch_adjoint import CompiledScan, Unsupported, flatten, scalar_slots, scalars_as_vectors, scalars_back

        if TORCH_ADJOINT and TORCH_CHUNK == 1:
            try:
                return self._forward_scan(prep, T0, inputs, dt, integrator, sub)
            except Unsupported:
                pass  # a large network's packed table: the scan below
            except Exception as e:  # noqa: BLE001 - compiler infrastructure, not the user's model
                self._compiling_failed(e)
                return None
        unbatched = T0.ndim == 1
        chunk = TORCH_CHUNK if unbatched else 1
        # the prepared values enter the graph flat, each 0-d tensor as a vector of one: a 0-d input would make
        # dynamo restart its analysis once the graph is traced (torch_adjoint.scalars_as_vectors), which cost the
        # first forward graph of every model a second trace (2026-11-29, TORCH_LOGS=+dynamo). The packed parameter
        # table of a large network has no flat form; it goes in as it is.
        try:
            flat, rebuild, pkey = flatten(prep)
        except Unsupported:
            flat, rebuild, pkey = None, None, None
        key = ("torch_scan", dt, integrator, sub, chunk, unbatched, TORCH_CPP_WRAPPER, _torch_vectorize(),
               TORCH_SIMD_BITS, pkey)
        compiled = self._jit_cache.get(key)
        if compiled is None:
            from torch._higher_order_ops import scan

            core = self._fused_core()
            slots = scalar_slots(flat) if flat is not None else ()

            def roll(prep, T0, U):  # U (n_chunks, chunk, ..., n_inputs), time-major
                if rebuild is not None:  # prep: the flat tensors, scalars as vectors of one
                    prep = rebuild(scalars_back(prep, slots))
                step = self._stepper(prep, dt, integrator, sub, core, traced=True)
                xs = core.rhs_u(prep, U)

                def body(T, c):
                    outs = []
                    for k in range(chunk):
                        T = step(T, {"s": {n: a[k] for n, a in c["s"].items()},
                                     "v": {n: a[k] for n, a in c["v"].items()}, "u": c["u"][k]})
                        outs.append(T)
                    return T, torch.stack(outs, 0)
                return scan(body, T0, xs)[1]
            # torch keeps compiled code per code object, with a limit on variants: a code object of this
            # model's own keeps models apart (and one model's shapes from exhausting another's limit)
            compiled = self._jit_cache[key] = CompiledScan(roll, f"tnn_rollout_{id(self):x}_{len(self._jit_cache)}",
                                                           inductor_options())
        M = inputs.shape[-2]
        n_chunks = -(-M // chunk)
        pad = n_chunks * chunk - M
        U = torch.movedim(inputs, -2, 0)
        if pad:  # the last sample repeated; its states are dropped
            U = torch.cat([U, U[-1:].expand(pad, *U.shape[1:])], 0)
        U = U.reshape(n_chunks, chunk, *U.shape[1:]).contiguous()
        # the scan's length is dynamic from the first call: one compiled graph serves every rollout length (a
        # burn-in of a few minutes, then the whole file) instead of a second compilation for the second length
        torch._dynamo.maybe_mark_dynamic(U, 0)
        # the scan's carry must be laid out as its body's result: one initial state broadcast to a batch of
        # input sequences is a view with a stride of 0, which torch refused (the model then ran eager)
        T0 = T0.contiguous()
        try:
            ys = compiled(prep if flat is None else scalars_as_vectors(flat), T0, U)
        except Exception as e:  # noqa: BLE001 - compiler infrastructure, not the user's model
            self._compiling_failed(e)
            return None
        ys = ys.reshape(n_chunks * chunk, *ys.shape[2:])[:M]
        return torch.movedim(ys, 0, -2)

    def _compiled_torch_param_batch(self, preps, T0, inputs, dt, integrator, sub):
        """The states after ``T0 (B, n_states)`` for the ``M`` samples of ``inputs (M, n_inputs)`` (all but the
        last of the rollouts'), ``(B, M, n_states)``, one parameter set per row (``preps``, each prepared by
        :meth:`_prepare`), through ``torch.compile`` of one ``scan`` over the samples whose body is the step
        ``torch.func.vmap``-ed over the sets (:meth:`rollouts_of`); the sets' prepared tensors enter flat, stacked on
        a new first axis, and their input-only contexts (:meth:`_Core.rhs_u`, vmapped too) are laid out time-major
        before the scan. The other nesting, ``vmap`` around the ``scan``, compiles too but leaves the context
        batched along the scanned axis: on the doctor's networks, whose candidate laws of an input live in that
        context, a Jacobian of 16 sets ran 31–34 s against 0.9 s so (BENCHMARKS.md, "a Jacobian's parameter sets").
        torch 2.13 specialises the graph on its batch size and its length (``maybe_mark_dynamic`` is ignored, each
        new size compiled again), so the sets run :data:`TORCH_PARAM_BATCH` at a time, the last chunk padded with
        copies of its last set: one graph per ``(dt, integrator, sub, the prepared values' structure)`` and rollout
        length. ``None`` where the sets' structures differ or hold a large network's packed table, and (after a
        warning, once per graph) where torch cannot compile it: :meth:`rollouts_of` then runs the sets one after
        another."""
        import torch

        from .torch_adjoint import CompiledScan, Unsupported, flatten, scalar_slots, scalars_as_vectors, scalars_back

        try:
            flats = [flatten(p) for p in preps]
        except Unsupported:
            return None
        flat0, rebuild, pkey = flats[0]
        if any(f[2] != pkey for f in flats[1:]):
            return None
        key = ("torch_param_batch", dt, integrator, sub, TORCH_CPP_WRAPPER, _torch_vectorize(), TORCH_SIMD_BITS, pkey)
        compiled = self._jit_cache.get(key)
        if compiled is False:  # failed before: the sets one after another
            return None
        if compiled is None:
            from torch._higher_order_ops import scan

            core = self._fused_core()
            slots = scalar_slots(flat0)

            def prep_of(flat):
                return rebuild(scalars_back(flat, slots))

            def roll(P, T0, U):
                # the input-only context of every set, then time-major: the scan runs outside vmap, its body is
                # the step vmapped over the sets
                xs = torch.func.vmap(lambda flat: core.rhs_u(prep_of(flat), U))(P)
                xs = {"s": {k: v.movedim(0, 1).contiguous() for k, v in xs["s"].items()},
                      "v": {k: v.movedim(0, 1).contiguous() for k, v in xs["v"].items()},
                      "u": xs["u"].movedim(0, 1).contiguous()}

                def step_one(flat, T, c):
                    return self._stepper(prep_of(flat), dt, integrator, sub, core, traced=True)(T, c)

                vstep = torch.func.vmap(step_one)

                def body(T, c):
                    Tn = vstep(P, T, c)
                    return Tn, Tn.clone()  # a scan's carry and output may not alias

                return scan(body, T0, xs)[1].movedim(0, 1)

            compiled = self._jit_cache[key] = CompiledScan(
                roll, f"tnn_param_batch_{id(self):x}_{len(self._jit_cache)}", inductor_options())
        B, k = len(preps), TORCH_PARAM_BATCH
        P = [torch.stack(ts) for ts in zip(*(scalars_as_vectors(f[0]) for f in flats))]
        T0 = T0.contiguous()
        pad = -B % k
        if pad:  # the last set repeated; its rollouts are dropped
            P = [torch.cat([t, t[-1:].expand(pad, *t.shape[1:])]) for t in P]
            T0 = torch.cat([T0, T0[-1:].expand(pad, T0.shape[-1])])
        U = inputs.contiguous()
        out = []
        try:
            with warnings.catch_warnings():
                # tracing vmap over the step meets a copy without a batching rule of its own (``select_copy``,
                # functorch's generic rule serves it; tests/test_torch_compile.py checks the results against JAX):
                # the warning would reach the user as noise
                warnings.filterwarnings("ignore", message="There is a performance drop because we have not yet")
                for s in range(0, B + pad, k):
                    out.append(compiled([t[s: s + k].contiguous() for t in P], T0[s: s + k].contiguous(), U))
        except Exception as e:  # noqa: BLE001 - compiler infrastructure, not the user's model
            self._jit_cache[key] = False
            warnings.warn(f"torch.compile failed for a batch of parameter sets ({type(e).__name__}: {str(e)[:200]});"
                          " they run one after another", TorchCompileWarning, stacklevel=4)
            return None
        return torch.cat(out)[:B]

    def _rollout_impl(self, params, T0, inputs, dt, integrator, sub):
        xp = self.xp
        prep = self._prepare(params)
        # torch with gradients: each step compiled apart (the compiled scan is forward-only); the burn-in fit's
        # forward-mode derivatives (torch.func) run eager, since compiled graphs cannot be called inside them
        grad = self.backend == "torch" and _needs_grad(params, T0, inputs)
        step_compiled = self.torch_compile and grad and not _functorch_active()
        if step_compiled:
            step = self._compiled_torch_step(prep, dt, integrator, sub)
        else:
            step = self._stepper(prep, dt, integrator, sub)
        N = xp.shape(inputs)[-2]
        batch = np.broadcast_shapes(xp.shape(T0)[:-1], xp.shape(inputs)[:-2])
        T0 = xp.broadcast_to(T0, (*batch, xp.shape(T0)[-1]))
        compiled = self.backend == "torch" and self.torch_compile and N > 1 and not grad and not _functorch_active()
        # the input-only part of the right-hand side, for every sample at once (outside the time loop; the
        # compiled torch rollout computes it inside its graph)
        ctx = self._core.rhs_u(prep, inputs[..., : max(N - 1, 0), :]) if N > 1 and not compiled else None
        if self.backend == "jax":
            import jax
            import jax.numpy as jnp

            # Reverse mode recomputes each sample's step from its start state instead of storing every stage's
            # intermediates (one store per intermediate per step): forward+gradient / forward 3.1 instead of 5.4
            # batched, 3.9 instead of 6.3 single (benchmarks/bench_rollout.py, case study M3).
            step = jax.checkpoint(step)

            def body(T, c):
                Tn = step(T, c)
                return Tn, Tn

            if N > 1:
                xs = {"s": {k: jnp.moveaxis(v, -1, 0) for k, v in ctx["s"].items()},
                      "v": {k: jnp.moveaxis(v, -2, 0) for k, v in ctx["v"].items()},
                      "u": jnp.moveaxis(ctx["u"], -2, 0)}
                _, rest = jax.lax.scan(body, T0, xs)
                states = jnp.concatenate([T0[None], rest], axis=0)
            else:
                states = T0[None][:N]
            states = jnp.moveaxis(states, 0, -2)
        elif compiled and (rest := self._compiled_torch_rollout(
                prep, T0, inputs[..., : N - 1, :], dt, integrator, sub)) is not None:
            states = xp.concat([T0[..., None, :], rest], axis=-2)
        elif (step_compiled and N > 1 and TORCH_ADJOINT
              and (rest := self._torch_adjoint_rollout(prep, T0, ctx, dt, integrator, sub)) is not None):
            states = xp.concat([T0[..., None, :], rest], axis=-2)
        elif (step_compiled and N > 1 and (chunk := max(1, TORCH_GRAD_CHUNK // sub)) > 1
              and (rest := self._compiled_torch_chunks(prep, T0, ctx, dt, integrator, sub, chunk)) is not None):
            states = xp.concat([T0[..., None, :], rest], axis=-2)
        else:
            T = T0
            states = [T]
            if N > 1:
                if ctx is None:  # the compiled rollout gave up (warned): eager from here on
                    ctx = self._core.rhs_u(prep, inputs[..., : N - 1, :])
                if self.backend == "numpy":
                    def split(v, ax):
                        return [np.take(v, k, axis=ax) for k in range(N - 1)]
                elif step_compiled:
                    def split(v, ax):  # contiguous samples: the compiled step is specialised on strides
                        return xp.moveaxis(v, ax, 0).contiguous().unbind(0)
                else:
                    def split(v, ax):
                        return v.unbind(ax)
                s_l = {k: split(v, -1) for k, v in ctx["s"].items()}
                v_l = {k: split(v, -2) for k, v in ctx["v"].items()}
                u_l = split(ctx["u"], -2)
                with _eager_steps(self.backend, grad):
                    for k in range(N - 1):
                        c = {"s": {name: a[k] for name, a in s_l.items()},
                             "v": {name: a[k] for name, a in v_l.items()}, "u": u_l[k]}
                        T = step(T, c)
                        states.append(T)
            states = xp.stack(states[:N], axis=-2) if N > 0 else xp.zeros((*batch, 0, xp.shape(T0)[-1]))
        outputs = self._core.outputs(prep, states, inputs)
        return states, outputs

    # -- steady state --------------------------------------------------------------------------------

    def steady_state(self, params: Mapping[str, Any], u: Any, T_init: Any = None, max_iter: int = 50,
                     tol: float = 1e-10) -> Any:
        """The steady state ``T* (..., n_states)`` K with ``f(T*, u) = 0`` for constant inputs
        ``u (..., n_inputs)`` (thesis eq. 4.1).

        Newton's method from ``T_init`` (default 298.15 K everywhere; its first step is the linear solve),
        at most ``max_iter`` iterations, stopping at a step below ``tol`` K. Differentiable: the iteration
        runs without gradient and one final Newton step with the Jacobian held fixed carries the
        implicit-function derivative ``dT*/dθ = −J⁻¹ ∂f/∂θ``."""
        P = self._plan
        if P.unanchored:
            raise TnnError([Diagnostic(
                f"no steady state: node(s) {', '.join(P.unanchored)} have no path to a boundary or fluid, so "
                "their temperature at rest depends on the initial state",
                hint="connect them to a boundary, or simulate with rollout() instead")])
        u = self._arr(u)
        T_init = None if T_init is None else self._arr(T_init)
        if self.backend == "jax":
            self._check(params)
            if T_init is None:
                T_init = self.xp.asarray(np.full(P.ns, NOMINAL_T))
            return self._run_jitted("steady", (max_iter, tol), self._packed(params), u, T_init)
        return self._steady_impl(params, u, T_init, max_iter, tol)

    def _jac(self, prep, T, u, exact: bool = True):
        """Jacobian ``∂f/∂T (..., n, n)`` (no gradient w.r.t. parameters). torch with ``exact=False``: central
        differences (:func:`_difference_jacobian`), for Newton's iterations, whose fixed point does not depend on
        the Jacobian's last digits."""
        core = self._core
        if self.backend == "jax":
            import jax
            import jax.numpy as jnp

            J = jnp.vectorize(jax.jacfwd(lambda x, v: core.rhs(prep, x, v)), signature="(n),(m)->(n,n)")(T, u)
            return J
        if self.backend == "torch":
            import torch

            if not exact:
                return _difference_jacobian(lambda x, v: core.rhs(prep, x, v), T, u)
            batch = T.shape[:-1]
            n = T.shape[-1]
            Tf = T.reshape(-1, n)
            uf = torch.broadcast_to(u, (*batch, u.shape[-1])).reshape(Tf.shape[0], u.shape[-1])
            J = torch.func.vmap(torch.func.jacfwd(lambda x, v: core.rhs(prep, x, v)))(Tf, uf)
            return J.reshape(*batch, n, n)
        # numpy: central differences (reference backend only)
        n = T.shape[-1]
        cols = []
        for j in range(n):
            e = np.zeros(n)
            e[j] = 1e-4
            cols.append((core.rhs(prep, T + e, u) - core.rhs(prep, T - e, u)) / 2e-4)
        return np.stack(cols, axis=-1)

    def _steady_impl(self, params, u, T_init=None, max_iter=50, tol=1e-10):
        xp, core, P = self.xp, self._core, self._plan
        prep = self._prepare(params)
        batch = tuple(xp.shape(u)[:-1])
        if T_init is None:
            T_init = xp.asarray(np.full(P.ns, NOMINAL_T))
        T = xp.broadcast_to(T_init, (*batch, P.ns)) * 1.0
        if self.backend == "jax":
            import jax
            import jax.numpy as jnp

            prep0 = self._core.prepare({k: jax.lax.stop_gradient(v) for k, v in params.items()})
            u0 = jax.lax.stop_gradient(u)

            def cond(c):
                k, _, delta = c
                return (k < max_iter) & (delta > tol)

            if self.sparse:  # Newton–Krylov: no (n, n) Jacobian (see compiler/krylov.py)
                from jax.scipy.sparse.linalg import bicgstab

                def newton_step(x, b):
                    _, d = core.rhs(prep0, x, u0, with_diag=True)
                    inv_d = jnp.where(d != 0, 1.0 / jnp.where(d != 0, d, 1.0), 1.0)
                    dx, _ = bicgstab(lambda v: jax.jvp(lambda y: core.rhs(prep0, y, u0), (x,), (v,))[1], b,
                                     M=lambda v: v * inv_d, tol=KRYLOV_TOL, maxiter=KRYLOV_MAXITER)
                    return dx
            else:
                def newton_step(x, b):
                    return xp.solve(self._jac(prep0, x, u0), b)

            def body(c):
                k, x, _ = c
                dx = newton_step(x, core.rhs(prep0, x, u0))
                return k + 1, x - dx, jnp.max(jnp.abs(dx))

            _, Ts, _ = jax.lax.while_loop(cond, body, (0, jax.lax.stop_gradient(T), jnp.asarray(jnp.inf, T.dtype)))
            Ts = jax.lax.stop_gradient(Ts)
            return Ts - newton_step(Ts, core.rhs(prep, Ts, u))
        if self.backend == "torch":
            import torch

            with torch.no_grad():
                prep0 = self._prepare({k: v.detach() if hasattr(v, "detach") else v for k, v in params.items()})
                x = T.detach().clone()
                u0 = u.detach()

                def f0(y):
                    return core.rhs(prep0, y, u0)

                def newton_step(x, b, exact=False):
                    if self.sparse:  # Newton–Krylov: no (n, n) Jacobian (see compiler/krylov.py)
                        return torch_solve(f0, x, core.rhs(prep0, x, u0, with_diag=True)[1], b)
                    return xp.solve(self._jac(prep0, x, u0, exact=exact), b)

                for _ in range(max_iter):
                    dx = newton_step(x, core.rhs(prep0, x, u0))
                    x = x - dx
                    if float(dx.abs().max()) <= tol:
                        break
            # the last step carries the implicit-function derivative −J⁻¹ ∂f/∂θ: with the exact Jacobian when a
            # gradient is wanted (else its digits only touch a step that is already below ``tol``)
            wanted = torch.is_grad_enabled() and any(getattr(v, "requires_grad", False)
                                                    for v in (*params.values(), u))
            return x - newton_step(x, core.rhs(prep, x, u), exact=wanted)
        x = np.array(T, dtype=float)
        for _ in range(max_iter):
            J = self._jac(prep, x, u)
            dx = xp.solve(J, core.rhs(prep, x, u))
            x = x - dx
            if np.max(np.abs(dx)) <= tol:
                break
        return x


def compile(net: Network, backend: str = "jax", dtype: str = "float64",  # noqa: A001
            torch_threads: int | None = 1, torch_compile: bool | None = None, sparse: bool | None = None) -> Model:
    """Compile a validated network for ``backend`` (``"jax"`` or ``"torch"``; ``"numpy"`` is a reference
    backend without autodiff) in ``dtype`` (``"float64"`` default, or ``"float32"``).

    ``torch_threads``: for the torch backend, the number of intra-op threads torch is set to
    (``torch.set_num_threads``; a process-wide setting). Thermal networks are small, so extra threads only
    add synchronisation: a batched case-study step measured 47× slower with torch's default 2 threads than
    with 1 on a 2-core machine (benchmarks/bench_rollout.py ``--torch-threads``). ``None`` leaves torch's
    setting alone. The environment variable ``TNN_TORCH_THREADS`` overrides the default.

    ``torch_compile``: for the torch backend, compile rollouts with ``torch.compile`` (inductor, with its C++
    wrapper: :data:`TORCH_CPP_WRAPPER`). A rollout without gradients (simulation, validation) is one compiled
    ``scan`` over the samples; a rollout with gradients (training) is a compiled forward scan and a compiled
    adjoint scan backward in time (:mod:`.torch_adjoint`; torch 2.13's ``scan`` cannot differentiate with respect
    to the parameters its body reads). Measured on the case study M3 (``python benchmarks/bench_rollout.py``,
    BENCHMARKS.md, 2026-11-27 09:35, Intel Xeon): single sequence forward 9.58 µs/step (eager 230, JAX 1.37), a
    batch of 256 windows 0.75 µs per window-step forward (eager 1.5, JAX 0.58) and 2.60 forward+gradient (eager
    5.59, JAX 1.61), after 4–19 s of compilation per graph (cold). Worth it for long simulations and training
    runs, not for one short simulation.
    ``None`` reads the environment variable ``TNN_TORCH_COMPILE`` (``1``/``0``, default off; a training decides
    by its length when neither is set: ``tnn_dsl.fit.config.torch_compile_pays``). Ignored by the other backends
    (JAX is always compiled).

    ``sparse``: keep the network's constant matrices as their non-zeros and apply them by gather and
    scatter-add, so that one step costs O(nodes + links) instead of O(n²) (:mod:`tnn_dsl.compiler.sparse`).
    ``None`` (default) chooses sparse for networks with at least
    :data:`~tnn_dsl.compiler.assembly.SPARSE_MIN_STATES` states. Both forms give the same numbers to
    round-off."""
    if backend not in ("jax", "torch", "numpy"):
        raise TnnError([Diagnostic(f"unknown backend {backend!r}", hint="use backend='jax' or backend='torch'")])
    if dtype not in ("float64", "float32"):
        raise TnnError([Diagnostic(f"unknown dtype {dtype!r}", hint="use dtype='float64' or dtype='float32'")])
    if backend == "torch":
        env = os.environ.get("TNN_TORCH_THREADS")
        if env:
            if not env.isdigit() or int(env) < 1:
                raise TnnError([Diagnostic(f"TNN_TORCH_THREADS must be a positive integer, got {env!r}")])
            torch_threads = int(env)
        if torch_threads is not None:
            import torch

            if torch.get_num_threads() != int(torch_threads):
                torch.set_num_threads(int(torch_threads))
        _torch_vectorize()  # a malformed TNN_TORCH_SIMD is reported here, not at the first rollout
    if torch_compile is None:
        env = os.environ.get("TNN_TORCH_COMPILE", "").strip()
        if env not in ("", "0", "1"):
            raise TnnError([Diagnostic(f"TNN_TORCH_COMPILE must be 0 or 1, got {env!r}")])
        torch_compile = env == "1"
    with collector_paused():  # compiling a large network walks every element: see core.collector
        return Model(net, backend, dtype, torch_compile=bool(torch_compile), sparse=sparse)


__all__ = ["compile", "Model", "ParamSpec", "TorchCompileWarning"]
