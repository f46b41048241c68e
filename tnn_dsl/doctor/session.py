"""One run of the model doctor as named stages (:class:`_Session`): read the data, fit the nominal model,
analyse its residual, rounds of forward selection (score test, shortlist, proper fits, successive halving,
the held-out decision), the extension, linear or MLP, the result. :func:`tnn_dsl.doctor.diagnose` runs them
in order; the state they share lives on the session."""

from __future__ import annotations

import math
import os
import re
import time as _time
from functools import partial
from typing import Any, Callable

import numpy as np

from ..analysis import residuals as R
from ..core import THN, Diagnostic, TnnError, check_output, write_text_atomic
from ..core.memory import release_free_memory
from ..ir import Input, Network
from .base import BOUNDED_AT_ZERO_KINDS, STRUCTURAL_KINDS, Candidate, Extended
from .candidates import build_extended, product_partners
from .engine import (
    DOCTOR_INIT_RULES,
    FIT_CONTINUE,
    FIT_ITER,
    FIT_ITER_FIRST,
    PRIOR_FACTOR,
    X0_PREFIX,
    _cand_in,
    _Engine,
    _InitPlan,
    _make_engine,
    _params_from_state,
    _split_masks,
    _State,
    prior_bounds,
)
from .extension import _check_text, changed_lines, doctor_targets, extend_network, extension_text, finding_clause
from .fitting import _fit_result, _fit_structural, _train_lr_test, continue_fit, refit_from_written
from .results import Diagnosis, Finding
from .scoring import MIN_R2, _indistinguishable, _score, _score_forced, _shortlist, same_correction
from .selection import CONFIRM_RATIO, MIN_GAIN, ROUNDOFF_MAE_K, _choose, _place, refusal, unphysical_reason
from .stopping import stop_requested
from .structural import structural_candidates
from .threads import fit_threads, side_by_side, two_at_once
from .uncertainty import final_uncertainty
from .words import _what_is_left, _words

__all__ = ["_Session"]

REPLACEMENTS = 2
"""Candidates fitted per round in place of shortlisted fits that diverged or are not physical
(:meth:`_Session.fit_replacements`)."""
RIVALS = 2
"""More physical candidates fitted before a heat load is accepted (:meth:`_Session.fit_physical_rivals`)."""
TIE_R2 = 0.95
"""Exactly-null candidates whose linearised fit explains at least this fraction of what the best one explains are
tied with it: the score test cannot order them (:meth:`_Session.tied_with_shortlist`)."""
TIED = 3
"""At most this many tied candidates are fitted beyond the shortlist in a round."""


def _joint(a: Candidate, b: Candidate) -> Candidate:
    """Two candidates of one target fitted together (a linear law and its square, a probe): k is the sum; accepted,
    both are (its ``members``)."""
    return Candidate(a.kind, a.target, a.depends_on + b.depends_on, a.columns + b.columns, fn=a.fn,
                     vars=a.vars, element={**a.element, "probe": True, "members": [a, b]})


def _same_model(a: Candidate, b: Candidate, partners: dict[str, str]) -> bool:
    """``a`` and ``b`` (single-target candidates) are one model written two ways: the same kind, shape and variables
    on two parameters that enter the network only as their product (``partners``:
    :func:`.candidates.product_partners`)."""
    return (a.kind == b.kind and a.k == b.k and a.depends_on == b.depends_on and len(a.members) == len(b.members) == 1
            and a.element.get("shape") == b.element.get("shape") and partners.get(a.target) == b.target)


def _partners_now(net_x: Network, accepted: list[Candidate]) -> dict[str, str]:
    """:func:`.candidates.product_partners` of the current network ``net_x``, less the parameters an ``accepted``
    finding took (:meth:`_Session.same_model_fit`'s pairs)."""
    partners = product_partners(net_x)
    taken = {m.target for a in accepted for m in a.members}
    return {a: b for a, b in partners.items() if a not in taken and b not in taken}


def _beats(mae: float, other: float) -> bool:
    """A held-out MAE (K) better than ``other`` by more than ``MIN_GAIN`` and by more than round-off."""
    return mae * (1 + MIN_GAIN) < other and other - mae > ROUNDOFF_MAE_K


def _as_in(ext: Extended, c: Candidate) -> Candidate | None:
    """``c`` as laid out in the extension ``ext`` (its function outputs and columns there; a line-and-square pair
    member by member), or ``None`` when ``ext`` does not hold it."""
    if c.element.get("probe"):
        members = [_cand_in(ext, m.key) for m in c.members]
        return None if any(m is None for m in members) else _joint(*members)  # type: ignore[misc]
    return _cand_in(ext, c.key)


def _paths_of(data) -> list:
    """The file paths among data arguments (paths or :class:`Experiment` objects)."""
    items = data if isinstance(data, (list, tuple)) else [data]
    return [x if isinstance(x, (str, os.PathLike)) else getattr(x, "path", None) for x in items if x is not None]


def _load(net_or_path) -> tuple[Network, str | None, str]:
    """Network, its file path (or None) and its source text."""
    from ..lang import load

    if isinstance(net_or_path, Network):
        path = net_or_path.source_files[0] if net_or_path.source_files else None
        text = open(path, encoding="utf-8").read() if path and os.path.isfile(path) else ""
        return net_or_path, path, text
    path = os.fspath(net_or_path)
    net = load(path)
    return net, path, open(path, encoding="utf-8").read()


def _unused_columns(net: Network, experiments) -> list[tuple[str, str]]:
    """(input name, column) for numeric data columns present in every training file that the network does
    not read (not the time column, not an input, not a sensor)."""
    from ..data import read_table

    used = {i.column for i in net.inputs} | {s.column for s in net.sensors}
    # a column that reads a modelled node's temperature (``T_hx1``, ``hx1``) is a state, not a driver
    node_cols = {n.lower() for n in net.node_names} | {f"t_{n}".lower() for n in net.node_names}
    common: list[str] | None = None
    for e in experiments:
        try:
            tab = read_table(e.path)
        except Exception:  # noqa: BLE001 - the file was read before; a re-read problem just skips this
            return []
        cols = []
        for j, c in enumerate(tab.columns):
            if not c or c in used or c == e.time_column or c.lower() in node_cols:
                continue
            vals = tab.cells.get(j)
            try:
                arr = np.asarray(vals, dtype=float)
            except (TypeError, ValueError):
                continue
            if arr.size and np.all(np.isfinite(arr)) and np.ptp(arr) > 0:
                cols.append(c)
        common = cols if common is None else [c for c in common if c in cols]
    taken = set(net.input_names) | set(net.node_names) | set(net.param_names) | set(net.boundary_names)
    out = []
    for c in common or []:
        name = re.sub(r"[^A-Za-z0-9_]", "_", c)
        if not re.match(r"[A-Za-z_]", name):
            name = "c_" + name
        while name in taken:
            name += "_"
        taken.add(name)
        out.append((name, c))
    return out


MOVED_SHARE = 0.30
"""A free parameter the baseline fit moves by more than this share of its written value is reported."""


def _moved(net: Network, fitted: dict[tuple[str, int], float]) -> list[dict]:
    """The baseline's free constants that moved far from the values written in the network: more than
    :data:`MOVED_SHARE` of a non-temperature value, or onto a bound (a temperature only then). Each is
    ``{"param", "written", "fitted", "change", "at_bound", "words"}`` (SI; ``words`` a ``warning:`` line in the
    file's units) — the nominal model absorbing something there before any candidate is scored."""
    from .words import _fmt, _unit_of

    out = []
    for (name, i), v in fitted.items():
        if i:
            continue
        try:
            p = net.param(name)
        except KeyError:
            continue
        if not (p.free and p.is_constant) or p.value is None:
            continue
        v0 = float(p.value)
        temp = p.role == "temperature" or p.dim == {"K": 1}
        lo, hi = prior_bounds(p)
        span = (hi - lo) if lo is not None and hi is not None else None
        tol = 1e-6 * (abs(span) if span else max(abs(v0), 1.0))
        bound = ("lower" if lo is not None and v <= lo + tol else "upper" if hi is not None and v >= hi - tol else None)
        change = (v - v0) / abs(v0) if v0 else math.inf
        if not (bound or (not temp and abs(change) > MOVED_SHARE)):
            continue
        if temp:
            show = (lambda x: f"{x - 273.15:.4g} °C") if net.temperature_unit == "degC" else (lambda x: f"{x:.4g} K")
        else:
            unit = _unit_of(net, name)
            show = lambda x, u=unit: f"{_fmt(x)} {u}".rstrip()  # noqa: E731
        what = (f"{name} moved {100 * change:+.0f} % from {show(v0)} (written) to {show(v)}" if not temp
                else f"{name} moved from {show(v0)} (written) to {show(v)}")
        if bound and p.lower is None and p.upper is None:
            what += (f", onto the {bound} edge of the doctor's prior range (the written value ÷ or × "
                     f"{PRIOR_FACTOR:g})")
        elif bound:
            what += f", onto its {bound} bound"
        out.append({"param": name, "written": v0, "fitted": v, "change": change, "at_bound": bound,
                    "words": f"warning: the baseline fit: {what}: the nominal model absorbs something here"})
    return out


def sub_step_note(model, dts: list[float], which: str) -> str | None:
    """The report's line when RK4, the doctor's integrator, takes sub-steps at the files' sample periods ``dts`` (s)
    on ``model``'s network at its written values (:func:`~tnn_dsl.compiler.integrators.stable_substeps`), else
    ``None``. The diagnosis says it once for the written and the extended network instead of the rollouts'
    ``StepSizeWarning`` from every call site of every fit (:func:`~tnn_dsl.doctor.diagnosis.diagnose` silences
    those): a lag or a heat capacity the doctor tries often has a time constant under the sample period."""
    from ..compiler.integrators import stable_substeps

    tau, where = model.fastest_time_constant()
    need = {dt: stable_substeps("rk4", dt, tau) for dt in sorted(set(dts))}
    more = {dt: n for dt, n in need.items() if n > 1}
    if not more:
        return None
    steps = ", ".join(f"{n} sub-steps of {dt / n:.4g} s per {dt:g} s sample" for dt, n in more.items())
    return (f"integration: {which}'s fastest time constant is {tau:.4g} s (node {where}), under the stable step of "
            f"RK4: its simulations take {steps}")


