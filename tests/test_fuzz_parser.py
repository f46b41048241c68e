"""Hypothesis mutations of valid files through `tnnc check` in-process: exit 0, or exit 1 with a first
line `<file>:L:C: error: `; never exit 2 (internal error) or a traceback; bounded time."""

from __future__ import annotations

import re
import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tnn_dsl.cli import main

VALID = [
    '''network tclab "two heaters"
units temperature = degC
input Q1 : [%]  column "Q1_pct"
param Ta  = 23 degC    free in [15 degC, 30 degC]
param a1  = 0.01 W/%   free in [0, 0.05 W/%]
boundary amb = Ta
node h1 "heater 1"  C = 4 J/K  free
node h2 "heater 2"  C = 4 J/K  free
G h1 -- amb = 0.05 W/K  free  as U1
G h2 -- amb = 0.05 W/K  free  as U2
G h1 -- h2  = 0.02 W/K  free  as U12
source h1 = a1 * Q1
sensor T1 = h1  lag 20 s free  column "T1_degC"
radiation h1 -- amb  area = 1e-3 m^2  emissivity = 0.9 free
''',
    '''network pe "Peltier"
units temperature = degC
input I : [A]
input u1 : [1]
input Tf1 : temperature
node ph C = 40 J/K
node pc C = 40 J/K
node hx1 C = 300 J/K
node 3 C = 60 J/K
boundary amb = 22 degC
R ph -- amb = 0.3 K/W
R pc -- hx1 = 0.05 K/W
R hx1 -- 3 = 0.2 K/W as R_hp1
G 3 -- amb = table(mean(T3, amb); 0 degC: 2.0 W/K, 50 degC: 2.4 W/K)
param R2 = 0.2 K/W * (1 + 1.5*(u1 - 0.5) - 0.02 1/K * (mean(T(hx1), T3) - 25 degC))
peltier pe hot = ph cold = pc current = I seebeck = 0.05 V/K free resistance = 2 ohm R_internal = 1.5 K/W
fluid f1 through hx1 inlet = Tf1 mdot = 0.002 kg/s cp = 4186 J/(kg*K) UA = 5 W/K
sensor T_out = hx1
learn R_hp1 as mlp(T3, hx1, u1; hidden = [4], activation = sigmoid)
learn pe.Q_hot, pe.Q_cold as linear(ph, pc, I)
subnet box(C0)
node n C = C0
G n -- amb = 1 W/K
end
use box(C0 = 3 J/K) as b1
''',
]

HEAD_RE = re.compile(r"^(?P<file>.+):\d+:\d+: (error|warning): ")
TOKEN_RE = re.compile(r'"[^"\n]*"|[A-Za-z_][A-Za-z0-9_.]*|[0-9.]+(?:[eE][+-]?\d+)?|--|\S|\n')


def tokens(text):
    return TOKEN_RE.findall(text)


def join(toks):
    out = []
    for t in toks:
        out.append(t if t == "\n" else t + " ")
    return "".join(out)


@st.composite
def mutated(draw):
    text = draw(st.sampled_from(VALID))
    kind = draw(st.sampled_from(["delete", "duplicate", "swap", "truncate", "bytes", "empty", "huge", "nonutf8",
                                 "replace"]))
    if kind == "empty":
        return b""
    if kind == "truncate":
        return text.encode()[: draw(st.integers(0, len(text)))]
    if kind == "bytes":
        data = bytearray(text.encode())
        for _ in range(draw(st.integers(1, 5))):
            i = draw(st.integers(0, len(data) - 1))
            data[i] = draw(st.integers(0, 255))
        return bytes(data)
    if kind == "nonutf8":
        data = text.encode()
        i = draw(st.integers(0, len(data)))
        return data[:i] + draw(st.sampled_from([b"\xff", b"\xc3", b"\xe2\x82", b"\x80\x80"])) + data[i:]
    if kind == "huge":
        return re.sub(r"\b\d+(\.\d+)?\b", draw(st.sampled_from(["1e999", "1e308", "9" * 400, "0", "1e-999"])),
                      text, count=draw(st.integers(1, 3))).encode()
    toks = tokens(text)
    n = draw(st.integers(1, 4))
    for _ in range(n):
        if not toks:
            break
        i = draw(st.integers(0, len(toks) - 1))
        if kind == "delete":
            del toks[i]
        elif kind == "duplicate":
            toks.insert(i, toks[i])
        elif kind == "swap":
            j = draw(st.integers(0, len(toks) - 1))
            toks[i], toks[j] = toks[j], toks[i]
        else:
            toks[i] = draw(st.sampled_from(["(", ")", "[", "]", ",", ";", ":", "=", "--", "free", "as", "learn",
                                            "node", "end", "subnet", "T", "Q", "%", "1/K", "degC", '"x"', "\n",
                                            "-", "^", "table", "use", "include", "@", "'"]))
    return join(toks).encode("utf-8")


def run_check(tmp_path, data, capsys):
    p = tmp_path / "m.thn"
    p.write_bytes(data)
    t0 = time.perf_counter()
    status = main(["check", "-q", str(p)])
    elapsed = time.perf_counter() - t0
    out = capsys.readouterr()
    assert elapsed < 10.0, "check took too long"
    assert status in (0, 1), out.err
    assert "Traceback" not in out.err and "internal error" not in out.err, out.err
    if status == 1:
        first = out.err.splitlines()[0]
        m = HEAD_RE.match(first)
        assert m is not None, first
        assert m.group("file") == str(p), first


@settings(max_examples=60, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=mutated())
def test_mutations_never_crash(tmp_path, capsys, data):
    run_check(tmp_path, data, capsys)


@pytest.mark.slow
@settings(max_examples=1000, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=mutated())
def test_mutations_never_crash_long(tmp_path, capsys, data):
    run_check(tmp_path, data, capsys)


@pytest.mark.parametrize("data", [b"", b"\n\n", b"# only\n", b"\xff\xfe", b"network x\n\x00\n", b"(" * 5000,
                                  b"network x\nparam p = " + b"(" * 3000 + b"1" + b")" * 3000 + b"\n"])
def test_edge_files(tmp_path, capsys, data):
    run_check(tmp_path, data, capsys)


def test_valid_seeds_pass(tmp_path, capsys):
    for text in VALID:
        p = tmp_path / "ok.thn"
        p.write_text(text)
        assert main(["check", str(p)]) == 0, capsys.readouterr().err
