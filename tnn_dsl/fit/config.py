"""Training options: :class:`TrainConfig` (every option with its default and meaning) and :func:`load_config`
(YAML file, then overrides)."""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..core import Diagnostic, TnnError

ROLLOUTS = ("auto", "free", "steady", "measured", "estimated")


INITS = ("estimate", "filter", "steady", "measured", "auto")
OBJECTIVES = ("output-error", "ml")


TORCH_COMPILE_MIN_WORK = 2_000_000
"""Sample-epochs (samples of the training and validation files × ``epochs``) from which a torch training compiles
its rollouts when ``torch_compile`` is not set (:func:`torch_compile_pays`). Compiling cost 20–35 s (five graphs,
cold, Intel Xeon; M2's training compiles two since 2026-12-02: the validation's free runs reuse the training's
forward scan); it then saves about 3 µs per window-step of training (batched forward + gradient: 2.60 against
5.59 µs, eager) and 220 µs per step of each validation run (9.6 against 230 µs) — BENCHMARKS.md, the `rollout`
section. The case study's M2 (4 h + 2 h at 1 s, 300 epochs: 6.5·10⁶) is over it; the test suite's short trainings
are far under it."""


FREE_RUN_BATCH_VALUES = 2**24
"""At most this many state values (files × samples × states, 128 MiB of float64) in one batched free run
(:func:`~tnn_dsl.fit.simulation.free_runs`): the demo's ten 2 h files at 1 s of a 7-state model are 504 000; a
10 000-node network's 7200-sample file (7.2·10⁷ values) runs alone, as it did before batches."""


FREE_RUN_COMPILE_MIN_SAMPLES = 10_000
"""Samples (all files of one call together) from which the free runs of a loaded model on torch
(:meth:`TrainedModel.predict <tnn_dsl.fit.model_files.TrainedModel.predict>`, ``evaluate``, ``tnnc evaluate``)
compile its rollouts (:func:`free_runs_compile_pay`): more than one 2 h file at 1 s. Per 2 h file (its initial state
estimated on a burn-in, then the free run; ``python benchmarks/bench_free_runs.py --files 4``, 2026-11-29, AMD EPYC,
2 cores): the case study's M2 eager 14.4 s for the first file and 7.4 s for each other, compiled 27.5 s for the
first (compilation included) and 0.40 s for each other; M4 (an MLP Peltier element) eager 36.7 and 18.8 s,
compiled 25.4 and 1.5 s. Compiling pays from the first file on M4 and from the third on M2 (JAX: 5.0 s for the
first file, then 0.21–0.27 s each)."""


def free_runs_compile_pay(n_samples: int) -> bool | None:
    """Whether the free runs of a trained model on torch over ``n_samples`` samples in all should compile its
    rollouts: ``None`` when the environment variable ``TNN_TORCH_COMPILE`` is set (``tnn_dsl.compile`` follows it),
    else whether ``n_samples`` reaches :data:`FREE_RUN_COMPILE_MIN_SAMPLES`."""
    if os.environ.get("TNN_TORCH_COMPILE", "").strip():
        return None
    return int(n_samples) >= FREE_RUN_COMPILE_MIN_SAMPLES


ONE_SEQUENCE_WORK_WEIGHT = 20
"""How many windowed sample-epochs one sample-epoch of a training that runs each file as one sequence (single
shooting, or free runs: ``rollout`` ``free``, or ``auto`` on files of at most three windows) counts for in
:func:`torch_compile_pays`. Eager torch pays its per-operation dispatch at every step of such a rollout, where a
batch of windows shares it: a one-heater board's training (900 + 500 samples at 1 s, 300 epochs, single shooting,
``tests/test_mlp_check.py``) ran 355 ms an epoch eager and 21 ms compiled (about 250 µs saved per training
sample-epoch, 220 µs per validation sample), for some 25 s of compiling — 62 s eager against 31 s compiled to the
same early stop at epoch 150 (2026-12-06, the AMD host; BENCHMARKS.md, issue 18). Compiling pays from about
10⁵ such sample-epochs: :data:`TORCH_COMPILE_MIN_WORK` / 20."""


def one_sequence_per_file(cfg: "TrainConfig", exps: list) -> bool:
    """Whether a training of ``exps`` certainly runs each file as one sequence: ``rollout`` ``free``, or ``auto``
    with every file at most three of the shortest windows it could choose (:func:`~.windows.auto_window` or the
    ``window`` set; the trainer's window may only be longer: ``_Rollouts.plan_rollout``)."""
    from .windows import auto_window

    if cfg.rollout == "free":
        return True
    if cfg.rollout != "auto" or not exps:
        return False
    window = float(cfg.window) if cfg.window is not None else auto_window(exps)
    dt = min(float(e.dt) for e in exps)
    return max(int(e.n_steps) for e in exps) <= 3 * (window / dt + 1)


