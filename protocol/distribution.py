"""The installed distribution ``koopman-swarm``: its version and its optional extras.

``pip install koopman-swarm`` brings the core, which runs every paper case. Features with
heavy dependencies come with an extra (``pyproject.toml``'s ``[project.optional-dependencies]``)
and import those dependencies inside :func:`needs`, so that a missing extra is one line saying
what to install instead of a traceback:

>>> with needs("dem"):
...     import rasterio_is_not_here
Traceback (most recent call last):
...
ModuleNotFoundError: No module named 'rasterio_is_not_here'
>>> try:
...     with needs("dem"):
...         raise ModuleNotFoundError("No module named 'rasterio'", name="rasterio")
... except MissingExtra as exc:
...     print(exc)
DEM terrain needs the [dem] extra: pip install 'koopman-swarm[dem]'
"""
from __future__ import annotations

import contextlib
import functools
import importlib
import importlib.metadata
import tomllib
from collections.abc import Iterator
from pathlib import Path

DISTRIBUTION = "koopman-swarm"
UNKNOWN_VERSION = "0+unknown"  # neither installed nor in a source checkout

EXTRAS: dict[str, tuple[str, tuple[str, ...]]] = {
    # extra: (the feature, as a user names it; the top-level modules it imports)
    "dem": ("DEM terrain", ("rasterio",)),
    "live": ("the live view", ("bokeh", "tornado")),
    "cluster": ("running on a dask scheduler", ("distributed", "dask")),
    "deploy": ("generating TLS certificates", ("cryptography",)),
    "ros": ("ROS 2 (bags, and live topics with --ros2)",
            ("rosbags", "mcap", "mcap_ros2", "xxhash")),
}
"""Every extra but ``test`` (which brings them all), as ``pyproject.toml`` declares them."""


class MissingExtra(ImportError):
    """A feature's dependencies are not installed; the message names the extra to install.

    Command-line entry points report it as one line and exit with status 2 (refused before
    anything ran)."""


def missing_extra_message(extra: str) -> str:
    """The one line that says ``extra``'s feature needs it, and how to install it."""
    if extra not in EXTRAS:
        raise ValueError(f"extra must be one of {sorted(EXTRAS)}, got {extra!r}")
    return (f"{EXTRAS[extra][0]} needs the [{extra}] extra: "
            f"pip install '{DISTRIBUTION}[{extra}]'")


@contextlib.contextmanager
def needs(extra: str) -> Iterator[None]:
    """Import the dependencies of ``extra`` within the block: a module of ``extra`` that is
    not installed raises :class:`MissingExtra` instead of ``ModuleNotFoundError``.

    Any other import error (another module missing, an installed package that fails to load)
    is left as it is: it is not cured by installing the extra.
    """
    message = missing_extra_message(extra)
    try:
        yield
    except ModuleNotFoundError as exc:
        if (exc.name or "").partition(".")[0] not in EXTRAS[extra][1]:
            raise
        raise MissingExtra(message, name=exc.name) from exc


def require(extra: str) -> None:
    """Import the modules of ``extra`` now (:class:`MissingExtra` if one is not installed):
    a check before work that will need them starts elsewhere, e.g. in worker processes."""
    with needs(extra):
        for module in EXTRAS[extra][1]:
            importlib.import_module(module)


@functools.cache
def version() -> str:
    """This code's version.

    Run from a source checkout (``pyproject.toml`` of this distribution next to the packages,
    whether installed editable or not), the checkout's ``pyproject.toml`` says it: an editable
    install's metadata is a copy taken at install time, stale once the version changes.
    Otherwise the installed distribution's metadata says it; :data:`UNKNOWN_VERSION` if
    there is neither.
    """
    try:
        project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml")
                                .read_text(encoding="utf-8")).get("project", {})
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        project = {}
    if project.get("name") == DISTRIBUTION and isinstance(project.get("version"), str):
        return project["version"]
    try:
        return importlib.metadata.version(DISTRIBUTION)
    except importlib.metadata.PackageNotFoundError:
        return UNKNOWN_VERSION
