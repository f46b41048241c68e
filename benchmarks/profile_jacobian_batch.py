"""How many simulations the doctor's forward-difference Jacobian runs at a time (issue 18, ``engine.JAC_BATCH``):
the nominal M1 engine of the case study (4 h of training, 2 h held out, as ``bench_diagnose.py``; the nominal model
fitted first), its 16-column Jacobian taken with each setting in turn, the settings alternating for ``--rounds``
rounds: the first call (compilation included) and the median of five more, and the largest difference from the
first setting's Jacobian. Each setting's programs are compiled afresh (``_Engine.release_programs``).

    python benchmarks/profile_jacobian_batch.py --dir /tmp/cs none 4 6 8

Prints one line per setting and round, then each setting's medians; nothing is written but the generated data.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("settings", nargs="+", help="simulations at a time: an integer, or 'none' (the whole batch)")
    ap.add_argument("--dir", default=None, help="where the case study's data are (generated there if missing)")
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args(argv)

    import tnn_dsl.doctor.engine as E
    from tnn_dsl.doctor.session import _Session
    from tnn_dsl.studies.casestudy import generate_case_study

    data = Path(a.dir or tempfile.mkdtemp(prefix="profile_jacobian_batch_")) / "cs"
    if not (data / "train.csv").is_file():
        generate_case_study(data, widen=(), n_ood=0)
    s = _Session(str(ROOT / "networks" / "peltier_heatpipe" / "m1.thn"), [str(data / "train.csv")],
                 [str(data / "val.csv")], None, "jax", None, top=8, max_rounds=1, output=None, kinds=None,
                 mlp_check=False, mlp_time=60.0, force=False, threads=1)
    s.read_data()
    s.fit_baseline()
    eng = s.eng
    active = list(range(len(eng.cols)))[:16]
    medians: dict[str, list[float]] = {}
    first: dict[str, np.ndarray] = {}
    for rnd in range(a.rounds):
        for v in a.settings:
            E.JAC_BATCH = None if v == "none" else int(v)
            eng.release_programs()
            t = time.perf_counter()
            J = eng.jacobian(active, method="difference")
            t_first = time.perf_counter() - t
            times = []
            for _ in range(5):
                t = time.perf_counter()
                eng.jacobian(active, method="difference")
                times.append(time.perf_counter() - t)
            medians.setdefault(v, []).append(float(np.median(times)))
            first.setdefault(v, J)
            print(f"round {rnd}  {v:>5}: first call {t_first:.2f} s, median {1e3 * np.median(times):.1f} ms",
                  flush=True)
    ref = first[a.settings[0]]
    for v in a.settings:
        diff = float(np.max(np.abs(first[v] - ref)) / np.max(np.abs(ref)))
        print(f"{v:>5}: medians {', '.join(f'{1e3 * m:.1f}' for m in medians[v])} ms; largest difference from "
              f"{a.settings[0]!r} {diff:.2g} (relative)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
