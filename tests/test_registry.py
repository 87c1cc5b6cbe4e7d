"""The method registry: every entry imports, subclasses Method and carries its key as its name; bad
entries and names are refused with one line."""
import pytest

from selfseg.method_api import Method
from selfseg.registry import METHODS, UnknownMethodError, get_method_class, method_names


@pytest.mark.parametrize("name", method_names())
def test_every_registered_method_imports_and_names_itself(name):
    cls = get_method_class(name)
    assert issubclass(cls, Method) and cls is not Method
    assert cls.name == name
    assert cls.__module__.startswith("selfseg.")


def test_pipeline_and_interface_do_not_import_baselines():
    """method/ (the self-supervised pipeline), the interface and the registry import nothing of baselines/
    (the registry names them in strings, imported only when asked for)."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    files = [*(root / "method").glob("*.py"), root / "selfseg/method_api.py", root / "selfseg/registry.py"]
    pattern = re.compile(r"^\s*(from selfseg\.baselines|import selfseg\.baselines|from selfseg import baselines)", re.M)
    assert [str(p.relative_to(root)) for p in files if pattern.search(p.read_text())] == []


def test_entry_with_wrong_name_is_refused(monkeypatch):
    monkeypatch.setitem(METHODS, "not-oracle", "selfseg.baselines.simple:Oracle")
    with pytest.raises(UnknownMethodError, match="whose name is 'oracle'"):
        get_method_class("not-oracle")


def test_entry_that_is_not_a_method_is_refused(monkeypatch):
    monkeypatch.setitem(METHODS, "dataset", "selfseg.dataset:Dataset")
    with pytest.raises(UnknownMethodError, match="not a subclass of selfseg.method_api.Method"):
        get_method_class("dataset")


@pytest.mark.parametrize("spec, message", [
    ("no_such_module_xyz:Thing", "cannot import module 'no_such_module_xyz'"),
    ("selfseg.baselines.simple:NoSuchClass", "has no 'NoSuchClass'"),
    ("selfseg.baselines.simple:", "expected a registered name or 'package.module:ClassName'"),
    ("oracl", "Did you mean 'oracle'"),
])
def test_bad_names_are_one_line(spec, message):
    with pytest.raises(UnknownMethodError, match=message) as e:
        get_method_class(spec)
    assert "\n" not in str(e.value)


def test_module_class_form_resolves_a_builtin():
    from selfseg.baselines.simple import Oracle

    assert get_method_class("selfseg.baselines.simple:Oracle") is Oracle
