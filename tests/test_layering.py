"""The layering as a test: the package's import graph (read with ``ast``, nothing imported, lazy
imports inside functions included) has no arrow that the intended picture forbids. The picture (who imports whom)::

    core (selfseg/)   ←  every stage
    generate          →  core
    method            →  core
    baselines         →  method, core; of eval only its public face (EVAL_PUBLIC)
    eval              →  method, core
    bench/, experiments/  →  the package, and each script its own folder's common.py only

The core knows no stage; the method knows no evaluation, baseline or generator; the generator
knows neither method nor evaluation. A baseline reaches no evaluation internals (the protocol, the sandbox,
scoring, the leaderboards): what is public to it is the results layout (``eval/layout.py``: the path templates of
the results folder, e.g. ``external``'s prediction files) and two modules of pure functions on label arrays that
define what is scored (``eval/metrics.py``; ``eval/merges.py``, the ground-truth merges the ``ours-gt-merging``
ceiling shares with Table II). The scripts of ``bench/`` (speed) and ``experiments/`` (research diagnostics) are
not installed: no script imports another script (their folder's ``common.py`` holds what they share), none
imports a module of ``tests/`` or changes ``sys.path``. ``leaderboards/`` holds no code, only what is published.
"""
from __future__ import annotations

import ast
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("generate", "method", "baselines", "eval")
FORBIDDEN = {  # layer → the layers it must not import
    "core": set(STAGES),
    "method": {"eval", "baselines", "generate"},
    "generate": {"method", "eval"},
}
EVAL_PUBLIC = {"layout", "metrics", "merges"}  # the eval modules a baseline may import
SCRIPT_FOLDERS = ("bench", "experiments")
SHARED = "common"  # the one module a script may import from its own folder


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
            parts = name.split(".")
            if parts[0] != "selfseg":
                continue
            if layer(name) in FORBIDDEN.get(src, ()):
                bad.append(f"{module}:{line} imports {name} ({src} → {layer(name)})")
            elif src == "baselines" and layer(name) == "eval" and len(parts) > 2 and parts[2] not in EVAL_PUBLIC:
                bad.append(f"{module}:{line} imports {name} (baselines → eval internals)")
    return bad


def script_problems(folders: list[Path], tests: Path) -> list[str]:
    """One line per script import of another script or of a ``tests/`` module, and per change of ``sys.path``, in
    the ``.py`` files of ``folders``: ``file:line what``."""
    scripts = {f.stem for d in folders for f in d.glob("*.py")} - {SHARED}
    test_modules = {f.stem for f in tests.glob("*.py")}
    bad = []
    for folder in folders:
        for path in sorted(folder.glob("*.py")):
            tree = ast.parse(path.read_text(), str(path))
            for node in ast.walk(tree):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                         [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
                for top in (n.split(".")[0] for n in names):
                    if top in scripts:
                        bad.append((path.name, node.lineno, f"imports the script {top}"))
                    elif top in test_modules:
                        bad.append((path.name, node.lineno, f"imports {top} of tests/"))
                if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and \
                        ast.unparse(node.func.value) == "sys.path":
                    bad.append((path.name, node.lineno, "changes sys.path"))
    return [f"{name}:{line} {what}" for name, line, what in sorted(bad)]


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


def test_baselines_reach_only_the_public_face_of_eval(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("from selfseg.eval.layout import PREDICTION_PNG\nfrom selfseg.eval.metrics import unique_inverse\n"
                   "from selfseg.eval import protocol\nfrom selfseg.eval.leaderboard import load_results\n")
    assert forbidden_imports({"selfseg.baselines.bad": bad}) == [
        "selfseg.baselines.bad:3 imports selfseg.eval.protocol (baselines → eval internals)",
        "selfseg.baselines.bad:4 imports selfseg.eval.leaderboard.load_results (baselines → eval internals)"]
    assert forbidden_imports({"selfseg.eval.bad": bad}) == []


def test_scripts_import_only_the_package_and_their_common_module():
    folders = [ROOT / f for f in SCRIPT_FOLDERS]
    assert all(list(f.glob("bench_*.py")) for f in folders)  # every folder was read
    assert script_problems(folders, ROOT / "tests") == []


def test_a_script_reaching_another_script_or_tests_is_reported(tmp_path):
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "analytic.py").write_text("")
    scripts = tmp_path / "bench"
    scripts.mkdir()
    (scripts / "common.py").write_text("")
    (scripts / "bench_a.py").write_text("")
    (scripts / "bench_b.py").write_text("import sys\nfrom common import x\nfrom bench_a import y\n\n\ndef f():\n"
                                       "    sys.path.insert(0, 'tests')\n    import analytic\n")
    assert script_problems([scripts], tmp_path / "tests") == [
        "bench_b.py:3 imports the script bench_a", "bench_b.py:7 changes sys.path",
        "bench_b.py:8 imports analytic of tests/"]


def test_leaderboards_hold_no_code():
    assert [p.name for p in (ROOT / "leaderboards").rglob("*.py")] == []
