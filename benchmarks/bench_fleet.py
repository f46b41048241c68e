"""Fleet benchmark (issue 19): a generated fleet of TCLab-like boards (``tnn_dsl.fleet.generate``: ±10 %
manufacturing spread on capacities, conductances and heater gains, a share with planted faults of the doctor's
kinds, sensor noise) run through ``tnn_dsl.fleet.run_fleet`` on a local Ray, then scored against the truth:

* **flagged**: precision and recall of the faulty units among the flagged ones (a unit is flagged when the doctor
  accepted a finding or it lies outside the fleet's distribution of a parameter or of the held-out error);
* **kind named**: the share of faulty units whose first accepted finding is the planted element or an
  equation-identical one (a heat load from Q1 at h2 = heater 2's source depending on Q1);
* **healthy parameters**: the share of healthy units' parameter estimates within 1 and 2 standard errors of the
  truth the template can identify (the apparent capacity and conductance at the datasheet heater gain);
* **throughput**: units per minute of ``train`` on a subset, one unit per task and batched (units fitted together
  in one compiled program, ``--batch``), in this process (no Ray) and on a local Ray with 1 and 2 workers; the
  batch size swept in this process; Ray's task overhead (an empty task's round trip); a projection to a 100-node
  cluster.

Writes the ``fleet`` section of BENCHMARKS.md (``--no-write``: print only).

    python benchmarks/bench_fleet.py                         # 200 boards, 20 faulty, 0.02 K (about 30 min)
    python benchmarks/bench_fleet.py --units 12 --faulty 5 --throughput-units 4 --no-write   # a smoke run
    python benchmarks/bench_fleet.py --only throughput --no-write      # the throughput part alone
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from tnn_dsl.fleet import FAULT_KINDS, FleetOptions, generate_fleet, run_fleet, template_path  # noqa: E402
from tnn_dsl.fleet.engine import auto_batch  # noqa: E402

EQUIVALENT = {
    "dependence": [("param_dependence", "U1", "T(h1)")],
    "heat_load": [("heat_load", "Q[h2]", "Q1"), ("param_dependence", "Q_src_h2", "Q1")],
    "sensor_lag": [("sensor_lag", "T1", None)],
    "missing_link": [("missing_link", "h1--h2", None)],
    "sensor_offset": [("sensor_offset", "T1", None)],
}
"""What counts as naming each planted fault: ``(kind, target, dependence or None)`` of the first accepted finding."""


IDENTICAL_COS = 0.999
"""An accepted finding whose linearised output correction has |cos| ≥ this with the planted element's is
equation-identical to it on this data (the doctor lists it under "cannot be told apart")."""


def named(fault: str, findings: list[dict], identical: bool = False) -> bool:
    """Whether the first accepted finding is the planted fault (``identical``: or lists it as indistinguishable,
    |cos| ≥ ``IDENTICAL_COS``: a constant heat at an uncoupled heater and an offset on its sensor are the same
    equations once its initial state is fitted)."""
    acc = [f for f in findings if f.get("accepted")]
    if not acc:
        return False
    f = acc[0]
    deps = [d for d in (f.get("depends_on") or []) if d]
    twins = {t.get("key") for t in (f.get("evidence") or {}).get("indistinguishable_from") or []
             if abs(float(t.get("cos") or 0.0)) >= IDENTICAL_COS}
    for kind, target, dep in EQUIVALENT[fault]:
        if f.get("kind") == kind and f.get("target") == target and (dep is None or deps == [dep]):
            return True
        if identical and f"{kind}:{target}:{dep or ''}" in twins:
            return True
    return False


def score(rep: dict, truth: dict) -> dict:
    units = {u["unit"]: u for u in rep["units"]}
    faulty = {n for n, t in truth["units"].items() if t["fault"]}
    flagged = {n for n, u in units.items() if u["flagged"]}
    tp = len(faulty & flagged)
    kinds: dict[str, list[bool]] = {}
    kinds_eq: dict[str, list[bool]] = {}
    for n in sorted(faulty):
        fault = truth["units"][n]["fault"]
        kinds.setdefault(fault, []).append(named(fault, units[n]["findings"]))
        kinds_eq.setdefault(fault, []).append(named(fault, units[n]["findings"], identical=True))
    within1, within2, total = 0, 0, 0
    for n, t in truth["units"].items():
        if t["fault"] or units[n]["status"] != "ok":
            continue
        for p, v in t["apparent"].items():
            est = units[n]["params"].get(p)
            if not est or est.get("se") is None or est.get("estimate") is None:
                total += 1
                continue
            d = abs(est["estimate"] - v) / est["se"]
            within1 += d <= 1.0
            within2 += d <= 2.0
            total += 1
    return {"faulty": len(faulty), "flagged": len(flagged), "tp": tp,
            "precision": tp / len(flagged) if flagged else float("nan"),
            "recall": tp / len(faulty) if faulty else float("nan"),
            "named": {k: (sum(v), len(v)) for k, v in kinds.items()},
            "named_all": (sum(sum(v) for v in kinds.values()), sum(len(v) for v in kinds.values())),
            "named_eq": {k: (sum(v), len(v)) for k, v in kinds_eq.items()},
            "named_eq_all": (sum(sum(v) for v in kinds_eq.values()), sum(len(v) for v in kinds_eq.values())),
            "within1": within1 / max(total, 1), "within2": within2 / max(total, 1), "n_params": total,
            "false_flags": sorted(flagged - faulty), "missed": sorted(faulty - flagged)}


def ray_overhead(n: int = 200) -> float:
    """Seconds per empty task on a local Ray with 2 CPUs (submitted together, gathered)."""
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    try:
        f = ray.remote(lambda x: x)
        ray.get([f.remote(i) for i in range(20)])  # workers up
        t = time.perf_counter()
        ray.get([f.remote(i) for i in range(n)])
        return (time.perf_counter() - t) / n
    finally:
        ray.shutdown()


def throughput(work: Path, a: argparse.Namespace, say) -> tuple[dict, dict, float]:
    """``tnnc fleet train`` on ``a.throughput_units`` healthy boards: one unit per task and batched, in this process
    and on Ray with 1 and 2 workers; the batch size swept in this process; Ray's task overhead."""
    generate_fleet(work / "sub", n_units=a.throughput_units, n_faulty=0, noise=a.noise, seed=a.seed + 1, force=True)
    thr: dict[str, tuple[float, float]] = {}
    runs = (("in process (no Ray), one unit at a time", 0, 1, True), ("Ray, 1 worker, one unit per task", 1, 1, True),
            ("Ray, 2 workers, one unit per task", 2, 1, True),
            ("Ray, 2 workers, one unit per task, no shared compilation cache", 2, 1, False),
            ("in process, batched (auto)", 0, None, True), ("Ray, 1 worker, batched (auto)", 1, None, True),
            ("Ray, 2 workers, batched (auto)", 2, None, True))
    for label, workers, batch, cache in runs:
        t = time.perf_counter()
        run_fleet(template_path(), work / "sub", work / f"train_{workers}_{batch}_{cache}",
                  options=FleetOptions(mode="train"), workers=workers, force=True, compile_cache=cache, batch=batch)
        dt = time.perf_counter() - t
        if batch is None:
            size = auto_batch(a.throughput_units, workers, FleetOptions(mode="train"))
            n_tasks = -(-a.throughput_units // size)
            label += f": {n_tasks} tasks of up to {-(-a.throughput_units // n_tasks)} units"
        thr[label] = (dt, 60.0 * a.throughput_units / dt)
        say(f"train {a.throughput_units} units, {label}: {dt:.1f} s")
    sweep: dict[int, tuple[float, float]] = {}
    for b in (2, 4, 8, 16, 32):
        if b > a.throughput_units:
            break
        t = time.perf_counter()
        run_fleet(template_path(), work / "sub", work / f"sweep_{b}", options=FleetOptions(mode="train"), workers=0,
                  force=True, batch=b)
        dt = time.perf_counter() - t
        sweep[b] = (dt, 60.0 * a.throughput_units / dt)
        say(f"train {a.throughput_units} units in this process, batches of {b}: {dt:.1f} s")
    return thr, sweep, ray_overhead()


def throughput_lines(a: argparse.Namespace, thr: dict, sweep: dict, overhead: float, proj: tuple | None) -> list[str]:
    lines = [
        f"Throughput of `tnnc fleet train` on {a.throughput_units} healthy boards (fit, standard errors, held-out "
        "error); batched: the units of a task fitted together in one compiled program (`--batch`, "
        "`tnn_dsl.fit.joint`):",
        "",
        "| how | wall time (s) | units per minute |",
        "|---|---|---|",
    ]
    lines += [f"| {k} | {v[0]:.1f} | {v[1]:.1f} |" for k, v in thr.items()]
    if sweep:
        lines += ["", "Batch size, in this process (`--workers 0 --batch N`; the first batch also pays the compiles):",
                  "", "| units per batch | " + " | ".join(str(b) for b in sweep) + " |",
                  "|---|" + "---|" * len(sweep),
                  "| units per minute | " + " | ".join(f"{v[1]:.1f}" for v in sweep.values()) + " |"]
    text = (f"Ray's task overhead (an empty task's round trip, 200 tasks on 2 CPUs): {1e3 * overhead:.2f} ms.")
    if proj is not None:
        per_unit, proj_units_min, cluster_cores = proj
        best = max(v[1] for k, v in thr.items() if k.startswith("Ray, 2 workers, batched"))
        text += (f" Projection, on paper: a 100-node cluster of 16-core machines runs {cluster_cores} units at a "
                 f"time; at {per_unit:.1f} s per diagnosed unit plus the overhead it would diagnose about "
                 f"{proj_units_min:,.0f} units per minute, and at the batched training's {best / 2:.1f} units per "
                 f"minute per worker train about {best / 2 * cluster_cores:,.0f} per minute, if the driver keeps up "
                 "(it writes every result; measured here only up to 2 workers).")
    return lines + ["", text]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--units", type=int, default=200)
    ap.add_argument("--faulty", type=int, default=20)
    ap.add_argument("--noise", type=float, default=0.02)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--throughput-units", type=int, default=20, help="units of the throughput runs (train)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dir", default=None, help="work directory (default: a temporary one)")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--only", choices=("throughput",), default=None, help="run only the throughput part")
    a = ap.parse_args(argv)
    work = Path(a.dir) if a.dir else Path(tempfile.mkdtemp(prefix="bench_fleet_"))
    say = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    thr, sweep, overhead = throughput(work, a, say)
    if a.only == "throughput":
        print("\n".join(throughput_lines(a, thr, sweep, overhead, None)))
        return 0
    t = time.perf_counter()
    truth = generate_fleet(work / "fleet", n_units=a.units, n_faulty=a.faulty, noise=a.noise, seed=a.seed,
                           force=True)
    t_gen = time.perf_counter() - t
    say(f"generated {a.units} boards in {t_gen:.0f} s")

    t = time.perf_counter()
    res = run_fleet(template_path(), work / "fleet", work / "diagnose", options=FleetOptions(mode="diagnose"),
                    workers=a.workers, force=True, progress=lambda s: say(s) if "/" in s.split(":")[0] else None)
    t_diag = time.perf_counter() - t
    sc = score(res.report, truth)
    unit_s = [r.get("seconds") or 0.0 for r in res.rows if r.get("seconds")]

    kinds = ", ".join(f"{k} {v[0]}/{v[1]}" for k, v in sorted(sc["named"].items()))
    kinds_eq = ", ".join(f"{k} {v[0]}/{v[1]}" for k, v in sorted(sc["named_eq"].items()))
    per_unit = float(np.median(unit_s)) if unit_s else float("nan")
    cluster_cores = 100 * 16
    proj_units_min = 60.0 / (per_unit + overhead) * cluster_cores
    lines = [
        f"Fleet: {a.units} generated TCLab-like boards, {a.faulty} with a planted fault (kinds cycling through "
        f"{', '.join(FAULT_KINDS)}), noise {a.noise} K, 1800 training + 900 held-out samples at 1 s per board; "
        f"`tnnc fleet diagnose` on a local Ray with {a.workers} workers (template `networks/tclab/tclab_fleet.thn`).",
        "",
        "| measure | result | target |",
        "|---|---|---|",
        f"| faulty units flagged: precision | {sc['precision']:.3f} ({sc['tp']}/{sc['flagged']}) | ≥ 0.9 |",
        f"| faulty units flagged: recall | {sc['recall']:.3f} ({sc['tp']}/{sc['faulty']}) | ≥ 0.9 |",
        f"| fault kind named (first accepted finding) | {sc['named_all'][0]}/{sc['named_all'][1]} ({kinds}) | ≥ 80 % |",
        f"| ... or named as equation-identical to it (listed by the doctor, \\|cos\\| ≥ {IDENTICAL_COS}) | "
        f"{sc['named_eq_all'][0]}/{sc['named_eq_all'][1]} ({kinds_eq}) | |",
        f"| healthy units' estimates within 2 SE of the truth | {100 * sc['within2']:.1f} % of {sc['n_params']} | "
        "≥ 90 % |",
        f"| ... within 1 SE | {100 * sc['within1']:.1f} % | (68 % if the SEs are right) |",
        f"| wall time, {a.units} units diagnosed | {t_diag / 60:.1f} min ({60 * a.units / t_diag:.1f} units/min) | |",
        f"| per unit (median, fit + diagnosis in one worker) | {per_unit:.1f} s | |",
        "",
        f"Flagged but healthy: {', '.join(sc['false_flags']) or 'none'}; faulty but not flagged: "
        f"{', '.join(sc['missed']) or 'none'}.",
        "",
    ]
    lines += throughput_lines(a, thr, sweep, overhead, (per_unit, proj_units_min, cluster_cores))
    text = "\n".join(lines)
    print(text)
    (work / "score.json").write_text(json.dumps({"score": sc, "throughput": thr, "overhead_s": overhead,
                                                 "t_diag": t_diag}, indent=1, default=str))
    if not a.no_write:
        from _report import write_section

        write_section("fleet", text, path=ROOT / "BENCHMARKS.md", title="Fleets: many boards at once on Ray")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
