"""The training bench times what its variants name, whatever the method config it reads sets."""
import importlib
from dataclasses import replace
from pathlib import Path

import pytest
import torch
import yaml

BENCH = Path(__file__).resolve().parents[1] / "bench"


def test_each_variant_overrides_a_bf16_method_config(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))  # the bench script imports its folder's common.py
    bench = importlib.import_module("bench_inference")
    cfg_file = tmp_path / "m.yaml"
    cfg_file.write_text(yaml.safe_dump({"train": {"channels_last": True, "precision": "bf16"}}))
    _, train_cfg, _, _ = bench.method_networks([str(cfg_file)])["m.yaml"]
    assert (train_cfg.channels_last, train_cfg.precision) == (True, "bf16")
    variants = {name: replace(train_cfg, **v) for name, v in bench.TRAIN_VARIANTS.items()}
    got = {name: (cfg.channels_last, cfg.precision) for name, cfg in variants.items()}
    assert got == {"fp32": (False, "fp32"), "channels_last": (True, "fp32"), "bf16": (True, "bf16"),
                   "compile": (True, "bf16"), "compile_whole": (True, "bf16")}


def test_gradient_agreement_tells_a_zero_gradient_from_a_rounded_one(monkeypatch):
    """A compiled step is checked against the eager one: a rounding-level difference reads about 1, a gradient of
    zeros (what compiling the whole network gives in torch 2.13 on the CPU) 0, a reversed one −1."""
    monkeypatch.syspath_prepend(str(BENCH))
    bench = importlib.import_module("bench_inference")
    ref = torch.tensor([3.0, -4.0, 0.0, 12.0])
    assert bench.gradient_agreement(ref * 1.001 + 1e-4, ref)["grad_cosine_vs_bf16"] == pytest.approx(1, abs=1e-4)
    assert bench.gradient_agreement(torch.zeros(4), ref) == {"grad_cosine_vs_bf16": 0.0,
                                                             "grad_norm_ratio_vs_bf16": 0.0}
    assert bench.gradient_agreement(-2 * ref, ref) == {"grad_cosine_vs_bf16": -1.0, "grad_norm_ratio_vs_bf16": 2.0}


def test_the_training_bench_times_only_the_variants_asked_for(monkeypatch):
    """--variants fp32,channels_last leaves bf16 out (emulated, 10× slower, on a CPU without native bf16)."""
    monkeypatch.syspath_prepend(str(BENCH))
    bench = importlib.import_module("bench_inference")
    net = bench.NetConfig(width=8, aspp_channels=8, low_level_channels=8, decoder_channels=8)
    cfg = bench.TrainConfig(batch_size=2, image_size=64, crop=(32, 48), threads=1)
    out = bench.bench_training(net, cfg, 1, bench.resolve_device("cpu"), ("fp32", "channels_last"))
    assert set(out) == {"fp32", "channels_last"} and out["channels_last"]["channels_last"] is True
    assert out["fp32"]["precision"] == out["channels_last"]["precision"] == "fp32"
