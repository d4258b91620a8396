"""An estimator of one's own, loaded as ``--estimator tests.example_estimator:MeanStep``."""
from __future__ import annotations

import os
import signal

import numpy as np

from agents.policies import NotReady, Proposal, relative
from protocol.limits import MAX_NAME


class MeanStep:
    """Predict the leader's relative position by its mean change over the last ``n`` ticks."""

    name = "mean-step"

    def __init__(self, settings, n: int = 4) -> None:
        self.n = n
        self.history: list[np.ndarray] = []  # relative positions, oldest first (data only)

    def propose(self, pre):  # a pure read of the state
        if len(self.history) <= self.n:
            raise NotReady(f"mean-step needs {self.n + 1} relative positions")
        last, first = self.history[-1], self.history[-1 - self.n]
        predicted = last + (last - first) / self.n
        return Proposal(relative(pre) - predicted, tuple(predicted))

    def record(self, settled, target):  # learn from the settled sensing
        self.history = self.history[-self.n:] + [relative(settled)]
        return tuple(self.history[-1])

    def skip(self):  # a missed tick: the history no longer has a constant step
        self.history = []


def not_a_policy(settings):
    """A factory that returns something without the streaming interface."""
    return object()


class LongName(MeanStep):
    """A policy whose name is one character too long to travel in an observation."""

    name = "x" * (MAX_NAME + 1)


class LongestName(MeanStep):
    """A policy whose name is as long as an observation carries."""

    name = "n" * MAX_NAME


class KillsItsProcess(MeanStep):
    """Ends the process it runs in at its first proposal, as the kernel's out-of-memory killer
    would (for the grid runner's tests: a run whose worker dies every time)."""

    name = "kills-its-process"

    def propose(self, pre):
        os.kill(os.getpid(), signal.SIGKILL)


class FailsAtTick(MeanStep):
    """Raises in ``propose`` once it has a full history (from tick 5 on): a plug-in's bug."""

    def propose(self, pre):
        if len(self.history) > self.n:
            raise KeyError("no such column 'x'")
        return super().propose(pre)


SETTINGS_SEEN: list = []
"""The settings every :class:`NotesItsSettings` was built with (a test reads them)."""


class NotesItsSettings(MeanStep):
    """Notes the settings its factory was given in :data:`SETTINGS_SEEN`."""

    name = "notes-its-settings"

    def __init__(self, settings, n: int = 4) -> None:
        super().__init__(settings, n)
        SETTINGS_SEEN.append(settings)
