"""Your own estimator: ``--estimator package.module:Name`` (design §6).

Only the follower process imports it (the world records the name). ``Name`` is a class or a
factory called with the follower's :class:`protocol.config.AgentSettings`; what it returns
implements the streaming interface of :class:`agents.policies.base.Policy`: ``propose(pre)``
without side effects (raising :class:`agents.policies.base.NotReady` while it cannot predict),
``record(settled, target)``, ``skip()``, and a ``name``.

A plug-in is code this project does not know: whatever its factory raises is reported as a
``ValueError`` naming the estimator (the follower refuses to start), and whatever its methods
raise, other than ``NotReady``, as :class:`EstimatorFailed` naming the estimator, the method and
the tick (the follower stops; the run ends with that one line), never as a traceback.
"""
from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

from agents.policies.base import NotReady, Policy, looks_before_moving
from protocol.cli import describe
from protocol.config import PLUGIN_ESTIMATOR, AgentSettings
from protocol.limits import MAX_NAME, NAME_PATTERN, NAME_RULE


def load_estimator(spec: str, settings: AgentSettings) -> Policy:
    """Import ``package.module:Name`` and build the policy from ``settings``.

    Raises
    ------
    ValueError
        If ``spec`` is malformed, cannot be imported, or does not give a policy.
    """
    if not isinstance(spec, str) or not PLUGIN_ESTIMATOR.match(spec):
        raise ValueError("estimator must be a built-in name or 'package.module:Name', "
                         f"got {spec!r}")
    module_name, attr = spec.split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ValueError(f"estimator {spec!r}: cannot import {module_name!r} ({exc})") from None
    factory = getattr(module, attr, None)
    if not callable(factory):
        raise ValueError(f"estimator {spec!r}: {module_name} has no class or factory {attr!r}")
    try:
        policy = factory(settings)
    except Exception as exc:  # a plug-in may raise anything: say what
        raise ValueError(f"estimator {spec!r}: its factory {attr} raised "
                         f"{_error(exc)}") from None
    missing = [m for m in ("propose", "record", "skip") if not callable(getattr(policy, m, None))]
    if missing:
        raise ValueError(f"estimator {spec!r} does not implement {', '.join(missing)}")
    if not isinstance(getattr(policy, "name", None), str) or not policy.name:
        policy.name = spec
    if not NAME_PATTERN.fullmatch(policy.name):  # it travels in every observation
        raise ValueError(f"estimator {spec!r}: name must be {NAME_RULE}, got "
                         f"{policy.name[:MAX_NAME]!r}")
    return Guarded(spec, policy)


class EstimatorFailed(RuntimeError):
    """A plug-in estimator's method raised; the message names it, the method and the tick."""


class Guarded(Policy):
    """A plug-in ``policy`` whose errors (other than ``NotReady``) become
    :class:`EstimatorFailed` naming ``spec``, the method and the tick."""

    def __init__(self, spec: str, policy: Any) -> None:
        self.spec, self.policy, self.name = spec, policy, policy.name
        self.looks_before_moving = looks_before_moving(policy)
        self._tick: int | None = None  # the tick of the last sensing seen (skip has none)

    def _call(self, method: str, tick: int | None, call: Callable[[], Any]) -> Any:
        self._tick = self._tick if tick is None else tick
        try:
            return call()
        except NotReady:
            raise
        except Exception as exc:  # a plug-in may raise anything: say what
            when = "" if self._tick is None else f" at tick {self._tick}"
            raise EstimatorFailed(f"estimator {self.spec!r}: {method} raised{when}: "
                                  f"{_error(exc)}") from None

    def propose(self, pre):
        return self._call("propose", pre.tick, lambda: self.policy.propose(pre))

    def record(self, settled, target):
        return self._call("record", settled.tick, lambda: self.policy.record(settled, target))

    def skip(self) -> None:
        self._call("skip", None, self.policy.skip)

    def leverage(self, pre):
        leverage = getattr(self.policy, "leverage", None)
        return None if leverage is None else self._call("leverage", pre.tick,
                                                        lambda: leverage(pre))


def _error(exc: Exception) -> str:
    """``TypeError: the message`` on one line."""
    return f"{type(exc).__name__}: {describe(exc)}"
