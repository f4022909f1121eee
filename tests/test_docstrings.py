"""Every public name of phisim and inverse carries a docstring (and so do public methods of public classes)."""

import importlib
import inspect

import pytest

PACKAGES = ["phisim", "inverse"]


def _public_objects():
    for pkg_name in PACKAGES:
        pkg = importlib.import_module(pkg_name)
        assert hasattr(pkg, "__all__"), f"{pkg_name} must declare __all__"
        for name in pkg.__all__:
            yield f"{pkg_name}.{name}", getattr(pkg, name)


def test_all_lists_existing_names():
    for pkg_name in PACKAGES:
        pkg = importlib.import_module(pkg_name)
        missing = [n for n in pkg.__all__ if not hasattr(pkg, n)]
        assert not missing, f"{pkg_name}.__all__ names missing attributes: {missing}"


@pytest.mark.parametrize("qualname,obj", list(_public_objects()), ids=lambda v: v if isinstance(v, str) else "")
def test_public_name_has_docstring(qualname, obj):
    if not (inspect.isclass(obj) or inspect.isfunction(obj) or inspect.ismodule(obj)):
        return  # constants
    assert inspect.getdoc(obj), f"{qualname} has no docstring"
    if inspect.isclass(obj):
        for mname, member in vars(obj).items():
            if mname.startswith("_"):
                continue
            fn = member.fget if isinstance(member, property) else getattr(member, "__func__", member)
            if inspect.isfunction(fn):
                assert inspect.getdoc(fn), f"{qualname}.{mname} has no docstring"
