"""The thesis's case study (chapter 5, Table 5.1, Figure 5.6), runnable end to end.

Used by ``examples/thesis_case_study.py`` (full budgets) and ``tnnc demo`` (budgets that fit in 10 minutes
on two cores). Steps:

1. generate the case-study data (``generate_case_study``; cached by its manifest);
2. train the model variants M1–M5 of Table 5.1 on ``train.csv`` with ``val.csv`` for early stopping
   (M5 = M4's Peltier network, frozen, loaded from the M4 model just trained, + M3's heat-pipe MLP);
3. validation MAE and max error (thesis eq. 4.9): the trainer's free run of ``val.csv`` from an initial state
   estimated on its first tenth (a burn-in, not scored; ``tnn_dsl.fit.initial``);
4. out of distribution: MAE averaged over the ``ood_<P>_<k>.csv`` sets per widening P (Figure 5.6);
5. the ratios the thesis reports (``THESIS``) computed from our numbers, side by side.

Everything measured is returned as a plain dict (and written as ``results.json``); nothing is hard-coded
but the thesis's own reported ratios, which are labelled as such.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..core import OutputKind, TnnError, check_output, save_figure, write_text_atomic

__all__ = ["StudyConfig", "run_study", "thesis_ratios", "THESIS", "results_table", "plot_study", "MODELS"]

MODELS = {
    "M1": ("m1.thn", "analytic Peltier, constant heat pipe"),
    "M2": ("m2.thn", "analytic Peltier, linear heat pipe"),
    "M3": ("m3.thn", "analytic Peltier, MLP heat pipe"),
    "M4": ("m4.thn", "MLP Peltier, constant heat pipe"),
    "M5": ("m5.thn", "frozen MLP Peltier (M4) + MLP heat pipe"),
}

THESIS = {
    "M1/M2 validation MAE": 4.2,
    "M1/M3 validation MAE": 3.1,
    "M3 − M2 validation MAE [mK]": 11.0,
    "M4 − M1 validation MAE [mK]": 10.0,
    "M5 improvement over M4 [%]": 26.0,
    "M5/M3 validation MAE": 2.5,
    "M4 growth at +40 % (×)": 7.0,
    "M5 growth at +40 % (×)": 7.0,
    "M1 growth at +40 % (×)": float("nan"),
    "M2 growth at +40 % (×)": 4.0,
    "M3 growth at +40 % (×)": 3.0,
}
"""What the thesis reports (§6.2, Table 6.1; case-study.md "What the thesis reports"). M1's growth is not
given separately (\"3–4× for M1–M3\")."""


@dataclass
class StudyConfig:
    """Budgets and sizes. ``durations`` (train, val, ood) s overrides the data lengths (quick runs);
    ``n_ood`` sets per widening; ``epochs``/``time_limit`` (s of training per model, compiling not counted) bound
    training."""

    backend: str = "jax"
    epochs: int = 300
    time_limit: float | None = 240.0
    lbfgs_iters: int = 100
    n_ood: int = 10
    widen: tuple[float, ...] = (0.1, 0.2, 0.3, 0.4)
    durations: tuple[float, float, float] | None = None
    models: tuple[str, ...] = ("M1", "M2", "M3", "M4", "M5")
    seed: int = 0
    train_options: dict = field(default_factory=dict)
    compile_ahead: bool | None = None
    """torch: compile the later models' programs in a helper process while the first ones train
    (:mod:`tnn_dsl.fit.compile_ahead`); ``None``: where it can pay (torch, two cores or more, 2 GB of memory
    available, ``TNN_COMPILE_AHEAD`` not ``0``)."""


def _networks_dir() -> Path:
    from .casestudy import network_path

    return Path(network_path("peltier_heatpipe/m1.thn")).parent


def _m5_network(m4_dir: Path):
    """m5.thn with its frozen Peltier function's ``init_from`` pointed at the M4 model just trained."""
    from ..lang import load

    net = load(str(_networks_dir() / "m5.thn"))
    learned = [fn.model_copy(update={"init_from": str(m4_dir)}) if fn.init_from else fn for fn in net.learned]
    return net.model_copy(update={"learned": learned})


DATA_BACKEND = "jax"
"""The backend that simulates the true system for the study's data, whichever backend trains the models
(``StudyConfig.backend``): the data are the study's "measurements", the same to round-off from any backend, and
a forward simulation of 4 h at 0.1 s steps plus 41 sets of 2 h took 14 s on JAX against 191 s on eager torch
(``tnnc demo`` and ``tnnc demo --backend torch``, 2026-11-29, AMD EPYC; issue 18)."""


STUDY_FILES = frozenset({"data", "data-quick", "models", "results.json", "report.md", "ood.png", "validation.png"})


def _is_study_dir(p: Path) -> bool:
    return all(c.name in STUDY_FILES for c in p.iterdir())


STUDY_DIR = OutputKind("case-study output directory", is_dir=True, ours=_is_study_dir, example="tnnc-demo")
"""What :func:`run_study` (``tnnc demo``) writes: data sets, model directories, results, report, plots."""


def run_study(out_dir: str | os.PathLike, data_dir: str | os.PathLike | None = None,
              config: StudyConfig | None = None, progress: Callable[[str], None] | None = None,
              *, force: bool = False, validation_runs: dict | None = None) -> dict:
    """Run the study; write ``out_dir/models/<m>``, ``out_dir/results.json``; → the results dict::

        {"config": ..., "data": {...}, "models": {"M1": {"validation": {"mae", "max_error"}, "ood": {"10": mae, ...},
         "ood_max": {...}, "train_seconds", "compile_seconds", "stopped", "epochs"}, ...}, "ratios": {...},
         "seconds": total}

    ``validation_runs``: a dict to fill with each model's free run on the validation set
    (``{"M1": TrainedModel.predict(...)[0], ...}``), made by the trained model still in memory, whose compiled
    programs the study has already built; :func:`plot_study` draws them without simulating again (loading five
    models from disk to simulate them took 53 s of the torch demo and 17 s of JAX's, 2026-11-29).
    """
    from .casestudy import generate_case_study

    cfg = config or StudyConfig()
    order = [m for m in MODELS if m in cfg.models]
    if "M5" in order and "M4" not in order:
        raise ValueError("M5 needs M4 (its frozen Peltier network comes from the trained M4)")
    say = progress or (lambda msg: None)
    out = Path(out_dir)
    check_output(out, STUDY_DIR, force=force)
    out.mkdir(parents=True, exist_ok=True)
    data_dir = Path(data_dir) if data_dir is not None else out / "data"
    t_start = time.perf_counter()
    say(f"[1/3] case-study data in {data_dir}")
    data = generate_case_study(data_dir, widen=cfg.widen, n_ood=cfg.n_ood, durations=cfg.durations,
                               backend=DATA_BACKEND, progress=lambda m: say("      " + m))
    results: dict = {"config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in cfg.__dict__.items()},
                     "data": {"dir": str(data_dir), "train": data["train"], "val": data["val"],
                              "n_ood": cfg.n_ood, "widen": list(cfg.widen), "cached": data["cached"]},
                     "models": {}}
    say(f"[2/3] training {', '.join(order)} ({cfg.backend}, ≤ {cfg.epochs} epochs"
        + (f", ≤ {cfg.time_limit:g} s of training each" if cfg.time_limit else "") + ")")
    trained = {}
    with _compile_ahead(order, cfg, data):
        for i, name in enumerate(order):
            say(f"      {name} ({MODELS[name][1]}) [{i + 1}/{len(order)}]")
            trained[name], results["models"][name] = _train_model(name, cfg, data, out, say)
    if cfg.n_ood > 0 and cfg.widen:
        say(f"[3/3] out of distribution: {len(cfg.widen)} widenings × {cfg.n_ood} sets × {len(order)} models")
        sets_for = _read_once(data["ood"])
        for name in order:
            results["models"][name].update(_out_of_distribution(trained[name], sets_for(trained[name].network),
                                                                cfg.backend))
            ood, bad = results["models"][name]["ood"], results["models"][name]["ood_diverged"]
            say(f"      {name}: " + ", ".join(f"+{p} %: " + (f"diverged on {len(bad[p])} of {len(data['ood'][p])} sets"
                                                            if p in bad else f"{v * 1e3:.0f} mK")
                                          for p, v in ood.items()))
            for p, reasons in bad.items():
                for reason in reasons:
                    say(f"        +{p} %: {reason}")
    if validation_runs is not None:
        for name in order:
            validation_runs[name] = trained[name].predict(data["val"], backend=cfg.backend)[0]
    results["ratios"] = thesis_ratios(results)
    results["seconds"] = time.perf_counter() - t_start
    write_text_atomic(out / "results.json", json.dumps(results, indent=2, default=float) + "\n")
    return results


def _compile_ahead(order: list[str], cfg: StudyConfig, data: dict):
    """The helper process that compiles the later models' torch programs while the first ones train
    (:mod:`tnn_dsl.fit.compile_ahead`; ``StudyConfig.compile_ahead``): every model after the first. M5's frozen
    Peltier network is M4's trained one, which does not exist before M4 has trained: the helper gives it the
    M4 of its own one-epoch warm-up (the weights are inputs of the compiled graphs, not part of them). A no-op
    context where it does not apply (JAX, one core, ``TNN_COMPILE_AHEAD=0``)."""
    import contextlib

    from ..fit.compile_ahead import CompileAhead, Job, wanted

    later = order[1:]
    on = cfg.compile_ahead if cfg.compile_ahead is not None else wanted(cfg.backend, len(later))
    if not (on and cfg.backend == "torch" and later):
        return contextlib.nullcontext()
    paths = [data["train"]] if isinstance(data["train"], (str, os.PathLike)) else list(data["train"])
    val = data.get("val")
    vals = None if val is None else [val] if isinstance(val, (str, os.PathLike)) else list(val)
    options = {"seed": cfg.seed, **cfg.train_options}
    jobs = [Job(str(_networks_dir() / MODELS[m][0]), [str(p) for p in paths],
                None if vals is None else [str(v) for v in vals], options,
                init_from=later.index("M4") if m == "M5" and "M4" in later else None) for m in later]
    return CompileAhead([j for j, m in zip(jobs, later) if m != "M5" or j.init_from is not None])


def _train_model(name: str, cfg: StudyConfig, data: dict, out: Path, say: Callable[[str], None]):
    """Train one model variant on the study's data → ``(TrainedModel, its results entry)``; progress every 10 s."""
    from ..fit import train
    from ..lang import load

    fname, what = MODELS[name]
    net = _m5_network(out / "models" / "m4") if name == "M5" else load(str(_networks_dir() / fname))
    t0 = time.perf_counter()
    last = [t0]

    def cb(info):
        now = time.perf_counter()
        if now - last[0] >= 10.0:
            last[0] = now
            v = info.get("val_mae")
            vs = f", validation MAE {v * 1e3:.1f} mK" if v is not None and math.isfinite(v) else ""
            say(f"      {name}: epoch {info.get('epoch')}/{info.get('epochs')} ({info.get('phase')}){vs}, "
                f"{now - t0:.0f} s")

    tm = train(net, data["train"], val=data["val"], out=out / "models" / name.lower(), callback=cb,
               backend=cfg.backend, epochs=cfg.epochs, time_limit=cfg.time_limit, lbfgs_iters=cfg.lbfgs_iters,
               seed=cfg.seed, **cfg.train_options)
    val = tm.meta["metrics"].get("validation", {})
    entry = {
        "network": fname, "what": what,
        "validation": {"mae": float(val.get("mae", math.nan)), "max_error": float(val.get("max_error", math.nan))},
        "train": {"mae": float(tm.meta["metrics"]["train"].get("mae", math.nan))},
        "train_seconds": float(tm.meta.get("train_seconds", time.perf_counter() - t0)),
        "compile_seconds": float(tm.meta.get("compile_seconds", math.nan)),
        "stopped": tm.meta.get("stopped"), "epochs": len(tm.meta.get("curve", [])),
        "n_trainable": int(sum(int(np.prod(np.shape(tm.params[k]))) for k, s in
                               tm.compiled(cfg.backend).param_specs.items() if s.trainable)),
    }
    say(f"      {name}: validation MAE {entry['validation']['mae'] * 1e3:.1f} mK, max "
        f"{entry['validation']['max_error'] * 1e3:.0f} mK ({entry['train_seconds']:.0f} s, of which "
        f"{entry['compile_seconds']:.0f} s compiling, {tm.meta.get('stopped')})")
    return tm, entry


def _read_once(ood_files: dict[str, list[str]]) -> Callable[[Any], dict[str, list]]:
    """``sets_for(network)``: the out-of-distribution files of each widening read as experiments for ``network``,
    each file read once for all networks that read it alike (:func:`tnn_dsl.data.columns_read`; the five models
    do). Reading a 2 h file takes about 0.2 s: 40 files for each of five models were 45 s of the demo on either
    backend (2026-11-29)."""
    from ..data import columns_read, read_data

    cache: dict = {}

    def sets_for(net) -> dict[str, list]:
        key = columns_read(net)
        if key not in cache:
            cache[key] = {p: read_data(net, paths) for p, paths in ood_files.items()}
        return cache[key]
    return sets_for


def _out_of_distribution(tm, ood_sets: dict[str, list], backend: str) -> dict:
    """Mean MAE and mean max error over the data sets of each widening (``ood_sets``: widening → files or
    experiments read for ``tm``'s network): ``{"ood": {...}, "ood_max": {...}, "ood_diverged": {widening: [file:
    reason]}}`` (K). A model whose free run leaves the physical range on a set (out of distribution, a learned law
    far outside its training range may) has no error there: that widening's means are NaN and the set is listed
    with the reason, so one diverged run does not stop the study."""
    ood, ood_max, diverged = {}, {}, {}
    for p, sets in ood_sets.items():
        maes, maxes = [], []
        for one, ev in zip(sets, tm.evaluate_each(list(sets), backend=backend)):  # the widening's runs batched
            if isinstance(ev, TnnError):
                name = Path(getattr(one, "path", one)).name
                diverged.setdefault(p, []).append(f"{name}: {ev.diagnostics[0].message}")
                continue
            maes += [e["mae"] for e in ev["experiments"]]
            maxes += [e["max_error"] for e in ev["experiments"]]
        bad = p in diverged
        ood[p] = math.nan if bad or not maes else float(np.mean(maes))
        ood_max[p] = math.nan if bad or not maxes else float(np.mean(maxes))
    return {"ood": ood, "ood_max": ood_max, "ood_diverged": diverged}


def thesis_ratios(results: dict) -> dict[str, dict[str, float]]:
    """``{quantity: {"thesis": x, "ours": y}}`` for every ratio the thesis reports that our run can compute."""
    m = results["models"]

    def v(name):
        return m[name]["validation"]["mae"] if name in m else math.nan

    def growth(name):
        if name not in m or "ood" not in m[name]:
            return math.nan
        ood = m[name]["ood"]
        key = max(ood, key=lambda k: float(k)) if ood else None
        return ood[key] / v(name) if key else math.nan

    ours = {
        "M1/M2 validation MAE": v("M1") / v("M2"),
        "M1/M3 validation MAE": v("M1") / v("M3"),
        "M3 − M2 validation MAE [mK]": (v("M3") - v("M2")) * 1e3,
        "M4 − M1 validation MAE [mK]": (v("M4") - v("M1")) * 1e3,
        "M5 improvement over M4 [%]": (1 - v("M5") / v("M4")) * 100,
        "M5/M3 validation MAE": v("M5") / v("M3"),
        "M4 growth at +40 % (×)": growth("M4"),
        "M5 growth at +40 % (×)": growth("M5"),
        "M1 growth at +40 % (×)": growth("M1"),
        "M2 growth at +40 % (×)": growth("M2"),
        "M3 growth at +40 % (×)": growth("M3"),
    }
    return {k: {"thesis": THESIS[k], "ours": float(ours[k])} for k in THESIS}


def _f(x: float, fmt: str) -> str:
    return "–" if x is None or not math.isfinite(x) else format(x, fmt)


def results_table(results: dict) -> str:
    """The M1–M5 table (Markdown): validation MAE and max (mK), MAE per widening (mK), growth at the widest."""
    m = results["models"]
    widen = [f"{round(float(w) * 100)}" for w in results["data"].get("widen", [])]
    head = "| model | what | trainable | val. MAE [mK] | val. max [mK] | " + " | ".join(f"+{p} % MAE" for p in widen)
    head += " | growth at widest |" if widen else ""
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for name, r in m.items():
        ood = r.get("ood", {})
        cells = [name, r["what"], str(r.get("n_trainable", "")), _f(r["validation"]["mae"] * 1e3, ".1f"),
                 _f(r["validation"]["max_error"] * 1e3, ".0f")]
        diverged = r.get("ood_diverged", {})
        cells += ["diverged" if p in diverged else _f(ood.get(p, math.nan) * 1e3, ".0f") for p in widen]
        if widen:
            g = ood.get(widen[-1], math.nan) / r["validation"]["mae"] if ood else math.nan
            cells.append(_f(g, ".1f") + ("×" if math.isfinite(g) else ""))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def ratios_table(results: dict) -> str:
    lines = ["| quantity | thesis | ours |", "|---|---|---|"]
    for k, r in results["ratios"].items():
        lines.append(f"| {k} | {_f(r['thesis'], '.3g')} | {_f(r['ours'], '.3g')} |")
    return "\n".join(lines)


def plot_study(results: dict, out_dir: str | os.PathLike, validation_runs: dict | None = None) -> list[str]:
    """Write ``ood.png`` (validation MAE and MAE per widening, the thesis's Figure 5.6) and ``validation.png``
    (T_out error through the validation run per model: ``validation_runs`` as :func:`run_study` fills it, else
    each model loaded from the study's model directories and simulated). Returns the paths written."""
    from .. import plots
    from ..fit import load_model

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    fig = plots.ood_growth(results)
    if fig is not None:
        save_figure(fig, out / "ood.png", dpi=110)
        written.append(str(out / "ood.png"))
    models_dir = Path(results.get("models_dir", out.parent / "models"))
    preds = {name: run for name, run in (validation_runs or {}).items() if name in results["models"]}
    for name in results["models"]:
        if name in preds:
            continue
        d = models_dir / name.lower()
        if d.is_dir():
            try:
                tm = load_model(d)
                preds[name] = tm.predict(results["data"]["val"], backend=results["config"].get("backend", "jax"))[0]
            except Exception:  # noqa: BLE001 - a plot must not break the study
                continue
    if preds:
        save_figure(plots.validation_runs(preds), out / "validation.png", dpi=110)
        written.append(str(out / "validation.png"))
    return written
