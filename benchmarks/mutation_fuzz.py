"""Mutation run (issue 13): edited copies of the shipped networks through ``tnnc check`` → ``tnnc simulate`` (compile
and a short free run), counting what a careless or hostile edit does.

Every mutant is one of the ``networks/`` files with 1–3 random edits: a number replaced (zero, negative, a
million times larger or smaller, 1e308), a unit swapped, an operator changed, ``/ 0``, ``* 0`` or ``- 8 J/K``
appended to a value, a line deleted, duplicated or moved, a name replaced by another name of the file, a
``learn`` clause or a statement of another network inserted. Each mutant goes through the command line in
this process (``tnn_dsl.cli.main``), as a user would run it:

1. ``tnnc check NET``: exit 0 (valid) or 1 (a ``file:line:col`` error); exit 2 is an **internal error**.
2. valid mutants: ``tnnc simulate NET --data D.csv -o OUT.csv`` on a short synthetic record (inputs stepped
   through a plausible range, sensors at 25 °C), with a random backend (torch; JAX for one in twenty), integrator
   and initial-state rule. Exit 0 with a written file, or 1 with a message (e.g. the run left the physical
   range); exit 2 is an internal error, and an exit 0 whose file holds a non-finite or implausible
   temperature (outside −100 … 10 000 °C) is a **silent non-finite output**.

Acceptance: zero internal errors and zero silent non-finite outputs. ``--n`` counts mutants that pass ``check``
(the rejected ones are counted too). Results go to ``--json`` and, with ``--write``, BENCHMARKS.md.

    python benchmarks/mutation_fuzz.py --n 10000 --jobs 2 --write
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import multiprocessing as mp
import os
import random
import re
import shutil
import signal
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
NETWORKS = ROOT / "networks"

NUMBER = re.compile(r"(?<![\w.])(\d+\.?\d*(?:[eE][+-]?\d+)?)")
UNITS = ["J/K", "kJ/K", "K/W", "W/K", "W", "kW", "MW", "degC", "K", "mK", "s", "h", "kg/s", "J/(kg*K)", "%", "W/%",
         "V/K", "ohm", "A", "m^2", "W/(m^2*K)", "1"]
UNIT_TOKEN = re.compile(r"(?<=\d )(" + "|".join(re.escape(u) for u in sorted(UNITS, key=len, reverse=True)) + r")\b")
APPEND = [" / 0", " * 0", " - 8 J/K", " * 1e300", " / 1e-300", " + 1 K", " - 1e6", " * -1"]
OPS = [("*", "/"), ("/", "*"), ("+", "-"), ("-", "+"), ("*", "+")]
NAME = re.compile(r"\b([A-Za-z_][A-Za-z0-9_]*)\b")
KEYWORDS = {"network", "units", "include", "input", "param", "node", "boundary", "R", "G", "source", "sensor",
            "radiation", "peltier", "fluid", "learn", "subnet", "use", "as", "free", "in", "column", "per",
            "experiment", "temperature", "lag", "offset", "mlp", "poly", "linear", "const", "table", "T", "Q"}


def corpus() -> list[Path]:
    """The shipped network files that pass ``check`` (main files; their includes come along)."""
    from tnn_dsl.lang import load

    out = []
    for p in sorted(NETWORKS.rglob("*.thn")):
        if "parts" in p.parts:
            continue
        try:
            load(p)
        except Exception:  # noqa: BLE001 - a part or a file that does not stand alone
            continue
        out.append(p)
    return out


def mutate(text: str, rng: random.Random, donors: list[str]) -> tuple[str, list[str]]:
    """``text`` with 1–3 random edits, and their descriptions."""
    lines = text.split("\n")
    done: list[str] = []
    for _ in range(rng.randint(1, 3)):
        code = [i for i, line in enumerate(lines) if line.strip() and not line.lstrip().startswith("#")]
        if not code:
            break
        i = rng.choice(code)
        line = lines[i]
        kind = rng.choice(["number", "number", "number", "unit", "append", "op", "delete", "duplicate", "move",
                           "rename", "learn", "donor"])
        if kind == "number" and NUMBER.search(line):
            ms = list(NUMBER.finditer(line))
            m = rng.choice(ms)
            x = float(m.group(1))
            new = rng.choice(["0", f"-{m.group(1)}", f"{x * 1e6:g}", f"{x * 1e-6:g}", "1e308", "1e-308", "-0",
                              f"{x * rng.uniform(0.1, 10):.4g}", "0.0", "99999999999"])
            lines[i] = line[:m.start(1)] + new + line[m.end(1):]
        elif kind == "unit" and UNIT_TOKEN.search(line):
            ms = list(UNIT_TOKEN.finditer(line))
            m = rng.choice(ms)
            lines[i] = line[:m.start(1)] + rng.choice(UNITS) + line[m.end(1):]
        elif kind == "append" and "=" in line:
            body, _, comment = line.partition("#")
            words = body.rstrip().split()
            # after the value expression: before `free`/`as`/`column`/`lag` clauses if any
            cut = next((k for k, w in enumerate(words) if w in ("free", "as", "column", "lag", "offset", "in")),
                       len(words))
            lines[i] = " ".join(words[:cut]) + rng.choice(APPEND) + (" " + " ".join(words[cut:]) if words[cut:]
                                                                      else "")
        elif kind == "op":
            a, b = rng.choice(OPS)
            if f" {a} " in line:
                lines[i] = line.replace(f" {a} ", f" {b} ", 1)
        elif kind == "delete":
            del lines[i]
        elif kind == "duplicate":
            lines.insert(i, line)
        elif kind == "move":
            j = rng.randrange(len(lines) + 1)
            lines.insert(j, lines.pop(i))
        elif kind == "rename":
            names = [n for n in NAME.findall(text) if n not in KEYWORDS]
            here = [n for n in NAME.findall(line) if n not in KEYWORDS]
            if names and here:
                lines[i] = re.sub(rf"\b{re.escape(rng.choice(here))}\b", rng.choice(names), line, count=1)
        elif kind == "learn":
            params = re.findall(r"\bas\s+([A-Za-z_]\w*)", text) + re.findall(r"^param\s+(\w+)", text, re.M)
            nodes = re.findall(r"^node\s+(\w+)", text, re.M)
            if params and nodes:
                fn = rng.choice(["const", f"linear({rng.choice(nodes)})", f"mlp({rng.choice(nodes)}; hidden = [4])",
                                 f"poly({rng.choice(nodes)}; degree = 2)",
                                 f"table(T({rng.choice(nodes)}); knots = [0 degC, 50 degC])"])
                lines.append(f"learn {rng.choice(params)} as {fn}")
        elif kind == "donor" and donors:
            donor = [d for d in rng.choice(donors).split("\n") if d.strip() and not d.startswith(("#", "network",
                                                                                                   "include"))]
            if donor:
                lines.insert(i, rng.choice(donor))
        else:
            continue
        done.append(kind)
    return "\n".join(lines), done


def synthetic_csv(net, path: Path, n: int, rng: random.Random) -> None:
    """``n`` samples at 1 s: each input stepped through a plausible range (temperatures 15–35 in the file's unit,
    % 0–100, others 0–scale), each sensor column at 25 (file unit; 298.15 for K)."""
    t = np.arange(n, dtype=float)
    cols: dict[str, np.ndarray] = {"time_s": t}
    unit = net.temperature_unit
    t25 = {"degC": 25.0, "K": 298.15, "degF": 77.0}[unit]
    for inp in net.inputs:
        steps = np.repeat(np.array([rng.random() for _ in range(4)]), int(math.ceil(n / 4)))[:n]
        if inp.is_temperature:
            v = t25 - 10 + 20 * steps
        elif inp.unit and "%" in inp.unit:
            v = 100 * steps
        else:
            v = rng.choice([1.0, 10.0, 0.1]) * steps
        cols[inp.column] = v
    for s in net.sensors:
        if s.column:
            cols[s.column] = np.full(n, t25)
    header = ",".join(cols)
    data = np.stack(list(cols.values()), axis=1)
    path.write_text(header + "\n" + "\n".join(",".join(f"{x:.6g}" for x in row) for row in data) + "\n")


TIMEOUT_S = 120


class _Timeout(BaseException):
    """A command ran longer than ``TIMEOUT_S`` (raised by SIGALRM inside ``main``)."""


def _alarm(signum, frame):
    raise _Timeout()


def _cli(argv: list[str]) -> tuple[int, str]:
    """``tnnc ARGV`` in this process: (exit status, stderr); 3 for an exception escaping ``main``, 4 for a run
    longer than ``TIMEOUT_S``."""
    from tnn_dsl.cli import main

    err = io.StringIO()
    old = signal.signal(signal.SIGALRM, _alarm) if hasattr(signal, "SIGALRM") else None
    if old is not None:
        signal.alarm(TIMEOUT_S)
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        try:
            rc = main(argv)
        except SystemExit as e:  # argparse
            rc = int(e.code or 0)
        except _Timeout:
            rc = 4
        except BaseException:  # noqa: BLE001 - anything escaping main is internal
            rc, err = 3, io.StringIO(traceback.format_exc())
        finally:
            if old is not None:
                signal.alarm(0)
                signal.signal(signal.SIGALRM, old)
    return rc, err.getvalue()


def _silent_bad(out_csv: Path, unit: str) -> str | None:
    """Why the written simulation is not plausible (non-finite or outside −100 … 10 000 °C), else None."""
    try:
        raw = np.genfromtxt(out_csv, delimiter=",", names=True)
    except Exception as e:  # noqa: BLE001
        return f"unreadable output: {e}"
    names = [n for n in (raw.dtype.names or ()) if not n.startswith("time")]
    if not names:
        return None
    vals = np.stack([np.atleast_1d(raw[n]) for n in names], axis=1)
    k = {"degC": 273.15, "K": 0.0, "degF": None}[unit]
    vals_k = vals + k if k is not None else (vals - 32) * 5 / 9 + 273.15
    if not np.all(np.isfinite(vals_k)):
        return "non-finite value written"
    if vals_k.min() < 173.15 or vals_k.max() > 10273.15:
        return f"implausible temperature written ({vals_k.min():.4g} … {vals_k.max():.4g} K)"
    return None


def _outcome(rc: int, err: str, stage: str, refused: str) -> dict:
    """The record of a non-zero exit: ``refused`` (exit 1, with the message's first line), a timeout (4) or an
    internal error of ``stage`` (anything else, with the end of its report)."""
    if rc == 4:
        return {"outcome": "timed out"}
    if rc != 1:
        return {"outcome": f"internal error ({stage})", "message": err[-2000:]}
    first = next((line for line in err.splitlines() if "error:" in line), err[-300:])
    return {"outcome": refused, "message": first}


def run_one(args: tuple[int, int, str]) -> dict:
    """One mutant: seed, index into the corpus, work directory. Returns its record."""
    seed, work = args[0], Path(args[2])
    rng = random.Random(seed)
    files = corpus_cached()
    src = files[args[1] % len(files)]
    texts = donor_texts()
    text, edits = mutate(src.read_text(), rng, texts)
    d = work / f"m{seed}"
    shutil.copytree(src.parent, d, dirs_exist_ok=True)
    net_path = d / src.name
    net_path.write_text(text)
    rec: dict = {"seed": seed, "source": str(src.relative_to(ROOT)), "edits": edits}
    t0 = time.perf_counter()
    rc, err = _cli(["check", "-q", str(net_path)])
    rec["check"] = rc
    if rc != 0:
        rec.update(_outcome(rc, err, "check", "rejected by check"))
    else:
        from tnn_dsl.lang import load

        net = load(net_path)
        data = d / "data.csv"
        synthetic_csv(net, data, rng.choice([30, 60, 120]), rng)
        backend = "jax" if rng.random() < 0.05 else "torch"
        integ = rng.choice(["rk4", "rk4", "expeuler", "euler"])
        init = rng.choice(["measured", "steady", "estimate"])
        out = d / "out.csv"
        rc2, err2 = _cli(["simulate", str(net_path), "--data", str(data), "-o", str(out), "--backend", backend,
                          "--integrator", integ, "--init", init])
        rec.update({"simulate": rc2, "backend": backend, "integrator": integ, "init": init})
        if rc2 != 0:
            rec.update(_outcome(rc2, err2, "simulate", "stopped with a message"))
        else:
            why = _silent_bad(out, net.temperature_unit) if out.exists() else "exit 0 but no output written"
            rec["outcome"] = "silent non-finite output" if why else "simulated"
            if why:
                rec["message"] = why
    rec["seconds"] = time.perf_counter() - t0
    if rec["outcome"].startswith(("internal", "silent", "timed")):
        keep = work / "failures"
        keep.mkdir(exist_ok=True)
        shutil.copy(net_path, keep / f"m{seed}_{src.name}")
    shutil.rmtree(d, ignore_errors=True)
    return rec


_CORPUS: list[Path] | None = None
_DONORS: list[str] | None = None


def corpus_cached() -> list[Path]:
    global _CORPUS
    if _CORPUS is None:
        _CORPUS = corpus()
    return _CORPUS


def donor_texts() -> list[str]:
    global _DONORS
    if _DONORS is None:
        _DONORS = [p.read_text() for p in corpus_cached()]
    return _DONORS


def _init_worker() -> None:
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover
        pass
    import warnings

    warnings.filterwarnings("ignore")


def run(n_valid: int, seed: int = 0, jobs: int = 1, max_total: int | None = None, work: Path | None = None,
        progress: bool = False) -> dict:
    """Mutants until ``n_valid`` of them pass ``check`` (at most ``max_total``, default 4·n_valid)."""
    work = Path(work or tempfile.mkdtemp(prefix="tnn_mutation_"))
    work.mkdir(parents=True, exist_ok=True)
    max_total = max_total or 4 * n_valid
    records: list[dict] = []
    t0 = time.perf_counter()
    n_files = len(corpus_cached())
    ctx = mp.get_context("spawn") if jobs > 1 else None
    tasks = ((seed * 1_000_003 + i, i % n_files, str(work)) for i in range(max_total))
    pool = ctx.Pool(jobs, initializer=_init_worker) if ctx else None
    try:
        it = pool.imap_unordered(run_one, tasks, chunksize=4) if pool else map(run_one, tasks)
        if not pool:
            _init_worker()
        for rec in it:
            records.append(rec)
            n_ok = sum(r["check"] == 0 for r in records)
            if progress and len(records) % 200 == 0:
                print(f"{len(records)} mutants, {n_ok} valid, {time.perf_counter() - t0:.0f} s", file=sys.stderr,
                      flush=True)
            if n_ok >= n_valid:
                break
    finally:
        if pool:
            pool.terminate()
    return summarise(records, time.perf_counter() - t0, jobs, work)


def summarise(records: list[dict], seconds: float, jobs: int, work: Path) -> dict:
    outcomes: dict[str, int] = {}
    for r in records:
        outcomes[r["outcome"]] = outcomes.get(r["outcome"], 0) + 1
    bad = [r for r in records if r["outcome"].startswith(("internal", "silent", "timed"))]
    stopped: dict[str, int] = {}
    for r in records:
        if r["outcome"] == "stopped with a message":
            key = re.sub(r"[-+]?\d[\d.e+-]*", "#", r.get("message", ""))[:90]
            stopped[key] = stopped.get(key, 0) + 1
    return {
        "mutants": len(records), "valid": sum(r["check"] == 0 for r in records), "outcomes": outcomes,
        "internal_errors": sum(r["outcome"].startswith("internal") for r in records),
        "silent_non_finite": sum(r["outcome"].startswith("silent") for r in records),
        "timed_out": sum(r["outcome"] == "timed out" for r in records),
        "by_backend": {b: sum(r.get("backend") == b for r in records) for b in ("torch", "jax")},
        "stopped_messages": dict(sorted(stopped.items(), key=lambda kv: -kv[1])[:12]),
        "failures": bad[:50], "seconds": seconds, "jobs": jobs, "failures_dir": str(work / "failures"),
        "corpus": [str(p.relative_to(ROOT)) for p in corpus_cached()],
    }


def markdown(s: dict) -> str:
    o = s["outcomes"]
    lines = [
        f"{s['mutants']} edited networks ({len(s['corpus'])} shipped files, 1–3 random edits each), "
        f"{s['valid']} of them valid (`tnnc check` exit 0), each valid one simulated with `tnnc simulate` "
        f"(torch {s['by_backend']['torch']}, JAX {s['by_backend']['jax']}; rk4/expeuler/euler; "
        f"measured/steady/estimate initial states) in {s['seconds']:.0f} s on {s['jobs']} processes.",
        "",
        "| outcome | mutants |",
        "|---|---:|",
    ]
    for k in ("rejected by check", "simulated", "stopped with a message", "internal error (check)",
              "internal error (simulate)", "silent non-finite output", "timed out"):
        lines.append(f"| {k} | {o.get(k, 0)} |")
    lines += ["", f"**Internal errors: {s['internal_errors']}. Silent non-finite or implausible outputs: "
              f"{s['silent_non_finite']}.** (Acceptance of issue 13: both zero.) Runs longer than {TIMEOUT_S} s: "
              f"{s['timed_out']}."]
    if s["stopped_messages"]:
        lines += ["", "Most frequent messages of valid mutants whose run was stopped (numbers as #):", ""]
        lines += [f"- {n}× `{m}`" for m, n in s["stopped_messages"].items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=10000, help="valid mutants to run (default 10000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=max(1, (os.cpu_count() or 1)))
    ap.add_argument("--json", default=None, help="write the summary (with the failures) here")
    ap.add_argument("--work", default=None, help="work directory (failing mutants are kept in WORK/failures)")
    ap.add_argument("--write", action="store_true", help="write the section `mutation` of BENCHMARKS.md")
    a = ap.parse_args(argv)
    s = run(a.n, a.seed, a.jobs, work=Path(a.work) if a.work else None, progress=True)
    md = markdown(s)
    print(md)
    for f in s["failures"][:10]:
        print(f"\n--- seed {f['seed']} {f['source']} {f['edits']}: {f['outcome']}\n{f.get('message', '')[-1500:]}")
    if a.json:
        Path(a.json).write_text(json.dumps(s, indent=1))
    if a.write:
        sys.path.insert(0, str(Path(__file__).parent))
        from _report import write_section

        write_section("mutation", md, path=ROOT / "BENCHMARKS.md", title="Mutation run: edited networks through "
                      "check, compile and a short rollout")
    return 0 if s["internal_errors"] == 0 and s["silent_non_finite"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
