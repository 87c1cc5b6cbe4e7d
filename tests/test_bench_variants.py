"""The training bench times what its variants name, whatever the method config it reads sets."""
import importlib
from dataclasses import replace
from pathlib import Path

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
    assert got == {"fp32": (False, "fp32"), "channels_last": (True, "fp32"), "bf16": (True, "bf16")}
