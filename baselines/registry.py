"""The one registry from method names to adapters, imported lazily ("module:Class" strings).

Adding a method is one line here; its heavy imports (torch, open3d, ...) load only when it is used.
"""
from __future__ import annotations

import difflib
import importlib

from selfseg.baselines.base import Method

METHODS: dict[str, str] = {
    "lccp-frame": "selfseg.baselines.lccp_frame:LCCPFrame",
    "supervised": "selfseg.baselines.supervised:SupervisedMethod",
    "v1-disjoint": "selfseg.baselines.supervised:V1DisjointMethod",
    "oracle": "selfseg.baselines.simple:Oracle",
    "one-segment": "selfseg.baselines.simple:OneSegment",
    "fg-components": "selfseg.baselines.simple:ForegroundComponents",
    "depth-clustering": "selfseg.baselines.simple:DepthClustering",
    "external": "selfseg.baselines.external:ExternalPredictions",
    "ours": "selfseg.method.pipeline:Ours",
    "ours-v2": "selfseg.method.pipeline:OursV2",
    "ours-v3": "selfseg.method.pipeline:OursV3",
    "ours-v4": "selfseg.method.pipeline:OursV4",
    "picie": "selfseg.baselines.picie:Picie",
    "stego": "selfseg.baselines.stego:Stego",
    "uois-sim": "selfseg.baselines.uois:UoisSim",
    "sdmaskrcnn-sim": "selfseg.baselines.maskrcnn:SDMaskRCNNSim",
}


class UnknownMethodError(KeyError):
    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


def method_names() -> list[str]:
    return sorted(METHODS)


def get_method_class(name: str) -> type[Method]:
    """Resolve a registered name to its adapter class; unknown names get a did-you-mean error."""
    try:
        target = METHODS[name]
    except KeyError:
        close = difflib.get_close_matches(name, METHODS, n=3)
        hint = f" Did you mean {', '.join(repr(c) for c in close)}?" if close else ""
        raise UnknownMethodError(f"unknown method {name!r}.{hint} Registered: {', '.join(method_names())}") from None
    module, _, cls = target.partition(":")
    return getattr(importlib.import_module(module), cls)