class _Session:
    """The state one diagnosis builds up, and its stages (called in this order by ``diagnose``)."""

    def __init__(self, net_or_path, train, val, budget_s: float | None, backend: str,
                 progress: Callable[[str], None] | None, *, top: int, max_rounds: int, output: str | None,
                 kinds: tuple[str, ...] | None, mlp_check: bool, mlp_time: float, force: bool,
                 init: str = "estimate", burn_in: float | None = None, objective: str = "output-error",
                 threads: int | None = None, model_dir: str | None = None):
        from .likelihood import OBJECTIVES

        self.t_start = _time.monotonic()
        if objective not in OBJECTIVES:
            raise TnnError(Diagnostic(f"unknown objective {objective!r} for the doctor",
                                      hint="use --objective output-error (the default) or --objective ml"))
        self.objective = objective
        self.ml = None
        self.uncertainty: dict | None = None  # the final fit's standard errors and identifiability (uncertainty.py)
        init = "estimate" if init == "auto" else init
        if init not in DOCTOR_INIT_RULES:
            raise TnnError(Diagnostic(f"unknown initial-state rule {init!r} for the doctor",
                                      hint=f"use --init {' | '.join(DOCTOR_INIT_RULES)} (default estimate)"))
        self.init_rule, self.burn_in_s = init, burn_in
        self.notes: list[str] = []
        self.deadline = None if budget_s is None else self.t_start + float(budget_s)
        self.budget_s = budget_s
        self.budget_cut: str | None = None
        self.interrupted = False
        """Whether Ctrl-C (:mod:`.stopping`), not the budget, cut the work at :attr:`budget_cut`."""
        """Where the budget first stopped work (``"before any candidate was tested"``, ``"in round 2"``,
        ``"before round 2"``, ``"in the final fits"``): a verdict reached with less work than the method asks says
        so."""
        self.round_now = 0
        self.round_net: dict | None = None
        """The round's one small network (:meth:`fit_shortlist`): its engine, extension and columns (``small``), its
        candidates (``keys``) and the engine's start values (``start``); :meth:`small` hands out clones of it for
        later fits of the round whose candidates it holds."""
        self.say = progress or (lambda s: None)
        self.timings: dict[str, float] = {}
        self.moved_names: list[str] = []  # free constants the current fit moved far (``refit_from_written``)
        self.top, self.max_rounds, self.output, self.kinds = top, max_rounds, output, kinds
        self.mlp_check, self.mlp_time, self.backend = mlp_check, mlp_time, backend
        self.net, self.path, self.text = _load(net_or_path)
        ins = [self.path, *self.net.source_files, *_paths_of(train), *_paths_of(val)]
        if output:
            check_output(output, THN, inputs=ins, force=force)
        if model_dir:
            from ..fit import MODEL_DIR

            check_output(model_dir, MODEL_DIR, inputs=[*ins, output], force=force, option="--model")
        self.model_dir, self.force = model_dir, force
        self.mlp_model: Any = None  # the MLP check's trained MLP, where it chose the MLP
        if backend not in ("jax", "torch"):
            raise TnnError(Diagnostic(f"unknown backend {backend!r}", hint="use --backend jax or --backend torch"))
        self.train_arg, self.val_arg = train, val
        # torch's forward-mode derivatives (the Gauss–Newton Jacobians) keep their dual levels per thread and fail
        # in a worker thread: torch fits one candidate at a time
        self.threads = fit_threads(threads) if backend == "jax" else 1

    def lap(self, name: str, t0: float) -> None:
        self.timings[name] = round(_time.monotonic() - t0, 3)

    def spent(self, where: str | None = None) -> bool:
        """The budget is spent (and where it first cut the work is remembered: :attr:`budget_cut`, ``where`` when
        given, else the round).

        The budget's rule: no piece of work starts once it is spent, and the long ones (fits, the score test's
        chunks) look at it as they go, so a diagnosis ends within about one Jacobian, one score-test chunk or one
        final report of its deadline. (The score test and each round's first fit used to run regardless: the torch
        doctor, ``--budget 60``, ran 117 s, its score test of 51 s and first fit of 18 s both past the deadline.)"""
        stop = stop_requested()  # Ctrl-C (doctor.stopping): spent like a budget, whatever is left of it
        out = stop or (self.deadline is not None and _time.monotonic() > self.deadline)
        if out and self.budget_cut is None:
            self.budget_cut = where or (f"in round {self.round_now}" if self.round_now > 0 else
                                        "before any candidate was tested" if self.round_now == 0
                                        else "in the final fits")
            self.interrupted = stop
        return out

    def cut_by(self) -> str:
        """What cut the work, in words: ``"Ctrl-C"`` or ``"the budget (60 s)"``."""
        return "Ctrl-C" if self.interrupted else f"the budget ({self.budget_s:g} s)"

    # -- stage 0: data -----------------------------------------------------------------------------

    def read_data(self) -> None:
        """The experiments, the unused data columns (inputs of the extended network), the row masks."""
        from ..data import Experiment, read_data

        net = self.net

        def read(x, n):
            if x is None:
                return []
            if isinstance(x, Experiment):
                return [x]
            if isinstance(x, (list, tuple)) and x and all(isinstance(e, Experiment) for e in x):
                return list(x)
            return read_data(n, x)

        train_exps, val_exps = read(self.train_arg, net), read(self.val_arg, net)
        if not train_exps:
            raise TnnError(Diagnostic("no training data given", hint="pass at least one CSV file"))
        train_paths = list(dict.fromkeys(e.path for e in train_exps))  # a file split at gaps is read once
        val_paths = list(dict.fromkeys(e.path for e in val_exps))
        kinds = self.kinds
        unused = _unused_columns(net, train_exps + val_exps) if (kinds is None or "unused_column" in kinds) else []
        net_x = net
        if unused:
            net_x = net.model_copy(update={"inputs": list(net.inputs) + [
                Input(name=n, column=c, dim={}, unit=None) for n, c in unused]}, deep=True)
            train_exps = read_data(net_x, train_paths) if train_paths and os.path.isfile(train_paths[0]) else train_exps
            val_exps = read_data(net_x, val_paths) if val_paths and os.path.isfile(val_paths[0]) else val_exps
            if train_exps[0].inputs.shape[1] != len(net_x.inputs):  # Experiments given directly: cannot add
                unused, net_x = [], net
        self.train_exps, self.val_exps, self.unused, self.net_x = train_exps, val_exps, unused, net_x
        from ..fit.initial import burn_in_samples

        # a held-out file's burn-in (its initial state is estimated there, never scored); training files' initial
        # states are fitted with the parameters
        burn = tuple(burn_in_samples(e, self.burn_in_s) if self.init_rule == "estimate" else 0
                     for e in train_exps + val_exps)
        self.plan = _InitPlan(self.init_rule, burn)
        self.exps, self.train_mask, self.val_mask = _split_masks(train_exps, val_exps,
                                                                 burn=burn if val_exps else ())
        self.all_u = np.concatenate([e.inputs for e in self.exps], 0)
        self.train_rows = self.train_mask.any(1)
        self.varying = [n for j, n in enumerate(net.input_names) if np.ptp(self.all_u[self.train_rows, j]) > 0]
        self.extra = [n for n, _ in unused]

    def small(self, keys: list[str]) -> tuple[_Engine, Extended, list[int], dict[str, list[int]]]:
        """An engine over the original network plus just the candidates ``keys`` (values from the state):
        (engine, its Extended, free column indices, candidate key → its column indices). Where the round's small
        network (:attr:`round_net`) holds every one of ``keys``, a clone of its engine at its start values instead:
        the other candidates sit there at their null values, where the simulation is the smaller network's, and
        its programs are compiled already."""
        shared = self.round_net
        if shared is not None and set(keys) <= shared["keys"]:
            e = shared["small"][0].clone()
            e.params = {k: np.array(v, copy=True) for k, v in shared["start"].items()}
            return (e, *shared["small"][1:])
        ext_s = build_extended(self.net_x, self.varying, self.extra, kinds=self.kinds, only=set(keys))
        return _make_engine(ext_s, self.net_x, self.exps, self.train_mask, self.val_mask, self.backend, self.state,
                            self.ref, keys)

    # -- stage 1: the nominal model and its fit -------------------------------------------------------

    def fit_baseline(self) -> None:
        t0 = _time.monotonic()
        self.say("building candidates from the network ...")
        self.ext: Extended = build_extended(self.net_x, self.varying, self.extra, kinds=self.kinds)
        self.state = _State(self.plan)
        self.ref: dict = {}
        eng, ext0, free_idx, _ = self.small([])
        self.lap("compile", t0)
        t0 = _time.monotonic()
        if self.threads > 1 and self.backend == "jax":
            # the nominal fit's programs compiled (at the values so far: nothing is kept but the programs) while the
            # training files' initial states are fitted to their burn-in (issue 18) — on a clone, whose parameter
            # table and last simulation are its own: the fit here writes the initial states into the engine's table
            # while the clone simulates (a simulation remembered under values written after it ran would be handed
            # back for them)
            two_at_once(partial(eng.clone().warm, list(free_idx)), eng.fitted_start, self.threads)
        else:
            eng.fitted_start()
        n_x0 = sum(1 for j in free_idx if eng.cols[j].key.startswith(X0_PREFIX))
        self.say(f"fitting the nominal model ({len(free_idx) - n_x0} free parameters"
                 + (f", {n_x0} initial-state values" if n_x0 else "")
                 + f") on {int(self.train_rows.sum())} samples ...")
        info = eng.fit(free_idx, max_iter=30, deadline=self.deadline, tol=1e-6)
        if info["capped"] and self.spent():
            self.notes.append(f"{self.cut_by()} stopped the nominal model's fit after "
                              f"{info['iterations']} iterations, before it converged: the baseline below is not the "
                              "best the written model does, and no candidate was tested; "
                              + ("run it to its end" if self.interrupted else "run with a larger --budget (or none)"))
        self.state.harvest(eng, ext0, [])
        self.lap("nominal_fit", t0)
        self.eng, self.ext0 = eng, ext0
        self.initial_notes()
        if self.objective == "ml":
            from .likelihood import LikelihoodSelection

            t0 = _time.monotonic()
            self.ml = LikelihoodSelection(self.train_exps, self.val_exps, self.backend, self.burn_in_s, self.say)
            if not self.ml.start(self.net):
                raise TnnError(Diagnostic(f"network {self.net.name!r} has no finite likelihood on these data",
                                          hint="check its values and ranges, or use --objective output-error"))
            self.lap("nominal_ml_fit", t0)

    def initial_notes(self) -> None:
        """The initial-state rule in words, and a warning for each file that does not start at rest."""
        from ..fit.initial import FAR_FROM_STEADY_K

        eng, rule = self.eng, self.init_rule
        n_tr = len(self.train_exps)
        held = {e.name: b for i, (e, b) in enumerate(zip(self.exps, self.plan.burn)) if i >= n_tr and b}
        self.initial = {"rule": rule, "burn_in": held}
        if rule == "estimate":
            self.notes.append("initial states: fitted with the parameters for the training files"
                              + ("; estimated from the first " + ", ".join(f"{b} samples of {p}"
                                                                          for p, b in held.items())
                                 + " (not scored) for the held-out files" if held else ""))
        elif rule == "measured":
            self.notes.append("initial states: the steady state of the first inputs with the sensed nodes at their "
                              "first readings (--init measured)")
        else:
            self.notes.append("initial states: the steady state of the first inputs (--init steady)")
        step = sub_step_note(eng.model, [float(e.dt) for e in self.exps], "the network")
        if step:
            self.notes.append(step)
        for i, e in enumerate(self.exps):
            gap = eng.steady_gap(i)
            if not np.isfinite(gap).any() or np.nanmax(np.abs(gap)) <= FAR_FROM_STEADY_K:
                continue
            k = int(np.nanargmax(np.abs(gap)))
            what = (f"warning: {e.name} does not start at rest: at the steady state of its first inputs "
                    f"{eng.model.output_names[k]} would read {abs(gap[k]):.2f} K "
                    f"{'below' if gap[k] > 0 else 'above'} its first measurement")
            self.notes.append(what + ("; the doctor starts from the steady state as asked, so the start-up transient "
                                      "will be taken for a deficiency (use --init estimate)" if rule == "steady"
                                      else "; its initial state is estimated, not assumed"))

    # -- stage 2: residual analysis -------------------------------------------------------------------

    def analyse_residuals(self) -> None:
        t0 = _time.monotonic()
        eng, net = self.eng, self.net
        self.y_nom, x_nom = eng.simulate()
        self.e_nom = eng.y - self.y_nom
        model = eng.model
        self.out_names = list(model.output_names)
        e_val = np.where(eng.val_mask, self.e_nom, np.nan)
        self.vrows = vrows = eng.val_mask.any(1)
        self.t_all = np.concatenate([e.t for e in self.exps])
        variables = {n: self.all_u[vrows, j] for j, n in enumerate(self.net_x.input_names)
                     if np.ptp(self.all_u[vrows, j]) > 0}
        for j, n in enumerate(model.state_names):
            variables[f"T({n})" if n in net.node_names else n] = x_nom[vrows, j]
        variables["time"] = self.t_all[vrows]
        self.variables = variables
        self.res = res = R.summarise(e_val[vrows], self.out_names, variables)
        e_tr = np.where(eng.train_mask, self.e_nom, np.nan)
        self.base = {
            "val_mae": res.mae, "val_max": res.max,
            "train_mae": float(np.nanmean(np.abs(e_tr))), "train_max": float(np.nanmax(np.abs(e_tr))),
            "per_sensor": res.errors,
            "free_params": {f"{k}" + (f"[{i}]" if i else ""): v for (k, i), v in self.state.physical().items()},
        }
        self.sigma = float(np.mean(list(res.sigma.values()))) if res.sigma else 0.0
        self.base["moved"] = moved = _moved(self.net, self.state.physical())
        if self.ml is not None and self.ml.current is not None:
            from .likelihood import likelihood_summary

            self.base["likelihood"] = likelihood_summary(self.ml.current)
        self.notes += [m["words"] for m in moved]
        from .plausibility import network_scales

        self.scales = network_scales(self.net, self.exps)
        self.lap("residuals", t0)
        self.say(f"baseline held-out MAE {res.mae:.4g} K, max {res.max:.4g} K; residual "
                 + ("white" if all(w.get("white") for w in res.whiteness.values()) else "not white"))
        # the forward selection starts from here
        self.findings: list[Finding] = []
        self.acc_findings: list[Finding] = []  # the accepted ones, in order, with ...
        self.acc_fits: list[dict] = []  # ... their fits
        self.final_act: list[int] = []
        self.scores_out: list[dict] = []
        self.accepted: list[Candidate] = []
        self.round_fits: list[dict] = []
        self.promised: set[str] = set()  # curved terms a probe showed to pay: fitted next round whatever their score
        self.current_val = (res.mae, res.max, eng.sse(which="val"))
        self.final_eng, self.final_ext = eng, self.ext0
        self.with_struct = self.kinds is None or any(k in STRUCTURAL_KINDS for k in self.kinds)
        self.dt_min = min(float(e.dt) for e in self.exps)
        self.remaining = self.candidates_now()
        self.big = None

    # -- stages 3–5: forward selection ----------------------------------------------------------------

    def candidates_now(self) -> list[Candidate]:
        """The candidates of the next round: not accepted yet, and a curved shape (``v²``, ``v·w``) only where a linear
        dependence of its target on one of its variables has been accepted."""
        done = {a.key for a in self.accepted}
        struct = structural_candidates(self.net_x, self.kinds if self.kinds else None) if self.with_struct else []
        return [c for c in list(self.ext.candidates) + struct if c.key not in done
                and (not c.element.get("parents") or any(p in done for p in c.element["parents"]))]

    def selection_round(self, rnd: int) -> bool:
        """One round: score test, proper fits of the shortlist, the held-out decision. ``False``: stop."""
        self.round_now = rnd
        first = self.budget_cut is None
        if self.spent():
            if first:
                self.budget_cut = "before any candidate was tested" if rnd == 1 else f"before round {rnd}"
            self.say("budget spent; stopping the forward selection")
            return False
        # last round's fits and their networks are done with: their freed arrays and compiled programs go back
        # before the score test
        release_free_memory(collect=True)
        self.round_fits = []  # this round's exact fits, a later fit of the same model starts from theirs
        scored = self.score(rnd)
        release_free_memory()  # the score test's Jacobian blocks (hundreds of MB on 4 h of data) likewise
        if not scored:
            return False
        t0 = _time.monotonic()
        fits: list[dict] = []
        try:
            fits = self.fit_shortlist(scored)
            self.lap(f"fit_round{rnd}", t0)
            if not fits:
                return False
            _, xc = self.final_eng.simulate()  # where the current model's states go (once per round)
            current = {n: (float(np.nanmin(xc[:, j])), float(np.nanmax(xc[:, j])))
                       for j, n in enumerate(self.final_eng.model.state_names) if np.isfinite(xc[:, j]).any()}
            for f in fits:
                self.judge(f, current)
            # the shortlist's networks are fitted and judged: their programs go before the twins', sub-models' and
            # probes' networks compile theirs (issue 18: ~40 MB a network on the case study); the fit chosen compiles
            # its network again when it becomes the current model
            for eng in {id(f["eng"]): f["eng"] for f in fits}.values():
                if not getattr(eng, "round_shared", False):  # the round's shared network goes at the round's end
                    eng.release_programs()
            fits += self.fit_twins(fits, current)
            fits += self.fit_nested(fits, scored, current)
            fits += self.fit_replacements(fits, scored, current)
            e_base_tr = self.final_eng.residual().ravel()[self.final_eng.train_idx]
            for f in fits:
                f["S_train"], f["p_train"] = _train_lr_test(e_base_tr, f["e_all"].ravel()[f["eng"].train_idx],
                                                            f["cand"].k, len(scored))
            chosen = (self.ml_choose(fits, current) if self.ml is not None
                      else _choose(fits, self.current_val, self.e_base_val))
            if chosen is not None and self.ml is None:
                rivals = self.fit_physical_rivals(chosen, fits, scored, current)
                if rivals:
                    for f in rivals:
                        f["S_train"], f["p_train"] = _train_lr_test(e_base_tr, f["e_all"].ravel()[f["eng"].train_idx],
                                                                    f["cand"].k, len(scored))
                    fits += rivals
                    chosen = _choose(fits, self.current_val, self.e_base_val)
            if self.ml is None:
                chosen = self.curvature_look_ahead(chosen, fits, current)
        finally:
            self.end_round_net(fits)  # its shared network's programs go before the chosen one's compile
        self.record(fits, scored, chosen, rnd)
        self.round_fits = []  # their engines and compiled networks go with the round
        if chosen is None:
            self.say(f"round {rnd}: no candidate pays on held-out data")
            return False
        self.accept(chosen, rnd)
        return True

    def score(self, rnd: int) -> list[dict]:
        """The score test of every remaining candidate at the current fit (the big extended network)."""
        t0 = _time.monotonic()
        acc_keys = self.acc_keys()
        if self.big is None:
            self.say(f"compiling the extended network ({len(self.ext.candidates)} candidates at their null value) ...")
            self.big = _make_engine(self.ext, self.net_x, self.exps, self.train_mask, self.val_mask, self.backend,
                                    self.state, self.ref, [c.key for c in self.ext.candidates], with_candidates=True)
        else:
            self.big[0].params = _params_from_state(self.big[0], self.big[1], self.state, acc_keys)
        b_eng, b_ext, b_free, b_cols = self.big
        self.say(f"round {rnd}: score test over {len(self.remaining)} candidates ...")
        scored = _score_forced(self.final_eng, b_eng, self.remaining, b_cols, [_cand_in(b_ext, k) for k in acc_keys],
                               stop=lambda: self.spent(f"in round {rnd}'s score test"), threads=self.threads)
        if scored == []:  # the budget stopped it between two chunks
            b_eng.release_programs()
            self.say(f"budget spent during round {rnd}'s score test; stopping the forward selection")
            return []
        if scored is None:
            self.remaining = [r for r in self.remaining if r.kind not in STRUCTURAL_KINDS]
            active_base = list(b_free) + [j for k in acc_keys for j in b_cols.get(k, [])]
            scored = _score(b_eng, self.remaining, active_base, b_cols, self.sigma)
        # the extended network's programs (~35 MB on the case study) go until the next round's score test compiles
        # them again: the round's candidate fits stand on what is left (issue 18)
        b_eng.release_programs()
        self.lap(f"score_round{rnd}", t0)
        if rnd == 1:
            self.scores_out = [dict(s["public"]) for s in scored]
        return scored

    def acc_keys(self) -> list[str]:
        """Keys of the accepted candidates held by the extended network (structural ones live in ``net_x``)."""
        return [c.key for c in self.accepted if c.kind not in STRUCTURAL_KINDS]

    def fit_shortlist(self, scored: list[dict]) -> list[dict]:
        """Proper fits of the best distinct candidates: ``FIT_ITER_FIRST`` iterations each on ONE small network
        holding all of them (each exactly null at zero, fitted with only its own columns moving, so the
        compiled simulation and Jacobian are shared), then successive halving."""
        self.e_base_val = e_base_val = self.final_eng.residual().ravel()[self.final_eng.val_idx]
        self.moved_names = [m["param"] for m in _moved(self.net, self.state.physical())]
        # a lag or a mass the linearised fit wants negative is not a physical candidate: it does not take a place
        neg = [s_ for s_ in scored if s_["cand"].kind in STRUCTURAL_KINDS
               and not (len(s_["delta"]) and float(s_["delta"][0]) > 0)]
        ml_neg: list[dict] = []
        if self.objective == "ml":  # the likelihood may still want them: fitted from their smallest value
            ml_neg, neg = neg, []
        # a new conductance or radiating area starts at its bound 0: when its linearised fit wants it negative,
        # the one-sided score says any allowed value makes the fit worse (both objectives)
        neg += [s_ for s_ in scored if s_["cand"].kind in BOUNDED_AT_ZERO_KINDS
                and len(s_["delta"]) and float(s_["delta"][0]) < 0]
        if neg:
            self.say(f"  {len(neg)} candidate(s) (lag, mass, link or radiation) whose linearised fit wants a negative"
                     " value: not fitted")
        short = []
        for s_ in _shortlist([s_ for s_ in scored if not any(s_ is t for t in neg)], self.top):
            if s_["r2"] < MIN_R2 and short:
                continue  # the linearised fit explains too little of the residual to pay
            short.append(s_)
        short += self.tied_with_shortlist(scored, short, neg)
        for s_ in scored:  # a square whose probe paid with the linear law accepted last round (curvature_look_ahead)
            if s_["cand"].key in self.promised and not any(s_ is t for t in short):
                short.append(s_)
        self.promised = set()
        if short and short[0]["r2"] < MIN_R2:
            self.say(f"  {short[0]['cand'].describe()}: the score test explains only {100 * short[0]['r2']:.2g} % of "
                     "the residual; not fitted")
            return []
        if self.spent(f"in round {self.round_now}, before its candidates were fitted"):
            self.say("budget spent after the score test; its ranking stands, no candidate is fitted")
            return []
        acc_keys = self.acc_keys()
        sh_keys = [s_["cand"].key for s_ in short if s_["cand"].kind not in STRUCTURAL_KINDS]
        ahead = [k for k in self.foreseen([s_ for s_ in short if s_["cand"].kind not in STRUCTURAL_KINDS], scored)
                 if k not in sh_keys and k not in acc_keys]
        t_c = _time.monotonic()
        e_s, x_s, f_s, c_s = self.small(acc_keys + sh_keys + ahead)
        t_c = _time.monotonic() - t_c
        start_params = {k: np.array(v, copy=True) for k, v in e_s.params.items()}
        if ahead:  # held to the round's end: the sub-models and probes fitted later run on it (:meth:`small`)
            e_s.round_shared = True
            self.round_net = {"small": (e_s, x_s, f_s, c_s), "keys": set(acc_keys + sh_keys + ahead),
                              "start": start_params}
        structural = [s_ for s_ in short if s_["cand"].kind in STRUCTURAL_KINDS]
        exact = [s_ for s_ in short if s_["cand"].kind not in STRUCTURAL_KINDS]

        if self.threads > 1 and len(exact) > 1:
            # the round's small network compiled here, alone, and the compilation's scratch memory handed back
            # before its fits start side by side (:meth:`_Engine.warm`)
            t_w = _time.monotonic()
            c0: Candidate = exact[0]["cand"]
            e_s.warm(list(f_s) + [j for k in acc_keys + [c0.key] for j in c_s.get(k, [])], self.threads)
            release_free_memory()
            t_c += _time.monotonic() - t_w

        def fit_structural(say) -> list[dict | None]:
            """The structural candidates one after the other (each compiles its own network and may update the
            learned inputs' reference run that the next one reads)."""
            out: list[dict | None] = []
            for s_ in structural:
                if self.spent():
                    break
                c: Candidate = s_["cand"]
                say(f"  fitting {c.describe()} (k={c.k}) ...")
                # a lag or mass whose linearised fit wants a negative value starts at its smallest (lag, mass) or at
                # the score test's lag (behind a source)
                small = [1.0 if c.kind == "source_mass" else 1e-300] if any(s_ is t for t in ml_neg) else None
                out.append(_fit_structural(c, s_, self.net_x, self.varying, self.extra, self.kinds, acc_keys,
                                           self.exps, self.train_mask, self.val_mask, self.backend, self.state,
                                           self.ref, self.dt_min, self.deadline, e_base_val, say, delta=small))
            return out

        def fit_one(i: int, s_: dict):
            def run(say) -> dict | None:
                if self.spent():
                    return None
                say(f"  fitting {s_['cand'].describe()} (k={s_['cand'].k}) ...")
                return self.fit_exact(s_, (e_s.clone(), x_s, f_s, c_s), start_params, acc_keys, FIT_ITER_FIRST,
                                      f", network compiled in {t_c:.1f} s" if i == 0 else "", say=say)
            return run

        done = self.side_by_side(([fit_structural] if structural else [])
                                 + [fit_one(i, s_) for i, s_ in enumerate(exact)])
        by_id = {id(s_): f for s_, f in zip(exact, done[1:] if structural else done)}
        struct_fits = iter(done[0] if structural else [])
        fits: list[dict] = []
        for s_ in short:  # in the shortlist's order
            f = next(struct_fits, None) if s_["cand"].kind in STRUCTURAL_KINDS else by_id.get(id(s_))
            if f is not None:
                fits.append(f)
        self.continue_fits(fits, x_s)
        return fits

    def foreseen(self, short: list[dict], scored: list[dict]) -> list[str]:
        """Keys of the candidates the round may fit after its shortlist ``short`` (exactly-null entries), each of
        which would otherwise compile a network of its own: the one-parameter sub-model of a dependence
        (:meth:`fit_nested`: a wrong constant, a constant heat load) and the square of a linear dependence on inputs
        (:meth:`curvature_look_ahead`'s probes) where its function stays input-only. They join the round's small
        network at their null values (a sub-model's column is its dependence's own intercept, a square one more
        input-only column), so those fits run on the programs the shortlist compiled: on the case study's first
        round a sub-model and a probe had compiled two networks more, about 2 s each with their held-out starts
        (issue 18)."""
        done = {a.key for a in self.accepted}
        square = {c.element["parents"][0]: c for c in self.ext.candidates
                  if c.element.get("shape") == "quadratic" and c.key not in done}
        groups = [{f"Q[{t.name}]" if t.kind == "heat_load" else t.name for t in fn.targets} for fn in self.net.learned]

        def function_of(c: Candidate) -> set[str]:
            """The targets sharing ``c``'s learned function in the network (a user's ``learn`` clause joins its own)."""
            out = {m.target for m in c.members}
            return out.union(*[g for g in groups if g & out])

        # a square goes in only where its function stays input-only: joined with a dependence on a temperature it
        # makes that function a polynomial in the temperature, evaluated inside the time loop (the case study's
        # R_base_hs on I² beside R_base_hs on T(hs): poly(I, hs; degree = 2), round 2's simulations 30 → 46 ms)
        on_states: set[str] = set()
        for c in [s_["cand"] for s_ in short] + list(self.accepted):
            if any(kind != "input" for kind, _ in c.vars):
                on_states |= function_of(c)
        keys: list[str] = []
        for s_ in short:
            c: Candidate = s_["cand"]
            if (c.key in square and not c.element.get("members") and all(kind == "input" for kind, _ in c.vars)
                    and not function_of(c) & on_states):
                keys.append(square[c.key].key)
            kind = {"param_dependence": "wrong_constant", "heat_load": "heat_load"}.get(c.kind)
            if kind is not None and c.depends_on and c.k >= 2:
                sub = next((t["cand"] for t in scored if t["cand"].kind == kind and t["cand"].target == c.target
                            and not t["cand"].depends_on and t["cand"].k == 1), None)
                if sub is not None:
                    keys.append(sub.key)
        return list(dict.fromkeys(keys))

    def end_round_net(self, fits: list[dict]) -> None:
        """The round's shared small network (:attr:`round_net`) is done with: its programs go, the clones' that the
        round's fits ``fits`` hold too (as every other network's went after its fits)."""
        if self.round_net is not None:
            self.round_net["small"][0].release_programs()
            self.round_net = None
        for f in fits:
            if getattr(f.get("eng"), "round_shared", False):
                f["eng"].release_programs()

    def tied_with_shortlist(self, scored: list[dict], short: list[dict], left_out: list[dict]) -> list[dict]:
        """Exactly-null candidates the shortlist left out whose linearised fit explains nearly as much as the best
        one (``r2 ≥ TIE_R2 · best``; at most ``TIED``, distinct from the shortlisted and from each other). The score
        test is a linearisation at the current fit, and when the baseline's free parameters have absorbed part of
        the effect, several placements explain the residual equally well to first order: only proper fits tell them
        apart. They share the round's one small network, so each costs a few Gauss–Newton iterations. The case
        study's load at hx2 growing with I² (``pe.resistance`` having moved +107 % to absorb it) was ranked fifth
        with 96 % of the best score; the three fitted before it were resistances along the heat path depending on
        I, and the load was never fitted (suite case ``casestudy/quadratic_load``)."""
        if not short or short[0]["r2"] < MIN_R2:
            return []
        best = max(s_["r2"] for s_ in short)
        taken = list(short)
        out: list[dict] = []
        for s_ in scored:
            if len(out) >= TIED:
                break
            c: Candidate = s_["cand"]
            if (s_["r2"] < TIE_R2 * best or c.kind in STRUCTURAL_KINDS or any(s_ is t for t in taken)
                    or any(s_ is t for t in left_out) or any(s_ is u for t in taken for u in t.get("same", []))):
                continue
            if any(same_correction(t, s_) for t in taken):
                continue  # an exact twin of one already fitted: the same linearised correction
            out.append(s_)
            taken.append(s_)
        if out:
            self.say(f"  {len(out)} more candidate(s) tied with the shortlist by the score test: fitted too")
        return out

    def side_by_side(self, jobs: list[Callable[[Callable[[str], None]], object]],
                     first: list[int] | None = None) -> list:
        """:func:`.threads.side_by_side` on this session's threads and progress (``first``: the start order)."""
        return side_by_side(jobs, self.threads, self.say, first)

    def fit_exact(self, s_: dict, small, start_params: dict, acc_keys: list[str], max_iter: int,
                  note: str = "", say: Callable[[str], None] | None = None, extra: Candidate | None = None) -> dict:
        """One exactly-null candidate fitted on the round's small network ``small`` (engine, extension, free and
        candidate columns) with only its own columns and the free ones moving, from ``start_params`` and the score
        test's Gauss–Newton step (kept only if it helps). ``extra``: a second candidate whose columns move too
        (from zero); the result's candidate is then the pair (:func:`_joint`)."""
        e_s, x_s, f_s, c_s = small
        c: Candidate = s_["cand"]
        parts = [c] + ([extra] if extra else [])
        e_s.params = {k: np.array(v, copy=True) for k, v in start_params.items()}
        act = list(f_s) + [j for k in acc_keys + [p.key for p in parts] for j in c_s.get(k, [])]
        init = np.zeros(len(act))
        for d, j in zip(s_["delta"], c_s.get(c.key, [])):
            init[act.index(j)] = d
        tell = say or self.say
        same = self.same_model_fit(parts, e_s, c_s)
        t_f = _time.monotonic()
        if same is not None:  # the same model at its twin's solution (verified): that fit, written on these columns
            src, e_s.params, sse = same
            info = {"sse": sse, "capped": bool(src.get("more"))}
            prod = sorted({f"{b.target}·{a.target}" for a, b in zip(parts, src["parts"])})
            tell(f"    the same model as {src['cand'].describe()} ({', '.join(prod)} enter only as one product): its "
                 f"fit, training SSE {sse:.6g} against {src['train_sse']:.6g} K²")
        else:
            info = e_s.fit(act, max_iter=max_iter, init_delta=init, deadline=self.deadline, tol=1e-4, stall=True)
            tell(f"    fitted in {_time.monotonic() - t_f:.1f} s ({info['iterations']} iterations, "
                 f"{info['jacobians']} Jacobians{note})")
            info = refit_from_written(e_s, act, info, start_params, self.moved_names, max_iter, self.deadline, tell,
                                      learned=[fn.name for fn in self.net.learned])
        f = _fit_result(c if extra is None else _joint(c, extra), s_, e_s, x_s, self.e_base_val)
        f.update(act=act, train_sse=info["sse"], more=bool(info["capped"]), parts=parts,
                 cand_cols={p.key: list(c_s.get(p.key, [])) for p in parts})
        if info.get("start") == "written":
            f["start"] = "written"
        self.round_fits.append(f)
        return f

    def same_model_fit(self, parts: list[Candidate], e_s, c_s: dict[str, list[int]]
                         ) -> tuple[dict, dict, float] | None:
        """The fit of ``parts`` (a candidate, or a line and its square) on engine ``e_s`` taken from this round's fit
        of the same model written on the partner parameters (:func:`_same_model`: a fluid's ``cp`` for its ``mdot``):
        that fit's values, the candidate columns copied in order. Taken only when they reproduce that fit's training
        SSE to 1e-9 (one simulation): then they are that fit, and fitting again would retrace it. On the case study's
        second round ``f1.cp`` and ``f1.mdot`` depending on I were each fitted from scratch, as were their
        sub-models and their probes, every pair along the same path to the same values (about 13 s of a 126 s
        diagnosis). Returns ``(that fit, the parameters, their training SSE K²)`` or None."""
        partners = _partners_now(self.net_x, self.accepted)
        if not partners:
            return None
        for src in self.round_fits:
            sp = src.get("parts") or []
            if (len(sp) != len(parts) or not all(_same_model(a, b, partners) for a, b in zip(sp, parts))
                    or not math.isfinite(src["train_sse"])):
                continue
            s_eng, s_par = src["eng"], src["params"]
            s_cols = [s_eng.cols[j] for a in sp for j in src["cand_cols"][a.key]]
            d_cols = [e_s.cols[j] for a in parts for j in c_s.get(a.key, [])]
            if len(s_cols) != len(d_cols):
                continue
            mine = {col.key for col in s_cols} | {col.key for col in d_cols}
            p = {k: np.array(v, dtype=float, copy=True) for k, v in e_s.params.items()}
            for k, v in s_par.items():  # free parameters, initial states, accepted findings
                if k in p and k not in mine and np.shape(v) == p[k].shape:
                    p[k] = np.array(v, dtype=float, copy=True)
            for cs, cd in zip(s_cols, d_cols):
                flat = p[cd.key].reshape(-1)
                flat[cd.index] = float(np.asarray(s_par[cs.key]).reshape(-1)[cs.index])
                p[cd.key] = flat.reshape(p[cd.key].shape)
            sse = e_s._train_sse(p)[0]
            # to 1e-9, or round-off where the fit is exact (residuals of 1e-10 K)
            if abs(sse - src["train_sse"]) <= 1e-9 * src["train_sse"] + 1e-20 * e_s.train_idx.size:
                return src, p, sse
        return None

    def fit_apart(self, jobs: list[Callable[[Callable[[str], None], "_Engine"], object]], small,
                  parts: list[list[Candidate]]) -> list:
        """Fits on one small network (``small``: :meth:`small`'s engine, extension, columns), one job per entry of
        ``parts`` (the candidates each fits), each job called with its progress function and its engine; results
        in job order. With more than one thread they run side by side, each on its own clone of the engine (the
        compiled programs shared), their progress lines said in order — unless two of them fit one model written
        two ways (:func:`_same_model`): then one after the other, so that the second takes the first's fit as
        :meth:`same_model_fit` does. One thread: one after the other on the engine itself, as before. Either way
        each fit starts from the same values and runs the same arithmetic, so the results do not depend on the
        threads. The engines' programs are let go at the end (fitted and judged: the next phase compiles its own).
        The round's sub-models, twins, replacements and probes had run one at a time on 2 cores (issue 18)."""
        partners = _partners_now(self.net_x, self.accepted) if self.threads > 1 and len(jobs) > 1 else {}
        alike = any(len(a) == len(b) and all(_same_model(x, y, partners) or _same_model(y, x, partners)
                                             for x, y in zip(a, b))
                    for i, a in enumerate(parts) for b in parts[i + 1:])
        apart = self.threads > 1 and len(jobs) > 1 and not alike
        if apart and not self.spent():  # (spent: every job returns at once, nothing to compile)
            # the network compiled alone first, its scratch memory handed back, as in fit_shortlist: two probes
            # compiling and taking their first Jacobians at once were the case study's peak (+15 MB, issue 18)
            acc_keys = self.acc_keys()
            small[0].warm(list(small[2]) + [j for k in acc_keys + [c.key for c in parts[0]]
                                            for j in small[3].get(k, [])], self.threads)
            release_free_memory()
        engines = [small[0].clone() if apart else small[0] for _ in jobs]
        bound = [lambda say, job=job, eng=eng: job(say, eng) for job, eng in zip(jobs, engines)]
        done = self.side_by_side(bound) if apart else [job(self.say) for job in bound]
        for eng in {id(e): e for e in engines}.values():
            if not getattr(eng, "round_shared", False):  # the round's shared network goes at the round's end
                eng.release_programs()
        return done

    def fit_extra(self, todo: list[dict], why: str, current: dict[str, tuple[float, float]]) -> list[dict]:
        """Exactly-null candidates (score-test entries) the shortlist left out, fitted to convergence on one small
        network (side by side where threads allow: :meth:`fit_apart`) and judged; ``why`` ends the progress line
        ("the twin of …")."""
        if not todo or self.spent():
            return []
        acc_keys = self.acc_keys()
        small = self.small(acc_keys + [t["cand"].key for t in todo])
        start = {k: np.array(v, copy=True) for k, v in small[0].params.items()}

        def fit_one(t: dict):
            def run(say: Callable[[str], None], eng: _Engine) -> dict | None:
                if self.spent():
                    return None
                say(f"  fitting {t['cand'].describe()} (k={t['cand'].k}), {why} ...")
                f = self.fit_exact(t, (eng, *small[1:]), start, acc_keys, FIT_ITER, say=say)
                self.judge(f, current)
                return f
            return run

        done = self.fit_apart([fit_one(t) for t in todo], small, [[t["cand"]] for t in todo])
        return [f for f in done if f is not None]

    def fit_twins(self, fits: list[dict], current: dict[str, tuple[float, float]]) -> list[dict]:
        """A shortlisted candidate stands for its exact twins (the same linearised correction, ``same`` of
        :func:`_shortlist`); when its own fit is not physical or diverged, up to two of its twins are fitted in its
        place, to convergence. Twins agree only at the null point: a pump column changing a heat exchanger's
        ``f2.mdot`` (and ``f2.cp``, the same product ṁ·c_p) drove the Peltier's cold side to 661 °C, while the
        planted ``f2.UA`` was never fitted (suite case ``casestudy/column_dependence``). The same holds for a fit
        that is physical but does not pay on held-out data: ``f2.mdot`` depending on the pump column, the best score
        of its round, made the held-out MAE worse (0.079 → 0.093 K) while its twin ``f2.UA`` is the planted cause.
        A fit that does not pay stands aside for its twins only when the score test ranked it with the best (its
        linearised fit explaining ``TIE_R2`` of the best's); at most ``REPLACEMENTS`` such twins a round (on the 4 h
        case study a second round where nothing pays fitted every twin of every fit: a minute more for nothing).

        The round's leading fit (physical, paying, the best held-out MAE of the round) stands aside for nobody, but
        its equally physical twins (the same placement; the shortlist already keeps the more physical of unequal
        ones) are fitted beside it, up to two: the score test gives them the same statistic and round-off ordered
        them. On the case study's pump column ``f2.UA``, ``f2.mdot`` and ``f2.cp`` score 35.672181 each; when
        ``f2.mdot`` came first it paid (÷1.47) and was accepted, while the planted ``f2.UA`` pays ÷2.82."""
        mae0 = self.current_val[0]
        bad = [t for f in fits if f.get("physical") in ("non-physical", "diverged") or not math.isfinite(f["val_mae"])
               for t in f["score"].get("same", [])[:2] if t["cand"].kind not in STRUCTURAL_KINDS]
        r2_best = max((float(f["score"].get("r2", 0.0)) for f in fits), default=0.0)
        idle = [t for f in fits if f.get("physical") not in ("non-physical", "diverged") and math.isfinite(f["val_mae"])
                and f["val_mae"] > (1 - MIN_GAIN) * mae0 and float(f["score"].get("r2", 0.0)) >= TIE_R2 * r2_best
                for t in f["score"].get("same", [])[:2] if t["cand"].kind not in STRUCTURAL_KINDS][:REPLACEMENTS]
        paying = [f for f in fits if f.get("physical") not in ("non-physical", "diverged")
                  and math.isfinite(f["val_mae"]) and f["val_mae"] <= (1 - MIN_GAIN) * mae0]
        lead = min(paying, key=lambda f: f["val_mae"], default=None)
        equal = ([t for t in lead["score"].get("same", []) if t["cand"].kind not in STRUCTURAL_KINDS
                  and t["place"] <= lead["score"]["place"]][:2] if lead is not None else [])
        todo = bad + idle
        todo += [t for t in equal if not any(t is u for u in todo)]
        return self.fit_extra(todo, "an exact twin of a fit the score test cannot tell it from", current)

    def fit_replacements(self, fits: list[dict], scored: list[dict], current: dict[str, tuple[float, float]]
                         ) -> list[dict]:
        """A shortlisted candidate whose fit is not physical or diverged gives its place to the next-best one the
        shortlist left out (at most ``REPLACEMENTS`` a round): for a structural candidate (a thermal mass, a lag, a
        capacity behind a source) the next of its kind, for an exactly-null one the next exactly-null candidate by
        score. A mass on the link hx1–base fitted to a node at −28 °C said nothing about the planted mass on hp–hx2
        ranked a few places lower (suite case ``casestudy/thermal_mass``); two heat-pipe resistances depending
        linearly on the current crossed zero and diverged while the planted load at hx2 growing with I², ranked
        fourth, was never fitted (``casestudy/quadratic_load``)."""
        bad = [f for f in fits if f.get("physical") in ("non-physical", "diverged") or not math.isfinite(f["val_mae"])]
        if not bad or self.spent():
            return []
        fitted = {f["cand"].key for f in fits} | {t["cand"].key for f in fits for t in f["score"].get("same", [])}
        todo: list[dict] = []
        for f in bad:
            structural = f["cand"].kind in STRUCTURAL_KINDS
            nxt = next((s_ for s_ in scored if s_["cand"].key not in fitted and not any(s_ is t for t in todo)
                        and ((s_["cand"].kind == f["cand"].kind) if structural
                             else s_["cand"].kind not in STRUCTURAL_KINDS)
                        and not (s_["cand"].kind in STRUCTURAL_KINDS + BOUNDED_AT_ZERO_KINDS and len(s_["delta"])
                                 and (float(s_["delta"][0]) <= 0 if s_["cand"].kind in STRUCTURAL_KINDS
                                      else float(s_["delta"][0]) < 0))), None)
            if nxt is not None:
                todo.append(nxt)
        todo = todo[:REPLACEMENTS]
        acc_keys = self.acc_keys()
        exact = [s_ for s_ in todo if s_["cand"].kind not in STRUCTURAL_KINDS]
        small = self.small(acc_keys + [s_["cand"].key for s_ in exact]) if exact else None
        start = {k: np.array(v, copy=True) for k, v in small[0].params.items()} if small else {}
        out = []
        for s_ in todo:
            if self.spent():
                break
            c: Candidate = s_["cand"]
            self.say(f"  fitting {c.describe()} (k={c.k}) in place of a fit that is not physical or diverged ...")
            if c.kind in STRUCTURAL_KINDS:
                f = _fit_structural(c, s_, self.net_x, self.varying, self.extra, self.kinds, acc_keys, self.exps,
                                    self.train_mask, self.val_mask, self.backend, self.state, self.ref, self.dt_min,
                                    self.deadline, self.e_base_val, self.say)
            else:
                f = self.fit_exact(s_, small, start, acc_keys, FIT_ITER)
            if f is not None:
                self.judge(f, current)
                out.append(f)
                if c.kind in STRUCTURAL_KINDS:
                    f["eng"].release_programs()
        if small is not None and not getattr(small[0], "round_shared", False):
            small[0].release_programs()  # fitted and judged: their networks' programs go
        return out

    def curvature_look_ahead(self, chosen: dict | None, fits: list[dict], current: dict[str, tuple[float, float]]
                             ) -> dict | None:
        """A linear law is the first step to a curved one, and a load growing with the square of an input is
        answered in the first round by the line through it, which may lose on held-out data to a constant that
        happens to fit the held-out range (a TCLab-like board's ``0.6 W·Q1²`` at h2: ``Q_src_h2`` linear in Q1,
        1.01 K, lost to heater 2's gain ``a2``, 0.78 K) or not pay at all (the case study's ``1 W/A²·I²`` at hx2:
        the line in I, 0.134 K against 0.093 K before). The two best fitted linear dependences with a square term
        ``v²`` in their function, v an input (a temperature's curvature is radiation's, a candidate of its own), are
        fitted together with it (a probe). When the best probe pays against the current
        model with its extra parameter and beats the chosen candidate by more than ``MIN_GAIN`` on held-out data:
        if its line pays alone, the line is accepted and the square is fitted next round whatever its score rank
        (``promised``: at the line's fit the score test may rank it low, the line having absorbed what it can of the
        curve); if not, the pair is accepted together (one finding, the line and its square). Either way the probe
        must divide the held-out MAE of the chosen candidate (or of the current model) by ``CONFIRM_RATIO``: a curve in
        one input can stand in for many things, so it only overrides the decision when it is the dominant effect
        (on M1 a heat exchanger's UA in u1 and u1², 0.0059 → 0.0052 K, was compensating for the heat pipe's own
        curvature in u1)."""
        done = {a.key for a in self.accepted}
        square = {c.element["parents"][0]: c for c in self.ext.candidates
                  if c.element.get("shape") == "quadratic" and c.key not in done}
        mae0 = self.current_val[0]
        lines = sorted([f for f in fits if f["cand"].key in square and not f["cand"].element.get("members")
                        and all(kind == "input" for kind, _ in f["cand"].vars) and unphysical_reason(f) is None],
                       key=lambda f: f["val_mae"])[:2]
        if not lines or self.spent():
            return chosen
        acc_keys = self.acc_keys()
        small = self.small(acc_keys + [k for f in lines for k in (f["cand"].key, square[f["cand"].key].key)])
        start = {k: np.array(v, copy=True) for k, v in small[0].params.items()}

        def probe_of(f: dict):
            def run(say: Callable[[str], None], eng: _Engine) -> dict | None:
                if self.spent():
                    return None
                sq = square[f["cand"].key]
                say(f"  fitting {f['cand'].describe()} with its curvature {', '.join(sq.depends_on)} (a probe) ...")
                probe = self.fit_exact(f["score"], (eng, *small[1:]), start, acc_keys, FIT_ITER, say=say, extra=sq)
                self.judge(probe, current)
                return probe
            return run

        # the probes fitted (side by side where threads allow) and judged; their network's programs let go
        probes = self.fit_apart([probe_of(f) for f in lines], small,
                                [[f["cand"], square[f["cand"].key]] for f in lines])
        line, best_probe = None, None
        for f, probe in zip(lines, probes):
            if probe is None:
                break
            f["probe"] = {"with": square[f["cand"].key].depends_on, "val_mae": probe["val_mae"]}
            ref = chosen["val_mae"] if chosen is not None else mae0
            if (refusal(probe, mae0) is None and _beats(probe["val_mae"], ref)
                    and probe["val_mae"] * CONFIRM_RATIO <= ref
                    and (best_probe is None or probe["val_mae"] < best_probe["val_mae"])):
                line, best_probe = f, probe
        if line is None or best_probe is None:
            return chosen
        if refusal(line, mae0) is None:  # the line pays alone: it first, its square next round
            pick = line
            self.promised = {square[line["cand"].key].key}
        else:  # only the pair pays: accepted together
            pick = best_probe
            best_probe["S_train"], best_probe["p_train"] = line.get("S_train"), line.get("p_train")
            fits.append(best_probe)
        self.say(f"  {line['cand'].describe()} with {', '.join(line['probe']['with'])}: held-out MAE "
                 f"{best_probe['val_mae']:.4g} K" + (f" against {chosen['val_mae']:.4g} K of "
                                                    f"{chosen['cand'].describe()}" if chosen is not None else "")
                 + ("" if pick is line else "; the line alone does not pay: the two are accepted together"))
        if chosen is not None and chosen is not pick:
            chosen["reason"] = (f"explains less than {line['cand'].describe()} with its curvature "
                                f"({', '.join(line['probe']['with'])}: held-out MAE {best_probe['val_mae']:.3g} K)")
        pick.pop("reason", None)
        return pick

    def fit_physical_rivals(self, chosen: dict, fits: list[dict], scored: list[dict],
                            current: dict[str, tuple[float, float]]) -> list[dict]:
        """Before a heat load at a node is accepted, the best-scoring candidates of a more physical placement with no
        more parameters (a sensor offset, a wrong constant, a missing link; at most ``RIVALS``, explaining at least
        90 % of what the heat load's linearised fit explains) are fitted to convergence if the shortlist left them
        out, so the compensation guard can weigh them: a constant heat load of 23 W at the heat sink stood in for a
        0.3 K offset of the only sensor, ranked 31st by the score test (suite case ``casestudy/sensor_offset``)."""
        c: Candidate = chosen["cand"]
        if _place(c) < 3 or self.spent():
            return []
        fitted = {f["cand"].key for f in fits}
        r2 = float(chosen["score"]["r2"]) if "r2" in chosen.get("score", {}) else 0.0
        todo = [s_ for s_ in scored if s_["cand"].kind not in STRUCTURAL_KINDS and s_["cand"].key not in fitted
                and s_["place"] < 3 and s_["k"] <= c.k and s_["r2"] >= 0.9 * r2
                and not (s_["cand"].kind in BOUNDED_AT_ZERO_KINDS and len(s_["delta"]) and float(s_["delta"][0]) < 0)
                ][:RIVALS]
        return self.fit_extra(todo, f"a more physical rival of {c.describe()}", current)

    def fit_nested(self, fits: list[dict], scored: list[dict], current: dict[str, tuple[float, float]]) -> list[dict]:
        """The one-parameter sub-model of the best fits, fitted to convergence when the shortlist left it out: a
        parameter depending on a variable contains the parameter being wrong (``wrong_constant``), a heat load
        depending on a variable contains the constant one. The compensation guard of :func:`_choose` can only
        prefer the smaller model if it was fitted; its score test ranks it low when the planted change is large
        (the linearisation at the written value is poor: a building's ``Ria`` a third of its written value was
        answered as ``Ria`` depending on ``T(ti)`` with a slope of 3e-6, suite case ``building/wrong_constant``)."""
        mae0 = self.current_val[0]
        fitted = {f["cand"].key for f in fits}
        good = sorted([f for f in fits if f["cand"].k >= 2 and math.isfinite(f["val_mae"])
                       and f["val_mae"] <= (1 - MIN_GAIN) * mae0 and f.get("physical") not in ("non-physical",
                                                                                             "diverged")],
                      key=lambda f: f["val_mae"])[:2]
        nested = []
        for f in good:
            c: Candidate = f["cand"]
            kind = {"param_dependence": "wrong_constant", "heat_load": "heat_load"}.get(c.kind)
            if kind is None or not c.depends_on:
                continue
            for s_ in scored:
                d = s_["cand"]
                if (d.kind == kind and d.target == c.target and not d.depends_on and d.k == 1
                        and d.key not in fitted and not any(s_ is t for t in nested)):
                    nested.append(s_)
                    break
        return self.fit_extra(nested, "the sub-model of a better-scoring fit", current)

    def continue_fits(self, fits: list[dict], x_s: Extended) -> None:
        """Successive halving: the fits still moving after ``FIT_ITER_FIRST`` iterations, best training SSE
        first, go on to convergence (the held-out rows never decide who continues), side by side. (Continuing
        each on a network of its own cut the case study's diagnosis from 332 s to 289–292 s but raised its peak
        memory from 946 to 1177 MB; tried in commit 2edc05b, off by default and then removed: BENCHMARKS.md.)"""
        going = sorted([f for f in fits if f.get("more")], key=lambda f: f["train_sse"])[:FIT_CONTINUE]
        # started worst first: the fit furthest from the others' training SSE has the most left to go (the case
        # study's round 1: R_pc_hx1 on u1, SSE 470 against 0.33–222 K², went on for 78 iterations while the others
        # took 4–22), and started last it ran alone on one of the two cores at the end (issue 18)
        worst_first = sorted(range(len(going)), key=lambda i: -going[i]["train_sse"])

        def go_on(f: dict):
            def run(say) -> dict | None:
                if self.spent():
                    return None
                c, e = f["cand"], f["eng"]
                say(f"  continuing {c.describe()} ...")
                e.params = {k: np.array(v, copy=True) for k, v in f["params"].items()}
                t_f = _time.monotonic()
                info = e.fit(f["act"], max_iter=FIT_ITER - FIT_ITER_FIRST, deadline=self.deadline, tol=1e-4,
                             stall=True)
                say(f"    fitted in {_time.monotonic() - t_f:.1f} s ({info['iterations']} more iterations, "
                    f"{info['jacobians']} Jacobians)")
                return {**_fit_result(c, f["score"], e, x_s, self.e_base_val), "train_sse": info["sse"]}
            return run

        for f, new in zip(going, self.side_by_side([go_on(f) for f in going], worst_first)):
            if new is not None:
                f.update(new)

    def ml_choose(self, fits: list[dict], current: dict[str, tuple[float, float]]) -> dict | None:
        """The likelihood objective's decision (:mod:`.likelihood`): each candidate whose output-error fit did not
        diverge written as a network (the current model plus it) and fitted by maximum likelihood, then judged
        physical or not on those values; of the physical ones passing the likelihood-ratio test and the held-out
        check, the largest log-likelihood."""
        from .likelihood import P_LR, with_plausible_bounds

        ml = self.ml
        # an output-error fit that diverged gives no start; a non-physical one may still reach physical values
        ok = [f for f in fits if f.get("physical") != "diverged" and math.isfinite(f["val_mae"])]
        for f in fits:
            if f not in ok:
                f["reason"] = unphysical_reason(f)
        for f in ok:
            c = f["cand"]
            acc = [_cand_in(f["ext"], a.key) or a for a in self.accepted]
            cf = _cand_in(f["ext"], c.key) or c
            try:
                net_c = extend_network(f["net"] if f["net"] is not None else self.net_x, acc + [cf], f["params"],
                                       self.unused)
                for a in acc + [cf]:  # every new capacity/resistance within its plausible range (with_plausible_bounds)
                    if a.kind in STRUCTURAL_KINDS:
                        net_c = with_plausible_bounds(net_c, a, self.scales)
            except (TnnError, ValueError, KeyError) as exc:
                f["reason"] = f"not written as a network: {exc}"
                continue
            self.say(f"  likelihood fit: {c.describe()} ...")
            fit = ml.fit(c.describe(), net_c)
            if fit is None:
                f["reason"] = "its likelihood fit failed"
                continue
            f.update(ml_fit=fit, ml_net=net_c, ml=ml.test(fit, len(ok)))
            self.take_ml_values(f)
            self.judge(f, current)  # the likelihood's values count
        paying = []
        for f in ok:
            t = f.get("ml")
            if t is None:
                continue
            if f.get("physical") != "ok":
                f["reason"] = unphysical_reason(f)
            elif t["p_lr"] >= P_LR:
                f["reason"] = (f"likelihood-ratio test not passed (LR = {t['lr']:.3g} on {t['df']} df, p = "
                               f"{t['p_lr']:.2g} ≥ {P_LR} after ×{t['m']})")
            elif t["p_val_loglik"] >= P_LR:
                f["reason"] = (f"not confirmed on held-out data (one-step log-likelihood {t['val_loglik_gain']:+.4g}, "
                               f"Diebold–Mariano p = {t['p_val_loglik']:.2g} ≥ {P_LR})")
            else:
                paying.append(f)
        if not paying:
            return None
        pick = max(paying, key=lambda f: f["ml"]["loglik"])
        for f in paying:
            if f is not pick:
                f["reason"] = (f"a smaller likelihood than the chosen one (log L {f['ml']['loglik']:.2f} < "
                               f"{pick['ml']['loglik']:.2f})")
        return pick

    def judge(self, f: dict, current: dict[str, tuple[float, float]], params: dict | None = None) -> None:
        """Is a fitted candidate physical (:mod:`.plausibility`)? Sets ``f["physical"]`` (``ok``, ``diverged``,
        ``non-physical``) and ``f["why"]``; ``current``: each state's range (K) in the current model's runs;
        ``params``: the values to judge (default the candidate's fitted ones)."""
        from .plausibility import judge, start_up_rows

        eng = f["eng"]
        params = f["params"] if params is None else params
        _, xs = eng.simulate(params)
        before = self.final_eng.params
        start = None
        if self.init_rule == "estimate":  # fitted initial states: their start-up transients are not judged
            start = start_up_rows([e.n_steps for e in eng.exps], [e.dt for e in eng.exps],
                                  eng.model.time_constants(params), eng.model.state_names)
        f["physical"], f["why"] = judge(eng.model.network, params, xs, eng.model.state_names, self.scales,
                                        self.net.temperature_unit, before=before, current=current, start=start)

    def record(self, fits: list[dict], scored: list[dict], chosen: dict | None, rnd: int) -> None:
        """A :class:`Finding` per fitted candidate, best held-out SSE first, with the evidence."""
        current_val = self.current_val
        twins = _indistinguishable(chosen["score"], scored) if chosen is not None else []
        if chosen is not None:  # what the held-out run says about the twins it has a fit of (cautions agree with it)
            by_key = {f["cand"].key: f for f in fits}
            for t in twins:
                g = by_key.get(t["key"])
                if g is None or g is chosen:
                    continue
                mae = g["val_mae"] if g.get("physical") != "diverged" else math.nan
                t["val_mae"] = mae
                # separated: diverged, or at least twice the chosen one's held-out error (the rival rule of
                # :func:`~.selection._choose`, where a rival within noise must also be within 2× the best's MAE)
                t["separated"] = bool(not math.isfinite(mae) or mae >= 2.0 * chosen["val_mae"])
        order = ((lambda f: -f["ml"]["loglik"] if f.get("ml") else math.inf) if self.ml is not None
                 else (lambda f: f["val_sse"]))
        for rank, f in enumerate(sorted(fits, key=order), start=1):
            c = f["cand"]
            cf = _as_in(f["ext"], c) or c  # the candidate as laid out in the network it was fitted on
            prm = f["params"]
            diverged = f.get("physical") == "diverged" or not math.isfinite(f["val_mae"])
            mae, mx, sse = (math.nan, math.nan, math.nan) if diverged else (f["val_mae"], f["val_max"], f["val_sse"])
            finding = Finding(
                rank=rank, kind=c.kind, target=c.target, depends_on=list(c.depends_on),
                clause=finding_clause(self.net_x, cf, prm, f.get("net")),
                val_mae_after=mae, val_max_after=mx, accepted=f is chosen,
                words=_words(cf, prm, f["ext"], f["eng"], f["eng"].model), round=rnd,
                evidence={"score": f["score"]["public"]["score"], "score_p": f["score"]["public"]["p"],
                          "r2_linearised": f["score"]["public"]["r2"], "k": c.k,
                          "val_mae_before": current_val[0], "val_sse_before": current_val[2],
                          "val_sse_after": sse, "dm_stat": f["F"], "p_value": f["p"], "n_eff": f["n_eff"],
                          "lr_train": f.get("S_train"), "p_train": f.get("p_train"),
                          "test": ("likelihood ratio on the training rows (effective N, Bonferroni over the "
                                   "candidates scored) and Diebold–Mariano on held-out squared errors (HAC "
                                   "variance, AIC charge for k)"),
                          "mae_gain": 1 - mae / current_val[0] if current_val[0] else 0.0,
                          "reason": f.get("reason", ""), "plausibility": f.get("physical", "ok"),
                          "diverged": diverged,
                          "indistinguishable_from": twins if f is chosen else []})
            if f.get("ml") is not None:
                finding.evidence["likelihood"] = dict(f["ml"])
                if f.get("values_from"):
                    finding.evidence["values_from"] = f["values_from"]
                finding.evidence["test"] = (
                    "likelihood ratio of the one-step (Kalman-filter) likelihood on the training rows, χ² on the "
                    "added estimated quantities (Bonferroni over the candidates fitted), and Diebold–Mariano on the "
                    "held-out rows' one-step log-likelihood (AIC charge for the added quantities)")
            self.findings.append(finding)
            if f is chosen:
                self.acc_findings.append(finding)

    def accept(self, chosen: dict, rnd: int) -> None:
        c = chosen["cand"]
        self.say(f"round {rnd}: accepted {c.describe()} (held-out MAE {self.current_val[0]:.4g} → "
                 f"{chosen['val_mae']:.4g} K)")
        self.accepted.extend(c.members if c.element.get("probe") else [c])  # a line and its square: both
        chosen["base_net"] = self.net_x
        for old in self.acc_fits:
            # an earlier round's accepted fit: its engine (that round's compiled simulation and Jacobians, 60–150 MB
            # on the case study) and residual arrays are no longer read — polish reads its candidate, extension and
            # networks only
            for key in ("eng", "e_all", "e_val", "params"):
                old.pop(key, None)
        self.acc_fits.append(chosen)
        self.final_act = list(chosen.get("act") or [])
        chosen["eng"].params = chosen["params"]
        self.state.harvest(chosen["eng"], chosen["ext"], [k.key for k in self.accepted])
        prev, self.final_eng, self.final_ext = self.final_eng, chosen["eng"], chosen["ext"]
        if prev is not self.final_eng and prev.model is not self.final_eng.model:
            # the model it replaces (in round 1 the nominal engine, which stays for its data) compiles nothing more
            # for the selection: its programs (~40 MB on the case study) go before the next round's fits
            prev.release_programs()
        self.current_val = (chosen["val_mae"], chosen["val_max"], chosen["val_sse"])
        if self.ml is not None:
            self.ml.accept(chosen["ml_fit"], chosen["ml_net"])
        if chosen["net"] is not None:  # a structural edit becomes part of the base network (its parameter free)
            self.net_x = chosen["net"]
            self.ext = build_extended(self.net_x, self.varying, self.extra, kinds=self.kinds)
            self.big = None
        self.remaining = self.candidates_now()

    def end_rounds(self) -> None:
        """After the last round: the score test's extended network (every candidate's column, its compiled
        simulation and derivatives) and the last round's fits are not needed by the extension or the MLP check."""
        self.big = None
        self.round_fits = []
        self.round_now = -1  # the budget, if spent from here on, cut the final fits

    # -- the extension ---------------------------------------------------------------------------------

    def build_extension(self) -> None:
        """The accepted findings applied to the IR (:func:`extend_network`, fitted values in the new parameters),
        printed; the extended model's held-out residual."""
        t0 = _time.monotonic()
        uncertain = bool(self.accepted and self.final_act and self.ml is None)  # under ml: the likelihood's own
        if uncertain and self.threads > 1 and self.backend == "jax":
            # the standard errors' forward-mode Jacobian (a program of its own, 0.7 s of compiling on the case study)
            # compiled, not run, on a clone beside the polish, whose fits take their Jacobians by differences; the
            # clone's parameter table is its own, the program shared (issue 18)
            two_at_once(partial(self.final_eng.clone().jacobian, list(self.final_act), run=False), self.polish,
                        self.threads)
        else:
            self.polish()
        if uncertain:
            self.uncertainty = final_uncertainty(self.final_eng, self.final_act, self.final_ext.fn_vars)
        self.acc_small = [_cand_in(self.final_ext, c.key) or c for c in self.accepted]
        self.ext_net = extend_network(self.net_x, self.acc_small, self.final_eng.params, self.unused)
        self.set_extension(self.ext_net)
        if self.accepted:
            from ..compiler import compile as compile_network

            step = sub_step_note(compile_network(self.ext_net, backend="numpy"), [float(e.dt) for e in self.exps],
                                 "the extended network")
            if step and step not in self.notes:
                self.notes.append(step)
        self.lap("extend", t0)
        self.y_fin, _ = self.final_eng.simulate()
        e_fin = np.where(self.final_eng.val_mask, self.final_eng.y - self.y_fin, np.nan)
        self.res_fin = R.summarise(e_fin[self.vrows], self.out_names)
        self.form = None

    def polish(self) -> None:
        """The extended model fitted to convergence on the training rows (all free parameters and the accepted
        findings' together; each round stopped early), then every accepted finding's words and clause made from
        these final values, so the verdict, the JSON and the written ``.thn`` say the same numbers. Under ``ml`` the
        values are the likelihood fit's (:meth:`take_ml_values`) and are not refitted here."""
        if not self.accepted or not self.final_act:
            return
        eng = self.final_eng
        if self.ml is None and not self.spent():
            self.say("fitting the extended model to convergence ...")
            rounds, val0 = eng.params, eng.sse(which="val")
            info = eng.fit(self.final_act, max_iter=FIT_ITER_FIRST, deadline=self.deadline, tol=1e-6)
            self.second_start(eng, info)
            val1 = eng.sse(which="val")
            if not val1 <= val0:
                # the training optimum loses on the held-out rows against the values the findings were accepted with
                # (a noisy case study: a heat load at hx1 accepted at 0.044 K held out, 0.105 K once converged, the
                # nominal model 0.084 K): the accepted values stay, and the summary says so
                eng.params = rounds
                self.notes.append(
                    "the extended model fitted to convergence on the training rows did worse on the held-out rows "
                    f"(SSE {val1:.4g} against {val0:.4g} K² with the values the findings were accepted with): the "
                    "accepted values are the ones reported and written")
                self.say("  the converged fit loses on held-out data: the accepted values are kept")
            self.state.harvest(eng, self.final_ext, [c.key for c in self.accepted])
        P = eng.params
        # a dependence found in one round and grown by a later one (R_hp1 on T(hx1), then on u1) is one learned
        # function: its final law is the later finding's words; the earlier keeps the words it was accepted with
        # (both printed from the final law read "R_hp1 depends on u1 and T(hx1)" twice)
        last = {fit["cand"].target: i for i, fit in enumerate(self.acc_fits) if fit["cand"].kind == "param_dependence"}
        for i, (finding, fit) in enumerate(zip(self.acc_findings, self.acc_fits)):
            c = fit["cand"]
            if c.kind == "param_dependence" and last[c.target] != i:
                later = self.acc_findings[last[c.target]]
                note = f" (grown in round {later.round}: the final law of {c.target} is given there)"
                if not finding.words.endswith(note):
                    finding.words += note
                continue
            in_final = _as_in(self.final_ext, c)
            cf = in_final or _as_in(fit["ext"], c) or c
            words = _words(cf, P, self.final_ext if in_final is not None else fit["ext"], eng, eng.model)
            if words != finding.words:
                finding.evidence["words_when_accepted"] = finding.words
                finding.words = words
            finding.clause = finding_clause(fit["base_net"], cf, P, fit.get("net"))

    def second_start(self, eng, info: dict) -> None:
        """The extended model fitted once more from the values written in the file (the user's free constants and
        learned functions at their written values, the findings' new coefficients at zero; initial states and the
        structural findings' values kept): the rounds start from the baseline fit, which may have moved constants
        far to absorb what a finding now explains (issue 17's "the Peltier coefficient rides along"), and a
        compensating optimum is then a local one. The lower training error wins (the ``train --objective ml`` rule
        of two starts) if it does not lose on the held-out rows; the summary says when the written start won.

        Successive halving between the two starts: ``eng`` holds the first start after ``FIT_ITER_FIRST`` Jacobians
        (``info``, its fit from the rounds' values); the written start gets as many, and only the one then ahead on
        the training rows goes on to convergence (``FIT_ITER`` Jacobians in all). The first start also goes on when
        the written one, continued, does not win. On the case study's 4 h the first start had crawled 80 Jacobians
        (15 s) from 1.315 to 1.268 K² before the written start reached 0.316 K² and won (issue 18)."""
        act = self.final_act

        def go_on(inf: dict) -> None:
            if not self.spent():
                continue_fit(eng, act, inf, FIT_ITER, self.deadline, 1e-6)

        first = eng.params
        init = eng.model.to_numpy(eng.model.init_params(seed=0))
        own = {p.name for p in self.net.params if p.free} | {fn.name for fn in self.net_x.learned}
        own |= {fn.name for fn in self.final_ext.network.learned if fn.name.startswith("dx_")}
        start = {k: np.array(v, dtype=float, copy=True) for k, v in first.items()}
        moved = 0
        for j in act:
            col = eng.cols[j]
            if col.key in own or col.key.split(".", 1)[0] in own:
                start[col.key].reshape(-1)[col.index] = np.asarray(init[col.key], dtype=float).reshape(-1)[col.index]
                moved += 1
        if not moved or self.spent():
            go_on(info)
            return
        self.say("fitting it again from the values written in the file ...")
        eng.params = start
        info2 = eng.fit(act, max_iter=FIT_ITER_FIRST, deadline=self.deadline, tol=1e-6)
        sse1 = info["sse"]
        if not info2["sse"] < sse1:
            self.say(f"  behind after {info2['jacobians']} Jacobians (training SSE {info2['sse']:.4g} against "
                     f"{sse1:.4g} K²): the fit from the rounds' values goes on")
            eng.params = first
            go_on(info)
            return
        go_on(info2)
        second, sse2, val2 = eng.params, eng.sse(), eng.sse(which="val")
        eng.params = first
        val1 = eng.sse(which="val")
        # the same optimum, or a better training fit that loses on the held-out rows (a compensating optimum of
        # findings that only paid from the rounds' values): the rounds' values stay, and their fit goes on
        if sse2 < (1 - 1e-3) * sse1 and val2 <= val1:
            eng.params = second
            self.say(f"  the written start wins (training SSE {sse2:.4g} against {sse1:.4g} K²)")
            self.notes.append(f"the extended model fitted from the values written in the file reached a lower "
                              f"training error than from the baseline's values (SSE {sse2:.4g} against {sse1:.4g} "
                              f"K² after {info['jacobians']} Jacobians): its values are the ones reported and written")
            return
        go_on(info)

    def take_ml_values(self, f: dict) -> None:
        """Under ``ml``: candidate ``f``'s likelihood estimates (its physical constants, by name and shape) put in a
        clone of its engine, then only the training files' initial states refitted to them (output error), and its
        held-out numbers taken again: the judge, the words, the clause and the held-out MAE of every finding fitted by
        likelihood say the likelihood's values, and for the chosen one the next round starts from them and the JSON,
        the written ``.thn`` and the free run reported are the likelihood fit's. A learned function's coefficients
        keep their output-error values (the likelihood fits them as weights of another layout); the evidence says so.

        The initial states must follow: those of the output-error fit belong to its own constants. On Bacher &
        Madsen's Ti the heater node's output-error fit started it at 157 °C, which with the likelihood's 6× weaker
        coupling heated the room to 47 °C after the start-up rows the judge leaves out, and the best candidate was
        called non-physical; a rejected sensor lag was worded with its output-error 60 s beside its likelihood
        estimate of 489 s."""
        from .likelihood import with_ml_values

        eng = f["eng"].clone()
        eng.params = with_ml_values(f["params"], f["ml_fit"])
        x0_cols = [j for j, col in enumerate(eng.cols) if col.key.startswith(X0_PREFIX)]
        if x0_cols and not self.spent():
            eng.fit(x0_cols, max_iter=FIT_ITER, deadline=self.deadline, tol=1e-6)
        keep = {k: f[k] for k in ("score", "act", "net", "ml", "ml_fit", "ml_net") if k in f}
        f.update(_fit_result(f["cand"], f["score"], eng, f["ext"], self.e_base_val), **keep)
        dep = f["cand"].kind not in STRUCTURAL_KINDS or any(c.kind not in STRUCTURAL_KINDS for c in self.accepted)
        f["values_from"] = ("the likelihood fit" + (" (a learned function's coefficients: the output-error fit)"
                                                    if dep else ""))

    def set_extension(self, ext_net: Network) -> None:
        """The extension's text, its diff from the original and its changed statements (``clauses``)."""
        self.ext_net = ext_net
        self.ext_text, self.diff = extension_text(self.net, ext_net, self.acc_small, self.path)
        self.clauses = changed_lines(self.net, ext_net) if self.accepted else []
        if not self.accepted:
            self.diff = ""

    def release_programs(self) -> None:
        """The nominal and current engines' compiled programs let go (:meth:`_Engine.release_programs`; built again
        if used): after the extension is built, before the MLP check compiles two trainings (issue 18)."""
        for eng in (self.eng, getattr(self, "final_eng", None)):
            if eng is not None:
                eng.release_programs()

    def compare_with_mlp(self) -> None:
        """Linear or MLP, as the evidence says: only where a structured residual is left and time allows."""
        res_fin = self.res_fin
        targets = doctor_targets(self.acc_small)
        if not (self.accepted and targets and self.mlp_check and not R.all_white(res_fin.whiteness)):
            return
        if stop_requested():  # Ctrl-C: the check is skipped and the result says so
            self.spent("before the check of an MLP against the linear law")
            return
        if self.deadline is not None and _time.monotonic() + 2 * self.mlp_time >= self.deadline:
            return
        from ..data import split_by_time
        from .mlp_check import compare, values_for_extension

        t0 = _time.monotonic()
        self.say("the residual is not white: is an MLP better than the linear law? (an MLP started as the doctor's "
                 "linear law, trained with the rest held at the doctor's fit)")
        tr_e, va_e = self.train_exps, self.val_exps
        if not va_e:
            parts = [split_by_time(e, 0.7) for e in self.train_exps]
            tr_e, va_e = [a for a, _ in parts], [b for _, b in parts]
        try:
            ext = _check_text(self.ext_text, self.output or (self.path or "extended.thn"))
            # from the doctor's fit where each of the extension's functions has its counterpart in it (always, for
            # what the doctor adds); else from nominal values, against the doctor's fit as the bar
            start = values_for_extension(ext, self.final_eng.net, self.final_eng.params)
            form = compare(ext, targets, tr_e, va_e, backend=self.backend, time_limit=self.mlp_time, say=self.say,
                           threads=self.threads, bar=res_fin.mae, stop=stop_requested, start=start)
        except TnnError as exc:  # e.g. data given as Experiments without the extension's extra columns
            form = {"choice": "linear", "reason": f"not compared: {exc.diagnostics[0].message}"}
        # an MLP that does not beat the doctor's own linear fit by MIN_GAIN is never chosen: ``compare`` checks it
        # (``bar``) before it trains the linear law at all
        if form is not None:
            self.say(f"  {form['reason']}")
            if form["choice"] == "mlp":
                self.set_extension(form["network"])
                self.mlp_model = form.get("model")
            form = {k: v for k, v in form.items() if k not in ("network", "model")}
        self.form = form
        self.lap("mlp_check", t0)

    def diagnosed_model(self, extended: dict, verdict: str, ext_file: str | None) -> Any:
        """The network the diagnosis ends with at the values it was measured with (:mod:`.saved_model`), or
        ``None`` (a note says why) where the doctor's values cannot be put under the extension's names."""
        from .mlp_check import values_for_extension
        from .saved_model import diagnosed_model

        eng = self.final_eng
        net = _check_text(self.ext_text, self.output or (self.path or "extended.thn")) if self.accepted else self.net
        form = extended.get("form", "linear")
        values = None if self.mlp_model is not None else values_for_extension(net, eng.net, eng.params)
        if self.mlp_model is None and values is None:
            self.notes.append("no model of the extension: the doctor's fitted values could not be put under the "
                              "names of the extension it printed (a bug: please report it)")
            return None
        val_files = [str(p) for p in _paths_of(self.val_arg) if p]
        train_files = [str(p) for p in _paths_of(self.train_arg) if p]
        diagnosis = {
            "verdict": verdict,
            "findings": [f.words for f in self.findings if f.accepted],
            "form": form,
            "values": ("the MLP check's training (the MLP started as the doctor's linear law)"
                       if self.mlp_model is not None else
                       "the doctor's fit of the extension" if self.accepted else "the doctor's baseline fit"),
            "network_file": self.path,
            "extended_file": ext_file,
            "held_out": {"mae": extended["val_mae"], "max": extended["val_max"],
                         "data": val_files if self.val_arg else
                         "the last 30 % of each training file (a free run over the whole file)",
                         "burn_in": self.initial.get("burn_in")},
            "train_files": train_files,
            # the values with their standard errors and what the data cannot tell apart (tnnc inspect shows them)
            "uncertainty": extended.get("uncertainty"),
            "mlp_from_fit": self.mlp_model is not None and ((extended.get("mlp_check") or {}).get("linear") or {}
                                                            ).get("stopped") == "the doctor's fit",
        }
        return diagnosed_model(net, values or {}, backend=self.backend, init_rule=self.init_rule, eng=eng,
                               train_arg=self.train_arg, data_files=[*train_files, *val_files], diagnosis=diagnosis,
                               trained=self.mlp_model)

    def result(self) -> Diagnosis:
        """Write the extension (checked by parsing it) where asked, and assemble the :class:`Diagnosis`."""
        ext_file = None
        if self.accepted and self.ext_text:
            _check_text(self.ext_text, self.output or (self.path or "extended.thn"))
            if self.output:
                write_text_atomic(self.output, self.ext_text)
                ext_file = self.output
        res_fin, form = self.res_fin, self.form
        extended = {"val_mae": res_fin.mae, "val_max": res_fin.max, "clauses": self.clauses,
                    "per_sensor": res_fin.errors, "form": "linear"}
        if self.ml is not None and self.ml.current is not None:
            from .likelihood import likelihood_summary

            extended["likelihood"] = likelihood_summary(self.ml.current)
        if self.uncertainty is not None:
            extended["uncertainty"] = self.uncertainty
        if form is not None:
            extended["mlp_check"] = form
            if form.get("choice") == "mlp":  # the held-out numbers of the trained MLP extension
                extended.update(form="mlp", val_mae=form["mlp"]["val_mae"], val_max=form["mlp"]["val_max"])
        verdict = ("; ".join(f.words for f in self.findings if f.accepted) if self.accepted
                   else "no significant deficiency found")
        if self.budget_cut is not None:
            where = self.budget_cut
            cut = (f"stopped by Ctrl-C {where}" if self.interrupted
                   else f"the budget ({self.budget_s:g} s) ran out {where}")
            verdict = (f"{verdict}; {cut}" + (": more rounds could find more" if "round" in where else "")
                       if self.accepted else
                       f"not decided: {cut}, so no deficiency was found but the search did not finish; "
                       + ("run it to its end" if self.interrupted else "run with a larger --budget (or none)"))
        model = self.diagnosed_model(extended, verdict, ext_file)
        if model is not None and self.model_dir:
            model.save(self.model_dir, force=self.force, source_text=self.ext_text if self.accepted else None)
            self.say(f"model written to {self.model_dir}")
        self.timings["total"] = round(_time.monotonic() - self.t_start, 3)
        eng = self.eng
        plots = {"t": self.t_all, "y": eng.y, "y_nominal": self.y_nom, "y_extended": self.y_fin,
                 "val_mask": eng.val_mask, "train_mask": eng.train_mask, "residual_nominal": self.e_nom,
                 "variables": self.variables, "output_names": self.out_names, "dependence": self.res.dependence}
        return Diagnosis(network=self.net.name, baseline=self.base, residuals=self.res, scores=self.scores_out,
                         findings=self.findings, extended_text=self.ext_text if self.accepted else self.text,
                         extended_file=ext_file, extended=extended, diff=self.diff, verdict=verdict,
                         left=_what_is_left(res_fin), timings=self.timings, plots=plots, notes=self.notes,
                         initial=self.initial, objective=self.objective, model=model,
                         model_dir=str(self.model_dir) if model is not None and self.model_dir else None,
                         budget=None if self.budget_cut is None else {"seconds": self.budget_s,
                                                                      "ran_out": self.budget_cut,
                                                                      "interrupted": self.interrupted})
