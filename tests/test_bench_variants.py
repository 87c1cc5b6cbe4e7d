"""The training bench times what its variants name, whatever the method config it reads sets."""
import sys
from dataclasses import replace
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

from bench_inference import TRAIN_VARIANTS, method_networks  # noqa: E402


def test_each_variant_overrides_a_bf16_method_config(tmp_path):
    cfg_file = tmp_path / "m.yaml"
    cfg_file.write_text(yaml.safe_dump({"train": {"channels_last": True, "precision": "bf16"}}))
    _, train_cfg, _, _ = method_networks([str(cfg_file)])["m.yaml"]
    assert (train_cfg.channels_last, train_cfg.precision) == (True, "bf16")
    got = {name: (replace(train_cfg, **v).channels_last, replace(train_cfg, **v).precision)
           for name, v in TRAIN_VARIANTS.items()}
    assert got == {"fp32": (False, "fp32"), "channels_last": (True, "fp32"), "bf16": (True, "bf16")}
