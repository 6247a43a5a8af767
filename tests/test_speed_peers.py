"""benchmarks/speed/peers.py: its contenders train the same update (the same losses from the same parameters on the
same batches), and the script itself, at its tiniest, writes the JSON its results README describes."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from helpers import ROOT, load_benchmark

peers = load_benchmark("speed/peers")
TOTAL = 2  # the cosine schedule's length: the actor's rate is 3e-4, then 1.5e-4, then 0
UPDATES = 3  # the first from the same parameters; the next two check the optimisers, schedules and target updates


def _same_start():
    """(a) eager on small synthetic data, and a fixed list of its batches (the others take its parameters)."""
    import torch

    torch.manual_seed(0)
    data, _ = peers.load_data("synthetic", transitions=512, seed=0)
    rmrl = peers.RmrlUpdate(data, TOTAL, compile=False)
    return data, rmrl, [rmrl.sample() for _ in range(UPDATES)]


def _losses(update, batches) -> list:
    return [update.update_on(b.clone()) for b in batches]


def _assert_close(mine: list, reference: list, rel: float) -> None:
    for step, (got, want) in enumerate(zip(mine, reference), 1):
        for key in ("loss_value", "loss_qvalue", "loss_actor"):
            assert got[key] == pytest.approx(want[key], rel=rel, abs=1e-6), (step, key, got[key], want[key])


def _assert_same_parameters(update, rmrl, atol: dict) -> None:
    """After the updates: the same weights network by network, to ``atol`` (an Adam step is about 3e-4 per weight
    here, so a wrong rate, schedule or target update is far outside it)."""
    mine, reference = peers.snapshot(update), peers.snapshot(rmrl)
    for net, want in reference.items():
        assert len(mine[net]) == len(want)
        for got, ref in zip(mine[net], want):
            assert got.shape == ref.shape, net
            assert np.abs(got - ref).max() <= atol.get(net, atol["other"]), net


def test_the_torch_contenders_compute_rmrls_losses():
    data, rmrl, batches = _same_start()
    corl, torchrl_iql = peers.CorlUpdate(data, TOTAL), peers.TorchRLUpdate(data, TOTAL)
    corl.load_from(rmrl)
    torchrl_iql.load_from(rmrl)
    reference = _losses(rmrl, batches)
    assert all(reference[0][k] > 0 for k in ("loss_value", "loss_qvalue"))
    for update in (corl, torchrl_iql):
        _assert_close(_losses(update, batches), reference, rel=1e-5)
        _assert_same_parameters(update, rmrl, {"other": 1e-5})


@pytest.mark.slow  # jit compiles: about 20 s
def test_the_jax_contender_computes_rmrls_losses():
    pytest.importorskip("jax")
    pytest.importorskip("optax")
    data, rmrl, batches = _same_start()
    jax_iql = peers.JaxUpdate(data, TOTAL, per_call=2)
    jax_iql.load_from(rmrl)
    _assert_close(_losses(jax_iql, batches), _losses(rmrl, batches), rel=1e-4)
    # XLA's float32 sums differ from torch's more: about 5e-6 on the actor's weights, 3e-5 on the value's
    _assert_same_parameters(jax_iql, rmrl, {"actor": 3e-5, "other": 1e-4})
    assert jax_iql.run(3) == 4  # whole calls of per_call updates
    jax_iql.sync()


@pytest.mark.slow
def test_the_script_reports_every_torch_contender_against_rmrl():
    contenders = ["rmrl_trainer", "corl_style_torch", "torchrl_iqlloss"]
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "speed" / "peers.py"), "--updates", "4",
                          "--warmup", "2", "--rounds", "1", "--data", "synthetic", "--transitions", "1000",
                          "--contenders", *contenders], check=True, capture_output=True, text=True, timeout=900)
    report = json.loads(out.stdout)
    assert {"benchmark", "date", "machine", "settings", "reference", "contenders", "notes"} <= set(report)
    assert report["reference"] == "rmrl_trainer" and report["settings"]["threads"] == 1
    for name in contenders:
        res = report["contenders"][name]
        assert "error" not in res, res
        assert {"setup_seconds", "first_call_seconds", "warmup_seconds", "peak_rss_mib"} <= set(res)
        assert len(res["rounds"]) == 1 and res["rounds"][0]["updates"] == 4
        for key in ("updates_per_wall_second", "updates_per_cpu_second"):
            assert res["rounds"][0][key] > 0 and res[f"best_{key}"] == res["rounds"][0][key]
        assert res["ratio_to_rmrl_trainer_cpu_per_round"][0] > 0
    assert report["contenders"]["rmrl_trainer"]["ratio_to_rmrl_trainer_wall_best"] == 1.0


def test_without_jax_the_jax_contender_is_skipped_with_a_note(monkeypatch, capsys):
    real = peers.importlib.util.find_spec
    monkeypatch.setattr(peers.importlib.util, "find_spec", lambda name, *a: None if name == "jax" else real(name, *a))
    peers.main(["--contenders", "jax_corl_style", "--data", "synthetic", "--transitions", "300"])
    report = json.loads(capsys.readouterr().out)
    assert set(report["contenders"]) == {"jax_corl_style"}
    assert "skipped" in report["contenders"]["jax_corl_style"]
    assert any("jax_corl_style skipped" in note for note in report["notes"])
