"""The layering as a test: the package's import graph (read with ``ast``, nothing imported, lazy
imports inside functions included) has no arrow that the intended picture forbids. The picture (who imports whom)::

    core (selfseg/)   ←  every stage
    generate          →  core
    method            →  core
    baselines         →  method, eval, core
    eval              →  method, core
    leaderboards      →  eval, core

The core knows no stage; the method knows no evaluation, baseline or generator; the generator
knows neither method nor evaluation; no method (``method/``, ``baselines/``) reads leaderboards.
"""
from __future__ import annotations

import ast
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("generate", "method", "baselines", "eval", "leaderboards")
FORBIDDEN = {  # layer → the layers it must not import
    "core": set(STAGES),
    "method": {"eval", "baselines", "generate", "leaderboards"},
    "generate": {"method", "eval"},
    "baselines": {"leaderboards"},
}


def layer(module: str) -> str:
    """``selfseg.method.x`` → ``method``; ``selfseg.x`` (or ``selfseg``) → ``core``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in STAGES else "core"


def package_modules(root: Path = ROOT) -> dict[str, Path]:
    """Every module of the installed package, by dotted name, from pyproject's package-dir mapping."""
    dirs = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    return {pkg if f.stem == "__init__" else f"{pkg}.{f.stem}": f
            for pkg, folder in dirs.items() for f in sorted((root / folder).glob("*.py"))}


def imported_names(module: str, path: Path) -> list[tuple[int, str]]:
    """(line, dotted name) of every import in the file, at any depth, relative imports resolved."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = module.split(".")[:None if path.stem == "__init__" else -1]
                pkg = pkg[:len(pkg) - node.level + 1]
                base = ".".join(pkg + ([base] if base else []))
            out += [(node.lineno, f"{base}.{a.name}") for a in node.names]
    return out


def forbidden_imports(modules: dict[str, Path]) -> list[str]:
    """One line per import that crosses a forbidden arrow: ``module:line imports name (from → to)``."""
    bad = []
    for module, path in modules.items():
        src = layer(module)
        for line, name in imported_names(module, path):
            if name.split(".")[0] == "selfseg" and layer(name) in FORBIDDEN.get(src, ()):
                bad.append(f"{module}:{line} imports {name} ({src} → {layer(name)})")
    return bad


def test_the_package_keeps_its_layers():
    modules = package_modules()
    assert {layer(m) for m in modules} == {"core", *STAGES}  # every folder was read
    assert forbidden_imports(modules) == []


def test_a_forbidden_import_is_reported_even_inside_a_function(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("from selfseg.method.background import frame_foreground\n\n\n"
                   "def scores():\n    from selfseg.eval import metrics\n    return metrics\n")
    assert forbidden_imports({"selfseg.method.bad": bad}) == [
        "selfseg.method.bad:5 imports selfseg.eval.metrics (method → eval)"]
    assert forbidden_imports({"selfseg.bad": bad}) == [
        "selfseg.bad:1 imports selfseg.method.background.frame_foreground (core → method)",
        "selfseg.bad:5 imports selfseg.eval.metrics (core → eval)"]
    relative = tmp_path / "rel.py"
    relative.write_text("from ..baselines import simple\n")
    assert forbidden_imports({"selfseg.method.rel": relative}) == [
        "selfseg.method.rel:1 imports selfseg.baselines.simple (method → baselines)"]
