"""``tnn_dsl.diagnose``: the model doctor.

Given a network and measured data it answers, in one call: where the simulation is wrong, why (a cause
named in words and as ``.thn`` structure), what the extended model is, and how much better it is on data
it was not fitted on. The question answered is the *simulation* one ("is my free-run simulation right?",
output error from each file's initial state, ``init``), not the one-step-predictor one of Kalman-filter methods.

Steps (see docs/architecture.md, "Diagnosis"):

1. **Fit** the nominal model's free parameters on the training rows by Levenberg–Marquardt (Gauss–Newton
   with Marquardt damping on forward-mode Jacobians; positive parameters in log space, bounds respected).
   Least squares is the statistic's own estimator; the Jacobians are reused by the score test. Free
   constants that are not identifiable as written (tclab.thn: heater gains, conductances and capacities
   scale together) leave a flat, curved valley where the damped step points the right way but is short:
   after an accepted step the fit goes on along it (2δ, 4δ, … up to 64δ, one simulation each, no
   Jacobian) while the training SSE keeps dropping. On the Kuntz–Rawlings TCLab file the nominal fit
   reaches the training least-squares optimum (the same SSE from the file's values and from the trainer's
   fitted values); its held-out MAE is that of the least-squares fit of the nominal structure, which is
   not the trainer's number (the trainer validates the tail from its measured state and keeps its
   best-*validation* iterate). Candidate fits (step 4) run until the SSE drops by less than 1e-4
   relatively, at most ``FIT_ITER`` Jacobians (a fresh Jacobian every ``JACOBIAN_EVERY`` iterations, Broyden's
   secant update in between: :meth:`tnn_dsl.doctor.engine._Engine.fit`).
2. **Residuals** on the held-out rows (``val`` files after their burn-in, else the last 30 % of each training
   file, simulated as a free run from the file's start): per-sensor MAE/max/bias, binned residual against inputs, states
   and time, whiteness (Ljung–Box, cumulated periodogram), noise σ (:mod:`tnn_dsl.analysis.residuals`).
3. **Candidates** from the IR (:mod:`.candidates`), all exactly null, in ONE extended network, plus structural
   ones (a sensor lag, a missing thermal mass on a link, a heat capacity behind a source) that are not.
   **Score test** at the fitted point: Jacobian ``J`` of the training outputs w.r.t. every candidate
   column and every free column. Candidates enter as extra heat flows per
   node (``C·∂rhs_big/∂θ`` at the current trajectory, pointwise) pushed through ONE batched forward-mode
   derivative of the current network's simulation w.r.t. forcing inputs (``_with_forcing``), plus direct
   output terms; a sensor lag's column is ``−dT_node/dt``. The free directions are projected out
   (``P = I − J_f J_f⁺``) and for candidate c
   ``S_c = N_eff · rᵀ Ĵ_c (Ĵ_cᵀĴ_c)⁻¹ Ĵ_cᵀ r / rᵀr`` (the LM statistic ``N·R²`` with the sample size corrected
   for residual autocorrelation), p-value from χ²(k_c); ranked on the noise's own scale (``_score_stats``).
   The Gauss–Newton step gives the initial value.
4. **Fit the best few** distinct candidates (``_shortlist``, plus those the score test cannot order against them;
   free + candidate columns, LM from the GN step, successive halving; a second start from the values written in
   the file for the constants the fit moved far) and measure on held-out rows. Accept the best only if it pays: a
   Diebold–Mariano test on the held-out squared errors (Newey–West variance for the autocorrelation, an AIC charge
   for the k extra parameters; p < 0.05) and MAE at least 10 % lower. Compensation guard (thesis §6.2.4): among
   fitted candidates whose held-out SSE is within noise of the best, the one with fewer parameters, then the
   more physical placement wins (a parameter of an element beats a heat load at a node, a parameter the
   user already declared uncertain beats one they did not; see ``_place``); runners-up are reported. A fit
   whose simulation diverges, or whose values or temperatures are not physical (:mod:`.plausibility`), is
   never accepted and the reason is shown; the next-best candidate is fitted in its place (its exact twins first,
   also when it does not pay). Before deciding, the
   one-parameter sub-model of the best dependences and, before a heat load wins, its more physical rivals are
   fitted to convergence; the best linear dependences are also fitted with their square term (a look-ahead: the
   line is accepted when the pair wins, or the pair itself when the line alone does not pay).
5. **Extend**: the accepted findings applied to the IR (``learn`` functions, links, radiation, sensor offsets and
   lags, thermal masses, capacities behind sources, with their fitted values), printed as ``.thn`` by
   :func:`tnn_dsl.lang.print_thn` and re-loaded to check it is valid; the gain on held-out data. Repeat 3–5
   (forward selection) until nothing pays.
"""

