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



# --- the checkout is left as the suite found it ---------------------------------------------

ROOT = Path(__file__).resolve().parents[1]
_CACHES = ("__pycache__/", ".pyc", ".hypothesis/", ".pytest_cache/", ".ruff_cache/",
           ".egg-info/", ".venv/")
"""What tools write on their own (bytecode, test and lint caches): not a test's doing."""


def checkout_state() -> set[str] | None:
    """Every changed, untracked or ignored file of the checkout (``git status``), caches
    left out; None outside a git checkout."""
    import subprocess

    try:
        status = subprocess.run(
            ["git", "status", "--porcelain", "--ignored", "--untracked-files=all", "--", ".",
             ":(exclude).venv"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    if status.returncode != 0:
        return None
    return {line for line in status.stdout.splitlines()
            if not any(cache in line for cache in _CACHES)}


def pytest_sessionstart(session):
    if not hasattr(session.config, "workerinput"):  # once: in the controller, or alone
        session.config._checkout_before = checkout_state()


def pytest_sessionfinish(session, exitstatus):
    """No test leaves anything in the checkout (a results folder, a lock, a figure): the
    suite fails, listing what appeared or changed, when the checkout differs from before."""
    before = getattr(session.config, "_checkout_before", None)
    after = checkout_state() if before is not None else None
    if after is None or after == before:
        return
    lines = [f"  {line}" for line in sorted(after ^ before)]
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    message = "\n".join(["the tests changed the checkout (write under tmp_path instead):",
                         *lines[:40]])
    if reporter is not None:
        reporter.ensure_newline()
        reporter.write_line(message, red=True)
    else:
        print(message)
    session.exitstatus = pytest.ExitCode.TESTS_FAILED