SINGLE_SHOOTING_MAX_STEPS = 8000
"""``rollout=auto`` with the ``estimate`` rule: after multiple shooting, files of at most this many samples are
fitted once more as one free run each from a fitted initial state (single shooting, an L-BFGS polish from the
windowed solution): the free run the model is judged by, without the windows' seams. The training then also runs
single shooting from the start and keeps the better of the two routes (:func:`single_shooting_route`)."""


def finishes_as_single_shooting(cfg: "TrainConfig", exps: list) -> bool:
    """The options' and files' part of whether a windowed fit of ``exps`` goes on as single shooting
    (:data:`SINGLE_SHOOTING_MAX_STEPS`; the trainer adds that its layout is windowed:
    :meth:`~tnn_dsl.fit.rollouts._Rollouts.wants_single_shooting_finish`)."""
    from .initial import check_rule

    return (cfg.rollout == "auto" and check_rule(cfg.init) in ("estimate", "filter") and cfg.lbfgs_iters > 0
            and bool(exps) and max(int(e.n_steps) for e in exps) <= SINGLE_SHOOTING_MAX_STEPS)


def single_shooting_route(cfg: "TrainConfig", exps: list) -> bool:
    """Whether a training of ``exps`` runs in windows and then also as one sequence per file: the windowed fit
    polished as single shooting, and a second training by single shooting from the start
    (:func:`finishes_as_single_shooting`, and not :func:`one_sequence_per_file`). Where the windows come out as
    long as the files (a slow node's time constant) the training is one sequence per file instead; either way
    most of its eager cost is that of one sequence per file."""
    return finishes_as_single_shooting(cfg, exps) and not one_sequence_per_file(cfg, exps)


def torch_compile_pays(cfg: "TrainConfig", n_samples: int, one_sequence: bool = False,
                       single_route: bool = False) -> bool | None:
    """``cfg.torch_compile`` where it is set; otherwise, for the torch backend, ``None`` when the environment
    variable ``TNN_TORCH_COMPILE`` is set (``tnn_dsl.compile`` reads it), else whether ``n_samples`` (training and
    validation samples, all files) × ``cfg.epochs`` × a weight reaches :data:`TORCH_COMPILE_MIN_WORK`. The weight:
    :data:`ONE_SEQUENCE_WORK_WEIGHT` where each file runs as ``one_sequence`` (:func:`one_sequence_per_file`);
    ``1 +`` that where a windowed training is followed by a ``single_route`` (:func:`single_shooting_route`:
    Bacher & Madsen's 70 % at 5 min, 1184 samples and 300 epochs, trained eager for 132 s on the doctor's
    nominal Ti model, 22 s compiled, 15 s of it compiling; 2026-12-06, BENCHMARKS.md); else 1."""
    if cfg.torch_compile is not None or cfg.backend != "torch":
        return cfg.torch_compile
    if os.environ.get("TNN_TORCH_COMPILE", "").strip():
        return None
    weight = ONE_SEQUENCE_WORK_WEIGHT if one_sequence else 1 + (ONE_SEQUENCE_WORK_WEIGHT if single_route else 0)
    return int(n_samples) * max(int(cfg.epochs), 1) * weight >= TORCH_COMPILE_MIN_WORK