from __future__ import annotations

import os
import warnings
from typing import Any, Callable

from ..compiler.backends.adapter import drop_compiled_caches
from ..compiler.integrators import StepSizeWarning
from ..core.blas import one_blas_thread
from ..core.memory import large_blocks_mapped, release_free_memory
from .results import Diagnosis, Finding
from .scoring import SHORTLIST_TOP
from .session import _Session
from .stopping import ctrl_c_stops

__all__ = ["diagnose", "Diagnosis", "Finding"]


def diagnose(net_or_path: Any, train: Any, val: Any = None, budget_s: float | None = None, backend: str = "jax",
             progress: Callable[[str], None] | None = None, *, top: int | None = None, max_rounds: int = 4,
             output: str | None = None, kinds: tuple[str, ...] | None = None, mlp_check: bool = True,
             mlp_time: float = 60.0, force: bool = False, init: str = "estimate",
             burn_in: float | None = None, objective: str = "output-error", threads: int | None = None,
             release_jax_caches: bool = False, stop_on_ctrl_c: bool = False,
             model_dir: str | os.PathLike | None = None) -> Diagnosis:
    """Diagnose ``net_or_path`` (a ``.thn`` path or a :class:`Network`) on measured data.

    Parameters
    ----------
    train : path(s) or list of :class:`Experiment`
        Training data; the fit and the score test use it.
    val : path(s) or list of Experiment, optional
        Held-out data; default the last 30 % of each training file (a free run over the whole file,
        measured on the tail).
    budget_s : float, optional
        Wall-clock budget in seconds; the forward selection stops early when it is spent.
    backend : "jax" | "torch"
    progress : callable(str), optional
        Called with one line per step (the CLI's progress display).
    top : int, optional
        How many of the best-scoring distinct candidates are fitted properly each round (default
        :data:`~tnn_dsl.doctor.scoring.SHORTLIST_TOP`, 3).
    output : str, optional
        Where to write the extended ``.thn`` (default: not written; the text is in the result). Checked
        before any work: never an input, never an existing file other than a ``.thn`` unless ``force``.
    model_dir : str, optional
        Where to write the diagnosed model (:attr:`Diagnosis.model`, a model directory as ``tnnc train`` writes:
        the extension at the doctor's values, the MLP check's trained MLP where it chose one, the network itself at
        its baseline fit where nothing was accepted), which ``tnnc evaluate`` free-runs to the held-out numbers the
        report gives. Checked before any work, as ``output`` is.
    mlp_check : bool
        When the extended model's held-out residual is still not white (all sensors and both whiteness tests
        together at a family-wise 5 %), train the extension with its
        ``linear`` clauses and with them as MLPs and keep the MLP only if it pays on held-out data
        (:mod:`tnn_dsl.doctor.mlp_check`); ``mlp_time`` s of training for each (skipped when the budget is short).
    init : "estimate" | "measured" | "steady"
        Where each free run starts (:mod:`tnn_dsl.fit.initial`). ``estimate`` (default): a training file's
        initial state is fitted with the parameters (and is a nuisance direction of the score test); a held-out
        file's is estimated from its first ``burn_in`` seconds (default a tenth of the file) with the parameters
        fixed, and those samples are not scored. ``measured``: the steady state of the first inputs with the
        sensed nodes at their first readings. ``steady``: the steady state of the first inputs (the summary warns
        when a file does not start at rest).
    objective : "output-error" | "ml"
        What decides between candidates (:mod:`tnn_dsl.doctor.likelihood`). ``output-error`` (default): the
        free-run error, held-out Diebold–Mariano test on squared errors. ``ml``: each physical shortlisted candidate
        is also fitted by maximum likelihood of the one-step predictor (Kalman filter) on the training rows; accepted
        by a likelihood-ratio test with the held-out one-step log-likelihood as the check; the largest likelihood
        first (Bacher & Madsen's forward selection). The values reported and written are then the likelihood fit's.

    threads : int, optional
        Candidate fits run side by side in this many threads (default ``$TNN_DOCTOR_THREADS``, else the CPUs this
        process may use, at most 4; JAX only: torch fits one at a time, its forward-mode derivatives are per
        thread). The result does not depend on it, except through ``budget_s``.
    release_jax_caches : bool
        Before the MLP check, empty JAX's caches of compiled programs (``jax.clear_caches()``): the selection's
        programs, let go by then, stay there otherwise. Off by default, because every jitted function in the
        process, the caller's own included, then compiles again on its next call; ``tnnc diagnose``, which owns its
        process, turns it on (issue 18: the case study's peak with two threads 580–614 → 557–558 MB,
        ``benchmarks/bench_diagnose.py``, BENCHMARKS.md "Diagnosis: time and memory").
    stop_on_ctrl_c : bool
        A first Ctrl-C (in the main thread) stops the diagnosis the way a spent budget does — no new work, a fit in
        progress ends after its iteration — and it returns what it has, the findings accepted so far with their
        extended model, its verdict saying where Ctrl-C stopped it (``budget["interrupted"]``); a second Ctrl-C
        aborts (:mod:`tnn_dsl.doctor.stopping`). Off by default: a program running diagnoses in a loop of its own
        expects Ctrl-C to end that loop. ``tnnc diagnose`` turns it on.

    Returns
    -------
    Diagnosis
    """
    run = _Session(net_or_path, train, val, budget_s, backend, progress,
                   top=SHORTLIST_TOP if top is None else top, max_rounds=max_rounds,
                   output=output, kinds=kinds, mlp_check=mlp_check, mlp_time=mlp_time, force=force, init=init,
                   burn_in=burn_in, objective=objective, threads=threads,
                   model_dir=None if model_dir is None else os.fspath(model_dir))
    with one_blas_thread(), ctrl_c_stops(progress or (lambda s: None), enabled=stop_on_ctrl_c), \
            warnings.catch_warnings():
        # one BLAS thread: small matrices between compiled simulations, where BLAS threads only spin (core.blas)
        # the rollouts' sub-steps said once in the report (session.sub_step_note), not as a StepSizeWarning from
        # every call site of every candidate's fit (19 of them on Bacher & Madsen's Ti)
        warnings.simplefilter("ignore", StepSizeWarning)
        return _run(run, max_rounds, release_jax_caches)


def _run(run: _Session, max_rounds: int, release_jax_caches: bool = False) -> Diagnosis:
    # the fits' large buffers (simulations' temporaries, Jacobians) mapped on their own and handed back when freed
    # (core.memory); the MLP check's trainings after it reuse theirs step after step
    with large_blocks_mapped():
        run.read_data()
        run.fit_baseline()
        run.analyse_residuals()
        for rnd in range(1, max_rounds + 1):
            if not run.selection_round(rnd):
                break
        run.end_rounds()
        release_free_memory(collect=True)  # the rounds' engines, networks and arrays are done with (core.memory)
        run.build_extension()
        # the extension's engines are done with too: collected before the MLP check compiles and trains two models
        # (its peak with two threads 878 → 829 MB, benchmarks/bench_diagnose.py, one run each, 2026-11-28), and the
        # nominal and extended engines' compiled programs let go (the result needs their data only)
        run.release_programs()
    if release_jax_caches:
        # the programs let go above are still in JAX's own caches until they are emptied
        drop_compiled_caches(run.backend)
    release_free_memory(collect=True)
    run.compare_with_mlp()
    return run.result()
