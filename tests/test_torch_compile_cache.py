"""torch's compiled-graph caches keep the compiled scans (``tnn_dsl.compiler.model.TORCH_CACHE_SCANS``, issue 18).

torch 2.13 bypasses its FX graph cache and AOT autograd's cache for a graph holding a higher-order operator unless it
is marked cacheable; the model's scans are marked. Marking is only safe when the cache key tells bodies apart: a
body's captured float or constant tensor changed must compile anew and compute the new values, and a value passed in
as a tensor must not be part of the key. Each check runs in a child process with an empty
``TORCHINDUCTOR_CACHE_DIR`` of its own (``torch._dynamo.reset()`` between compilations, so the second one goes to
inductor's caches instead of dynamo's), so that the test process's own caches are left alone."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[1]

RAW_SCANS = r"""
import json, sys, torch
from torch._higher_order_ops import scan
from torch._dynamo.utils import counters
from tnn_dsl.compiler.model import inductor_options

def run(k, w, const):
    torch._dynamo.reset()
    w = torch.tensor([w], dtype=torch.float64)
    c = torch.tensor([const, 1.0, 2.0], dtype=torch.float64)

    def roll(T0, xs):
        def body(T, x):
            Tn = T * k + x[0] * w + torch.tensor([const, 1.0, 2.0], dtype=torch.float64)
            return Tn, Tn.clone()
        return scan(body, T0, [xs])[1]

    T0 = torch.ones(3, dtype=torch.float64)
    xs = torch.linspace(0.0, 1.0, 12, dtype=torch.float64).reshape(4, 3)
    before = dict(counters["inductor"])
    out = torch.compile(roll, fullgraph=True, options=inductor_options())(T0, xs)
    T, ref = T0, []
    for x in xs:
        T = T * k + x * w + c
        ref.append(T)
    hits = counters["inductor"]["fxgraph_cache_hit"] - before.get("fxgraph_cache_hit", 0)
    return {"hit": hits > 0, "exact": bool(torch.equal(out, torch.stack(ref)))}

cases = [(2.0, 1.0, 0.5), (2.0, 1.0, 0.5), (3.0, 1.0, 0.5), (2.0, 5.0, 0.5), (2.0, 1.0, 7.0)]
print("RESULT " + json.dumps([run(*c) for c in cases]))
"""

MODEL = r"""
import json, sys, numpy as np, torch
from torch._dynamo.utils import counters
import tnn_dsl

src = open(sys.argv[1]).read()
out = []
for scale in (1.0, 1.0, 1.3):
    torch._dynamo.reset()
    model = tnn_dsl.compile(tnn_dsl.loads(src, "two.thn"), "torch", torch_compile=True)
    p_np = {k: v * (scale if k == "R_b_amb" else 1.0) for k, v in model.to_numpy(model.init_params(0)).items()}
    p = {k: v.requires_grad_(True) for k, v in model.from_numpy(p_np).items()}
    T0 = torch.full((3, 2), 293.15, dtype=torch.float64)
    U = torch.stack([torch.linspace(0.0, 20.0, 50, dtype=torch.float64).expand(3, 50),
                     torch.full((3, 50), 293.15, dtype=torch.float64)], -1)
    before = dict(counters["inductor"])
    s, y = model.rollout(p, T0, U, 1.0)
    y.sum().backward()
    hits = counters["inductor"]["fxgraph_cache_hit"] - before.get("fxgraph_cache_hit", 0)
    out.append({"hits": hits, "y": y.detach().numpy().tolist(),
                "grad": {k: v.grad.numpy().tolist() for k, v in p.items() if v.grad is not None}})
print("RESULT " + json.dumps(out))
"""

TWO_NODES = """\
network two "two capacities heated through a resistance"
units temperature = K
input P  : [W]
input Ta : temperature
node a  C = 50 J/K
node b  C = 80 J/K
boundary amb = Ta
source a = P
R a -- b   = 0.5 K/W
R b -- amb = 2 K/W  free  as R_b_amb
sensor T_a = a
"""


def _child(code: str, tmp_path: Path, *args: str) -> list:
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(tmp_path / "inductor"), "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, timeout=600)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stderr[-3000:]
    return json.loads(lines[-1][len("RESULT "):])


def test_a_marked_scan_is_reused_only_when_its_body_is_the_same(tmp_path):
    first, again, new_float, new_input, new_constant = _child(RAW_SCANS, tmp_path)
    assert all(r["exact"] for r in (first, again, new_float, new_input, new_constant))
    assert not first["hit"]
    assert again["hit"]  # the same body: inductor's cache, no compilation
    assert not new_float["hit"]  # a captured float is in the body's code
    assert new_input["hit"]  # a value passed in as a tensor is not part of the key
    assert not new_constant["hit"]  # a constant tensor's values are


def test_a_networks_scans_compile_once_across_models_and_parameter_values(tmp_path):
    net = tmp_path / "two.thn"
    net.write_text(TWO_NODES)
    first, again, other = _child(MODEL, tmp_path, str(net))
    assert first["hits"] == 0
    assert again["hits"] >= 2  # the forward and the adjoint scan, from the cache
    assert other["hits"] >= 2  # new parameter values are inputs
    np.testing.assert_array_equal(np.asarray(again["y"]), np.asarray(first["y"]))
    for k in first["grad"]:
        np.testing.assert_array_equal(np.asarray(again["grad"][k]), np.asarray(first["grad"][k]))
    assert not np.allclose(np.asarray(other["y"]), np.asarray(first["y"]))
