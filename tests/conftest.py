"""Shared by every test module. The project's BLAS setting (one thread per process, see
``protocol/__init__``) must precede numpy, which test modules import first."""
from collections import Counter
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
    """The files that hold slow tests go first, those made mostly of them (the long end-to-end
    runs) before the others, then the files without: the workers take files in this order
    (``--dist loadfile``), so the long runs start at once and overlap the many short files,
    instead of starting late and ending the suite alone. The order is otherwise kept, and
    without slow tests selected it is unchanged."""
    total: Counter = Counter(item.path for item in items)
    slow: Counter = Counter(item.path for item in items if item.get_closest_marker("slow"))
    items.sort(key=lambda item: -slow[item.path] / total[item.path])  # a stable sort
