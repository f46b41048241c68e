"""A candidate fit continued on a network of its own (issue 18: ``_Session.own_network``) reaches what it reaches on
the round's shared network: the same findings, word for word, and the same values to round-off. The values move
column by column, by the candidate's own columns, not by name and index: a learned function's weight matrix has
one row per input its candidates read, so the shared network of a second round (where the accepted law's function
also reads the new candidates' inputs) lays it out differently from a network holding one candidate."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

import tnn_dsl
import tnn_dsl.doctor.session as session
from tnn_dsl.studies.planted import plant

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TCLAB = os.path.join(ROOT, "networks", "tclab", "tclab.thn")
BOUNDS = {"Q1": (0.0, 1.0), "Q2": (0.0, 1.0)}  # heater fraction (SI of [%])


def _planted():
    net = tnn_dsl.load(TCLAB)
    return net, plant(net, BOUNDS, "param_dependence", "U1", "T(h1)", 0.4, noise=0.01, seed=3, n_train=700,
                      n_val=400, hold=(20, 150), backend="jax")


def test_fits_continue_on_their_own_networks_in_both_rounds(monkeypatch):
    """The fast variant (CI; the option is off by default): with it on, both rounds continue fits on networks of
    their own — each was taken only after it reproduced the shared network's training SSE to 1e-9, so the values
    moved over exactly — and the planted dependence is accepted."""
    net, pl = _planted()
    monkeypatch.setattr(session, "OWN_NETWORK_RATIO", 1.5)
    said: list[str] = []
    d = tnn_dsl.diagnose(net, pl.train, pl.val, top=3, max_rounds=2, mlp_check=False, backend="jax", threads=1,
                         progress=said.append)
    assert sum("on its own network" in s for s in said) >= 2, said
    acc = [f for f in d.to_dict()["findings"] if f["accepted"]]
    assert acc and "U1" in acc[0]["words"] and "T(h1)" in acc[0]["words"], d.summary()


@pytest.mark.slow
def test_a_fit_continued_on_its_own_network_gives_the_shared_networks_result(monkeypatch):
    net, pl = _planted()
    runs, lines = [], []
    for ratio in (math.inf, 1.5):  # off (the default), and on wherever the shared network holds 1.5× the columns
        monkeypatch.setattr(session, "OWN_NETWORK_RATIO", ratio)
        said: list[str] = []
        runs.append(tnn_dsl.diagnose(net, pl.train, pl.val, top=3, max_rounds=2, mlp_check=False, backend="jax",
                                     threads=1, progress=said.append))
        lines.append(said)
    assert not any("on its own network" in s for s in lines[0])
    assert sum("on its own network" in s for s in lines[1]) >= 2, lines[1]  # both rounds continued somewhere
    a, b = (d.to_dict() for d in runs)
    assert [f["words"] for f in a["findings"]] == [f["words"] for f in b["findings"]], (runs[0].summary(),
                                                                                         runs[1].summary())
    assert [f["accepted"] for f in a["findings"]] == [f["accepted"] for f in b["findings"]]
    assert runs[0].extended_text == runs[1].extended_text
    np.testing.assert_allclose(a["extended"]["val_mae"], b["extended"]["val_mae"], rtol=1e-6)
