"""The public API: every exported name exists, is documented, and packages nest one level."""

import importlib
import inspect
import pkgutil

import pytest

import jface

MODULES = sorted(
    name
    for _, name, _ in pkgutil.walk_packages(jface.__path__, "jface.")
    if not any(part.startswith("_") for part in name.split(".")[1:])
)


@pytest.mark.parametrize("name", MODULES)
def test_public_names_are_documented(name):
    module = importlib.import_module(name)
    assert module.__doc__, f"{name} has no docstring"
    for attr in getattr(module, "__all__", ()):
        obj = getattr(module, attr)  # AttributeError if __all__ lies
        if inspect.isfunction(obj) or inspect.isclass(obj):
            assert obj.__doc__, f"{name}.{attr} has no docstring"


def test_nesting_is_one_level():
    for name in MODULES:
        assert name.count(".") <= 2, name


def test_every_public_module_is_reachable_from_the_package():
    """``import jface; jface.detail...`` works for every public module, and the package's
    docstring names each of them."""
    top = sorted({name.split(".")[1] for name in MODULES if name.count(".") >= 1})
    assert sorted(jface._SUBMODULES) == [n for n in top if n != "cli"]
    for name in top:
        if name != "cli":
            assert getattr(jface, name) is importlib.import_module(f"jface.{name}")
            assert f"jface.{name}" in jface.__doc__
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        jface.nothing  # noqa: B018
