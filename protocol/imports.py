"""A user's own code, named ``package.module:name`` (a surface, an estimator), is imported the
same way in every entry point: from the installed packages and the current folder.

``python -m swarm`` puts the current folder on ``sys.path``; an installed console script
(``swarm``, ``swarm-world``, ``swarm-follower``) does not. :func:`import_user_module` makes both
behave as ``python -m`` does, so a plug-in resolves whichever way the tool was started
(docs/estimators.md, docs/surfaces.md).
"""
from __future__ import annotations

import importlib
import importlib.machinery
import importlib.util
import os
import sys
from types import ModuleType


def current_folder_importable() -> None:
    """Put the current folder first on ``sys.path`` unless it is there already."""
    here = os.getcwd()
    if not any(os.path.abspath(entry or os.curdir) == here for entry in sys.path):
        sys.path.insert(0, here)


def import_user_module(name: str) -> ModuleType:
    """Import the module ``name`` of a user's ``package.module:name`` (ImportError, or
    whatever its code raises, as :func:`importlib.import_module`)."""
    current_folder_importable()
    return importlib.import_module(name)


def user_module_exists(name: str) -> bool:
    """Whether :func:`import_user_module` would find the module ``name``, without running
    any of its code or its packages' (a launcher checks a plug-in it must not execute)."""
    current_folder_importable()
    if name in sys.modules:
        return True
    parts = name.split(".")
    try:
        spec = importlib.util.find_spec(parts[0])  # a top-level name: nothing is executed
    except (ImportError, ValueError):
        return False
    for depth in range(2, len(parts) + 1):
        if spec is None or spec.submodule_search_locations is None:
            return False
        spec = importlib.machinery.PathFinder.find_spec(".".join(parts[:depth]),
                                                        spec.submodule_search_locations)
    return spec is not None
