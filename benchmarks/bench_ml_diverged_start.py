"""One likelihood fit of the model doctor on real data, timed run by run: the candidate "a heat capacity behind the
solar gain" of Bacher & Madsen's Ti (the network the doctor builds, below), fitted by
``tnn_dsl.doctor.likelihood.LikelihoodSelection.fit`` as the doctor fits it under ``--objective ml`` (an output-error
fit, then ``fit_ml`` from that fit and from the values written in the network). Each L-BFGS-B run prints its
evaluations, end value, iterations and seconds. Its start from the written values ends on a diverged filter: before
1e5de20 the fit restarted from there and crawled 1000 iterations (issue 18).

Data (third-party, real): ``../shared/data/bacher_madsen_inputPRBS1.csv`` (DTU's CTSM-R building example, see
``../shared/data/README.md``), the whole file.

    python benchmarks/bench_ml_diverged_start.py                 # JAX
    python benchmarks/bench_ml_diverged_start.py --backend torch
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import scipy.optimize

import tnn_dsl
from tnn_dsl.compiler.integrators import StepSizeWarning
from tnn_dsl.doctor.likelihood import LikelihoodSelection

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "bacher_madsen_inputPRBS1.csv"

NETWORK = """\
network building_ti "Bacher & Madsen 2011, model Ti: one interior node"
units temperature = degC

input Ta : temperature  "outdoor temperature"
input Ps : [kW/m^2]  "global solar irradiance"
input Ph : [kW]  "electric heating power"

param Aw = 11 m^2  free in [0 m^2, 50 m^2]  "effective window area (solar gain per irradiance)"

boundary amb "outdoor" = Ta

node ti "interior (air, furniture, inner walls)"  C = 2.9 kWh/K  free in [0.1 kWh/K, 50 kWh/K]

R ti -- amb = 5.4 K/kW  free in [0.5 K/kW, 50 K/kW]  as Ria

source m_Q_solar = Aw * Ps  as Q_solar
source ti = Ph  as Q_heat

node m_Q_solar "heat capacity behind source Q_solar"  C = 0.295172 kWh/K  free in [0.0029 kWh/K, 2900 kWh/K]

R m_Q_solar -- ti = 0.113666 K/kW  free in [0.0054000000000000003 K/kW, 5400 K/kW]  as R_m_Q_solar

sensor Ti = ti  column "yTi"
"""
"""The doctor's candidate as ``tnn_dsl.diagnose("networks/building/ti.thn", [DATA], objective="ml",
kinds=("source_mass",))`` built it (2026-12-06; its description shortened)."""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="jax", choices=["jax", "torch"])
    args = ap.parse_args()
    warnings.simplefilter("ignore", StepSizeWarning)
    real = scipy.optimize.minimize

    def timed(fun, x0, **kw):
        n = [0]

        def counted(z):
            n[0] += 1
            return fun(z)
        t = time.perf_counter()
        r = real(counted, x0, **kw)
        print(f"  L-BFGS-B run: {n[0]} evaluations, end {float(r.fun):.4f}, {int(r.nit)} iterations, "
              f"{time.perf_counter() - t:.1f} s ({str(r.message)[:40]})", flush=True)
        return r

    scipy.optimize.minimize = timed  # fit_ml imports it at the call
    net = tnn_dsl.loads(NETWORK, "q_solar.thn")
    exps = tnn_dsl.read_data(net, [str(DATA)])
    t = time.perf_counter()
    fit = LikelihoodSelection(exps, [], args.backend, None, print).fit("q_solar", net)
    print(f"{args.backend}: log L {fit.loglik:.2f} in {time.perf_counter() - t:.1f} s")


if __name__ == "__main__":
    main()
