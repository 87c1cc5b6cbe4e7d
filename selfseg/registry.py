"""The one registry from method names to classes, imported lazily ("module:Class" strings).

Adding a built-in method is one line in ``METHODS``; its heavy imports (torch, open3d, ...) load only
when it is used. A user's own method needs no line here: ``evaluate --method package.module:ClassName``
imports it from ``PYTHONPATH`` (:func:`get_method_class`; ``evaluate`` imports it only in the method's own
sandboxed process). Every class must subclass :class:`selfseg.method_api.Method`; a registered one's
``name`` must equal its key.

What a method's sandbox holds besides the fold's unlabeled videos is a property of its entry here, never of
the class: the labels it is given (:data:`GROUND_TRUTH`) and the folders its config names
(:data:`CONFIG_DIRS`). A user's method gets neither, except the training videos' labels with ``evaluate
--method-needs-ground-truth``, which its results record.
"""
from __future__ import annotations

import difflib
import importlib
import re

from selfseg.method_api import Method

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
    "ours-gt-merging": "selfseg.baselines.gt_merging:OursGTMerging",
    "picie": "selfseg.baselines.picie:Picie",
    "stego": "selfseg.baselines.stego:Stego",
    "uois-sim": "selfseg.baselines.uois:UoisSim",
    "sdmaskrcnn-sim": "selfseg.baselines.maskrcnn:SDMaskRCNNSim",
}


# Labels a registered method's process is given (every other method: none): "train" = the fold's training
# videos', "all" = the test videos' too (the oracle only, a check of the harness that must score 1.0).
GROUND_TRUTH: dict[str, str] = {"supervised": "train", "ours-gt-merging": "train", "oracle": "all"}
# Config fields of registered methods naming folders outside the dataset that their sandbox mounts, at the
# same path: "ro" read-only (a training dataset of other objects, a predictions folder), "rw" writable.
CONFIG_DIRS: dict[str, dict[str, str]] = {
    **{m: {"train_data": "ro"} for m in ("v1-disjoint", "uois-sim", "sdmaskrcnn-sim")},
    "external": {"predictions": "ro"},
    **{m: {"stage_dir": "rw"} for m in ("ours", "ours-v2", "ours-v3", "ours-v4", "ours-gt-merging")},
}


class UnknownMethodError(KeyError):
    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


def method_names() -> list[str]:
    return sorted(METHODS)


def split_spec(spec: str) -> tuple[str, str]:
    """``"package.module:ClassName"`` → (module, class name); UnknownMethodError (one line) if it is not of that form."""
    module, sep, attr = spec.partition(":")
    if not sep or not module or not attr:
        raise UnknownMethodError(f"method {spec!r}: expected a registered name or 'package.module:ClassName'")
    return module, attr


def import_method(spec: str) -> type[Method]:
    """``"package.module:ClassName"`` → the class, imported; UnknownMethodError (one line) if the module
    or class is missing or the class is not a :class:`Method`."""
    module, attr = split_spec(spec)
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as e:
        raise UnknownMethodError(f"method {spec!r}: cannot import module {e.name!r} (is it on PYTHONPATH?)") from None
    except SyntaxError as e:
        raise UnknownMethodError(f"method {spec!r}: {e.filename}:{e.lineno}: {e.msg}") from None
    cls = getattr(mod, attr, None)
    if cls is None:
        raise UnknownMethodError(f"method {spec!r}: module {module!r} ({mod.__file__}) has no {attr!r}")
    if not (isinstance(cls, type) and issubclass(cls, Method)):
        raise UnknownMethodError(f"method {spec!r}: {attr!r} is not a subclass of selfseg.method_api.Method")
    return cls


def get_method_class(name: str) -> type[Method]:
    """A registered name, or ``"package.module:ClassName"`` for a method outside the registry, → its class.

    Unknown names get a did-you-mean error; a registered class whose ``name`` differs from its key is an error.
    """
    if ":" in name:
        return _user_method(name)
    try:
        target = METHODS[name]
    except KeyError:
        close = difflib.get_close_matches(name, METHODS, n=3)
        hint = f" Did you mean {', '.join(repr(c) for c in close)}?" if close else ""
        raise UnknownMethodError(f"unknown method {name!r}.{hint} Registered: {', '.join(method_names())}; "
                                 "a method of your own: 'package.module:ClassName'") from None
    cls = import_method(target)
    if cls.name != name:
        raise UnknownMethodError(f"method {name!r}: registered as {target}, whose name is {cls.name!r}")
    return cls


def check_user_method_name(spec: str, name: object) -> str:
    """``name``, the ``name`` of the class ``spec`` (outside the registry) names: it names the method's results, so
    it must be its own (a folder name, not the base class's, not a registered method's unless ``spec`` is that
    method's entry); UnknownMethodError (one line) otherwise. Needs no import: ``evaluate`` checks the name
    the method's process reports."""
    if not isinstance(name, str) or name == Method.name or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", name):
        raise UnknownMethodError(f"method {spec!r}: set the class attribute name to a name of its own "
                                 f"(letters, digits, '.', '_', '-'), got {name!r}")
    if name in METHODS and METHODS[name] != spec:
        raise UnknownMethodError(f"method {spec!r}: its name {name!r} is a registered method's "
                                 f"({METHODS[name]}); choose another")
    return name


def _user_method(spec: str) -> type[Method]:
    """A method outside the registry, imported here (``train``; tests): its name checked as
    :func:`check_user_method_name` does."""
    cls = import_method(spec)
    check_user_method_name(spec, cls.name)
    return cls