@dataclass
class TrainConfig:
    """Every training option (all also ``tnnc train`` flags and YAML keys). Defaults work without
    tuning on the networks in ``networks/``.

    Units: ``window`` and ``time_limit`` in s; ``lam`` weights a max error in K against a mean squared
    error in K²; ``gamma`` weights squared *relative* deviations from the reference values."""

    backend: str = "jax"
    """``jax`` or ``torch``."""
    objective: str = "output-error"
    """``output-error``: fit the free run (thesis eq. 4.8), standard errors by Gauss–Newton. ``ml``: then maximise
    the continuous–discrete Kalman-filter likelihood from that fit (process and measurement noise estimated;
    standard errors from its Hessian; :mod:`tnn_dsl.fit.estimates`)."""
    torch_compile: bool | None = None
    """torch backend: compile the rollouts with ``torch.compile`` (see ``tnn_dsl.compile``: a forward scan, and
    an adjoint scan for the gradients). The case study's M2 reached within 10 % of its final MAE in 51 s
    compiled, compilation included, against 197–389 s eager in earlier runs (benchmarks/bench_train.py,
    BENCHMARKS.md "Training time"); a short run spends most of it compiling. ``None``: the ``TNN_TORCH_COMPILE``
    environment variable (``1``/``0``) if set, else compiled when the training is long enough to pay for it
    (:func:`torch_compile_pays`)."""
    dtype: str = "float64"
    seed: int = 0
    integrator: str = "rk4"
    """``euler`` (thesis eq. 4.7), ``rk4`` or ``expeuler``."""
    substeps: int | None = None
    rollout: str = "auto"
    """``auto``, ``free``, ``steady``, ``measured`` or ``estimated`` (see the module docstring)."""
    window: float | None = None
    """Window length (s) for windowed rollouts; ``None``: :func:`auto_window` (600 s, and at least
    :data:`MIN_WINDOW_SAMPLES` samples of the coarsest training file)."""
    batch_size: int = 0
    """Windows per optimiser step; 0 = all (full batch)."""
    epochs: int = 300
    """Adam steps over the whole training set."""
    lr: float = 0.02
    """Adam step size in transformed coordinates (0.02 ≈ 2 % of a positive parameter per step)."""
    lr_final: float = 0.1
    """Cosine decay of the step size to ``lr · lr_final`` at the last epoch."""
    clip: float | None = None
    """Global gradient-norm clip; ``None``: clip at 10× the running mean norm."""
    lam: float = 0.0
    """λ of eq. 4.8: weight of the max absolute error over each window."""
    gamma: float | dict[str, float] = 0.0
    """γ of eq. 4.8: weight of ((θ − θ_ref)/θ_ref)² per free physical parameter (one number for all,
    or ``{name: γ}``)."""
    weight_decay: float = 0.0
    """L2 weight on learned-function weights."""
    continuity: float = 10.0
    """Weight of the multiple-shooting continuity penalty (``rollout=estimated``)."""
    lbfgs_iters: int = 1000
    """L-BFGS polish iterations after Adam (0 to skip). The polish starts from Adam's last state, keeps
    the iterate with the best validation MAE (Adam's best if none is better) and stops after 100
    iterations without a better one."""
    patience: int = 80
    """Early stopping: epochs without a better validation MAE, checked from half of ``epochs`` on (a free
    run's validation error often rises while a learned function leaves its nominal value, then falls)."""
    val_every: int = 0
    """Validate every N epochs; 0 = automatically (validation takes ≤ ~40 % of the time; from step counts,
    so the schedule — and the model picked — is the same on every machine and backend)."""
    val_fraction: float = 0.0
    """Without validation files: hold out the last fraction of each training file."""
    init: str = "estimate"
    """Initial state of every free run (:mod:`tnn_dsl.fit.initial`): ``estimate`` (fitted with the parameters in
    single shooting; on validation files fitted to a burn-in at their start, which is not scored), ``filter``
    (an EKF over the burn-in), ``steady`` or ``measured``. ``auto`` is read as ``estimate``."""
    burn_in: float | None = None
    """Burn-in (s) at the start of a validation file for ``estimate``/``filter``; ``None``: a tenth of the file
    (at least 10 samples)."""
    freeze: list[str] = field(default_factory=list)
    """Parameter names or learned-function names kept fixed."""
    init_from: str | None = None
    """A model directory whose arrays (same name and shape) initialise this model."""
    prefit: bool = True
    """Pre-fit ``replace``-mode flow functions to the nominal physics flow."""
    centre_sigmoid: bool = True
    """Optimise sigmoid MLPs in tanh coordinates (σ(a) = ½ + ½·tanh(a/2), see ``_tanh_to_sigmoid``):
    the same functions and stored weights, but zero-centred hidden units with unit slope, so the steps
    of Adam are not spent moving the next layer's bias against its weights."""
    max_restarts: int = 6
    """Divergence guard: how often the best state is restored with a smaller step before giving up."""
    time_limit: float | None = None
    """Stop Adam (and the L-BFGS polish) after this many seconds of training (the best state is kept). The first
    call of each program the training compiles (tracing, compiling and one evaluation: seconds on JAX, up to
    minutes on compiled torch) is not counted; ``meta.json`` reports it as ``compile_seconds``."""

    def __post_init__(self) -> None:
        problems = []
        if self.backend not in ("jax", "torch"):
            problems.append(f"backend must be jax or torch, not {self.backend!r}")
        if self.dtype not in ("float64", "float32"):
            problems.append(f"dtype must be float64 or float32, not {self.dtype!r}")
        if self.rollout not in ROLLOUTS:
            problems.append(f"rollout must be one of {', '.join(ROLLOUTS)}, not {self.rollout!r}")
        if self.objective not in OBJECTIVES:
            problems.append(f"objective must be one of {', '.join(OBJECTIVES)}, not {self.objective!r}")
        if self.init not in INITS:
            problems.append(f"init must be one of {', '.join(INITS)}, not {self.init!r}")
        if self.burn_in is not None and not (isinstance(self.burn_in, (int, float)) and math.isfinite(self.burn_in)
                                             and self.burn_in >= 0):
            problems.append(f"burn_in must be a non-negative number of seconds, not {self.burn_in!r}")
        if self.integrator not in ("euler", "rk4", "expeuler"):
            problems.append(f"integrator must be euler, rk4 or expeuler, not {self.integrator!r}")
        positive = (("window",) if self.window is not None else ()) + ("lr",) \
            + (("clip",) if self.clip is not None else ()) + (("time_limit",) if self.time_limit is not None else ())
        for name in positive:
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
                problems.append(f"{name} must be a positive finite number, not {v!r}")
        if self.substeps is not None and (not isinstance(self.substeps, int) or isinstance(self.substeps, bool)
                                          or self.substeps < 1):
            problems.append(f"substeps must be a whole number ≥ 1 (or left out for the model's choice), "
                            f"not {self.substeps!r}")
        for name in ("epochs", "lbfgs_iters", "patience", "val_every", "batch_size", "max_restarts"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                problems.append(f"{name} must be a non-negative integer, not {v!r}")
        vf = self.val_fraction
        if not (isinstance(vf, (int, float)) and not isinstance(vf, bool) and 0.0 <= float(vf) < 1.0):
            problems.append(f"val_fraction must be in [0, 1), not {self.val_fraction!r}")
        for name in ("lam", "weight_decay", "continuity", "lr_final"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0):
                problems.append(f"{name} must be a non-negative finite number, not {v!r}")
        gammas = self.gamma.values() if isinstance(self.gamma, dict) else [self.gamma]
        for v in gammas:
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0):
                problems.append(f"gamma must be a non-negative finite number (or NAME: number), not {v!r}")
        if isinstance(self.freeze, str):
            self.freeze = [s for s in self.freeze.replace(",", " ").split() if s]
        if problems:
            raise TnnError([Diagnostic(f"training option: {p}", hint="see `tnnc train --help`") for p in problems])

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def load_config(path: str | os.PathLike | None = None, **overrides: Any) -> TrainConfig:
    """A :class:`TrainConfig` from a YAML file (keys = option names, ``-`` or ``_``) and overrides
    (``None`` values ignored). Unknown keys are an error naming the known ones."""
    import yaml

    data: dict[str, Any] = {}
    if path is not None:
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")
        except OSError as e:
            raise TnnError(Diagnostic(f"cannot read the training config {p}: {e.strerror}",
                                      hint="pass an existing YAML file to --config"))
        try:
            loaded = yaml.safe_load(text)
        except yaml.YAMLError as e:
            mark = getattr(e, "problem_mark", None)
            from ..ir import Span

            span = Span(file=str(p), line=mark.line + 1, col=mark.column + 1, end_line=mark.line + 1,
                        end_col=mark.column + 2) if mark is not None else None
            raise TnnError(Diagnostic(f"the training config is not valid YAML: {getattr(e, 'problem', e)}",
                                      span=span, hint="write `key: value` lines, e.g. `epochs: 200`"))
        if loaded is None:
            loaded = {}
        if not isinstance(loaded, dict):
            raise TnnError(Diagnostic(f"{p}: the training config must be a mapping of option: value",
                                      hint="write `key: value` lines, e.g. `epochs: 200`"))
        known = {f.name for f in dataclasses.fields(TrainConfig)}
        for k, v in loaded.items():
            key = str(k).replace("-", "_")
            if key not in known:
                import difflib

                close = difflib.get_close_matches(key, sorted(known), n=1)
                hint = f"did you mean `{close[0]}`?" if close else f"known options: {', '.join(sorted(known))}"
                raise TnnError(Diagnostic(f"{p}: unknown training option {k!r}", hint=hint))
            data[key] = v
    data.update({k: v for k, v in overrides.items() if v is not None})
    try:
        return TrainConfig(**data)
    except TypeError as e:
        raise TnnError(Diagnostic(f"training config: {e}"))
