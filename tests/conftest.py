"""Shared by every test module. The project's BLAS setting (one thread per process, see
``protocol/__init__``) must precede numpy, which test modules import first."""
from pathlib import Path

import pytest

import protocol  # noqa: F401

# The helper modules here (every file but this one and test_*.py) hold no doctests, and pytest's
# --doctest-modules would import each of them at collection, in every worker (scipy's ODE
# solver, the launcher, ...): write a helper's examples as tests instead.
collect_ignore = [path.name for path in Path(__file__).parent.glob("*.py")
                  if path.name != "conftest.py" and not path.name.startswith("test_")]


@pytest.hookimpl(trylast=True)  # after ``-m`` has deselected
def pytest_collection_modifyitems(items):
    """The files that hold slow tests go first (in their order), the rest after them: the
    workers take files in this order (``--dist loadfile``), so the long end-to-end runs start
    at once and overlap the many short files, instead of starting late and ending the suite
    alone. Without slow tests selected, the order is unchanged."""
    slow_files = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow_files)  # a stable sort
