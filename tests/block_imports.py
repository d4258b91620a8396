"""Test support: Python processes that see only the core install (``pip install .``).

:func:`core_environment` returns the environment of such a process: a folder first on
``PYTHONPATH`` holds a copy of this file as ``sitecustomize``, which Python imports at
start-up, in that process and in every process it starts (they inherit the environment), and
which then puts a finder first on ``sys.meta_path`` that refuses, as if they were not
installed, the top-level modules named in :data:`BLOCKED_ENV`.

The modules refused are those of every installed distribution outside the core: the closure of
``pyproject.toml``'s ``dependencies`` over the installed distributions' own requirements
(:func:`core_distributions`). So the extras, the test tools and anything else installed here
are out of reach, as in a fresh virtual environment holding the core only.
"""
from __future__ import annotations

import os
import shutil
import sys
import tomllib
from pathlib import Path

BLOCKED_ENV = "SWARM_TEST_BLOCKED_MODULES"
OWN_PACKAGES = frozenset({"agents", "protocol", "swarm", "tests", "world"})


class Blocker:
    """A ``sys.meta_path`` finder that refuses ``names`` (top-level modules) and their
    submodules with the error of a module that is not installed."""

    def __init__(self, names: frozenset[str]) -> None:
        self.names = names

    def find_spec(self, fullname: str, path=None, target=None):
        if fullname.partition(".")[0] in self.names:
            raise ModuleNotFoundError(f"No module named {fullname!r}", name=fullname)
        return None


if __name__ == "sitecustomize" and os.environ.get(BLOCKED_ENV):
    sys.meta_path.insert(0, Blocker(frozenset(os.environ[BLOCKED_ENV].split(","))))


def _name(requirement: str) -> str:
    from packaging.utils import canonicalize_name

    return canonicalize_name(requirement)


def core_distributions(pyproject: Path) -> set[str]:
    """Canonical names of the distributions a core install brings: ``pyproject``'s
    ``dependencies`` and, recursively, what the installed ones require (extras and
    requirements whose markers do not hold here left out)."""
    from importlib import metadata

    from packaging.requirements import Requirement

    project = tomllib.loads(pyproject.read_text(encoding="utf-8"))["project"]
    todo = [Requirement(r) for r in project["dependencies"]]
    seen: set[str] = set()
    while todo:
        req = todo.pop()
        name = _name(req.name)
        if name in seen or (req.marker is not None and not req.marker.evaluate({"extra": ""})):
            continue
        seen.add(name)
        try:
            todo += [Requirement(r) for r in metadata.requires(name) or ()]
        except metadata.PackageNotFoundError:
            continue
    return seen


def blocked_modules(pyproject: Path) -> frozenset[str]:
    """Top-level modules of every installed distribution outside the core."""
    from importlib import metadata

    core = core_distributions(pyproject)
    return frozenset(module for module, dists in metadata.packages_distributions().items()
                     if module not in OWN_PACKAGES and module.isidentifier()
                     and not any(_name(d) in core for d in dists))


def core_environment(folder: Path, root: Path) -> dict[str, str]:
    """The environment of a process run from the checkout ``root`` that sees only the core
    install; ``folder`` (created) receives the ``sitecustomize.py``."""
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(__file__, folder / "sitecustomize.py")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(folder), str(root), *filter(None, [os.environ.get("PYTHONPATH")])])
    env[BLOCKED_ENV] = ",".join(sorted(blocked_modules(root / "pyproject.toml")))
    return env
