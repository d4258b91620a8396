"""Shared by every test module. The project's BLAS setting (one thread per process, see
``protocol/__init__``) must precede numpy, which test modules import first."""
from pathlib import Path

import protocol  # noqa: F401

# The helper modules here (every file but this one and test_*.py) hold no doctests, and pytest's
# --doctest-modules would import each of them at collection, in every worker (scipy's ODE
# solver, the launcher, ...): write a helper's examples as tests instead.
collect_ignore = [path.name for path in Path(__file__).parent.glob("*.py")
                  if path.name != "conftest.py" and not path.name.startswith("test_")]

