"""Several units of one network fitted in one compiled program (:mod:`tnn_dsl.fit.joint`, the fleet's batched path).

* The joint loss with each file's values gathered per window (one vectorised rollout, JAX) equals the loss with
  one rollout per file, value and gradient, to round-off.
* Each unit's estimates from the joint fit lie within a tenth of a standard error of the unit fitted alone, with
  the same standard errors, on both backends; each unit's model saves, loads and predicts as a model trained alone.
* What cannot be fitted jointly is said, not attempted.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import tnn_dsl
from tnn_dsl.compiler import compile as compile_network
from tnn_dsl.data import as_experiments
from tnn_dsl.fit import load_model, train
from tnn_dsl.fit.config import load_config
from tnn_dsl.fit.joint import joint_fit_problem, joint_network, train_jointly
from tnn_dsl.fit.trainer import _Trainer
from tnn_dsl.fleet import generate_fleet, template_path

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def boards(tmp_path_factory):
    """Three generated TCLab-like boards (300 training and 150 held-out samples each; one with a sensor lag)."""
    out = tmp_path_factory.mktemp("boards") / "fleet"
    generate_fleet(out, n_units=3, n_faulty=1, n_train=300, n_val=150, seed=3, kinds=("sensor_lag",))
    net = tnn_dsl.load(str(template_path()))
    return net, [(as_experiments(net, [str(out / u / "train.csv")]), as_experiments(net, [str(out / u / "val.csv")]))
                 for u in sorted(p.name for p in out.iterdir() if p.is_dir())]


def _trainer(net, exps, vectorise: bool):
    cfg = load_config(None, backend="jax", val_fraction=0.0)
    model = compile_network(net, backend="jax")
    tr = _Trainer(net, exps, [], cfg, model)
    tr.vectorise_files = vectorise
    params = tr.initial_params()
    nom, nom_bp, runs = tr.nominal_runs(params)
    tr.set_stats(params, nom, nom_bp, runs)
    tr.layout(params)
    tr.build_batches(runs)
    return tr


def test_one_vectorised_rollout_for_every_file_is_the_loss_of_one_rollout_per_file(boards):
    net, sets = boards
    joint = joint_network(net)
    exps = [t[0] for t, _v in sets]
    loop, vec = _trainer(joint, exps, False), _trainer(joint, exps, True)
    assert vec.pe_vmap and not loop.pe_vmap
    assert len(vec.groups) < len(loop.groups)  # the files' windows share groups
    rng = np.random.default_rng(0)
    z = np.concatenate([loop.z_from_params(loop.params0), np.zeros(loop.n_x0 * len(loop.model.state_names))])
    z = z + 0.05 * rng.standard_normal(z.shape)
    values = []
    for tr in (loop, vec):
        data, statics = tr.batch_arrays(None)
        values.append(tr.ops.value_and_grad(tr.make_loss(statics))(z, data))
    (v0, g0), (v1, g1) = values
    assert np.isfinite(v0) and v1 == pytest.approx(v0, rel=1e-12)
    np.testing.assert_allclose(g1, g0, rtol=1e-9, atol=1e-12 * np.abs(g0).max())


# torch (one rollout per unit, the loop the vectorised rollout is checked against above) is slow: 100 s
@pytest.mark.parametrize("backend", ["jax", pytest.param("torch", marks=pytest.mark.slow)])
def test_each_unit_of_a_joint_fit_is_the_unit_fitted_alone(boards, backend, tmp_path):
    net, sets = boards
    models = train_jointly(net, sets, backend=backend, epochs=60)
    assert len(models) == 3
    for k, ((tr, va), tm) in enumerate(zip(sets, models)):
        alone = train(net, tr, None, backend=backend, epochs=60, val_fraction=0.0)
        rows = {r["name"]: r for r in alone.meta["estimation"]["rows"]}
        joint = {r["name"]: r for r in tm.meta["estimation"]["rows"]}
        assert set(rows) == set(joint)
        for name, r in rows.items():
            j = joint[name]
            assert j["status"] == r["status"], (k, name)
            if r["se"] is None:
                assert j["estimate"] == pytest.approx(r["estimate"], rel=1e-3), (k, name)
                continue
            assert abs(j["estimate"] - r["estimate"]) <= 0.1 * r["se"], (k, name, j["estimate"], r["estimate"])
            assert j["se"] == pytest.approx(r["se"], rel=0.05), (k, name)
        assert tm.meta["joint"]["sets"] == 3 and tm.meta["joint"]["index"] == k
        held_out = tm.meta["metrics"]["validation"]["mae"]
        assert held_out == pytest.approx(alone.evaluate(va)["mae"], rel=0.02)
        # saved and loaded as any model: the same held-out error
        back = load_model(tm.save(tmp_path / f"unit{k}"))
        assert back.evaluate(va)["mae"] == pytest.approx(held_out, rel=1e-9)
        assert not back.network.params[0].per_experiment and back.meta["joint"]["sets"] == 3


def test_what_cannot_be_fitted_jointly_is_said(boards):
    net, sets = boards
    assert joint_fit_problem(net, sets) is None
    assert "at least two" in joint_fit_problem(net, sets[:1])
    two_files = [(sets[0][0] + sets[1][0], sets[0][1]), sets[2]]
    assert "2 training files" in joint_fit_problem(net, two_files)
    m1 = tnn_dsl.load(str(ROOT / "networks" / "peltier_heatpipe" / "m4.thn"))
    assert "learned functions" in joint_fit_problem(m1, sets)
    with pytest.raises(tnn_dsl.TnnError, match="no joint fit: a joint fit needs at least two"):
        train_jointly(net, sets[:1])
