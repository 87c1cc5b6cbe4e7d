"""Every shipped config (configs/<method>-<preset>.yaml) loads into its method's typed config: a misspelt or
moved key in a config no test trains with fails here, not hours into a benchmark run."""
from pathlib import Path

import pytest

from selfseg.config import ConfigError, load_config
from selfseg.registry import METHODS, get_method_class

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"
CONFIGS = sorted(CONFIG_DIR.glob("*.yaml"))
# the ablations and the diagnostic read the same file as the method they vary (scripts/benchmark.sh)
SHARED = {"ours": ("ours", "ours-v2", "ours-v3", "ours-v4", "ours-gt-merging"),
          "supervised": ("supervised", "v1-disjoint")}


def method_of(path: Path) -> str:
    """configs/sdmaskrcnn-sim-tiny.yaml → sdmaskrcnn-sim (the longest registered name before the preset)."""
    stem = path.stem
    names = [m for m in METHODS if stem.startswith(m + "-")]
    assert names, f"{path.name}: no registered method is named before its preset"
    return max(names, key=len)


def test_configs_found():
    assert len(CONFIGS) >= 10 and {method_of(p) for p in CONFIGS} >= {"ours", "supervised"}


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_config_loads(path):
    for method in SHARED.get(method_of(path), (method_of(path),)):
        load_config(get_method_class(method).config_cls, path)


def test_unknown_key_rejected(tmp_path):
    bad = tmp_path / "supervised-typo.yaml"
    bad.write_text((CONFIG_DIR / "supervised-calibrated.yaml").read_text().replace("image_size", "imgae_size"))
    with pytest.raises(ConfigError, match="imgae_size"):
        load_config(get_method_class("supervised").config_cls, bad)
