"""Your own estimator: ``--estimator package.module:Name`` (SPEC §6).

Only the follower process imports it (the world records the name). ``Name`` is a class or a
factory called with the follower's :class:`protocol.config.AgentSettings`; what it returns
implements the streaming interface of :class:`agents.policies.base.Policy`: ``propose(pre)``
without side effects (raising :class:`agents.policies.base.NotReady` while it cannot predict),
``record(settled, target)``, ``skip()``, and a ``name``.
"""
from __future__ import annotations

import importlib

from agents.policies.base import Policy
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
        raise ValueError(f"estimator must be a built-in name or 'package.module:Name', got {spec!r}")
    module_name, attr = spec.split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ValueError(f"estimator {spec!r}: cannot import {module_name!r} ({exc})") from None
    factory = getattr(module, attr, None)
    if not callable(factory):
        raise ValueError(f"estimator {spec!r}: {module_name} has no class or factory {attr!r}")
    policy = factory(settings)
    missing = [m for m in ("propose", "record", "skip") if not callable(getattr(policy, m, None))]
    if missing:
        raise ValueError(f"estimator {spec!r} does not implement {', '.join(missing)}")
    if not isinstance(getattr(policy, "name", None), str) or not policy.name:
        policy.name = spec
    if not NAME_PATTERN.fullmatch(policy.name):  # it travels in every observation
        raise ValueError(f"estimator {spec!r}: name must be {NAME_RULE}, got "
                         f"{policy.name[:MAX_NAME]!r}")
    return policy
