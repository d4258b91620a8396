"""``auto``: run several candidate policies side by side, follow the one with the lowest recent
one-step error (beyond the paper)."""
from __future__ import annotations

import dataclasses
import math
from collections import deque

import numpy as np

from agents.estimators import NotFitted
from agents.policies.base import Policy, Proposal, reconstructed_pre
from protocol.messages import Sensing


class Auto(Policy):
    """Follow the candidate with the lowest mean squared one-step error over recent ticks.

    Every candidate is scored each tick once the true ideal position is seen (``target``):
    ``record`` asks each candidate what it would have proposed from where the follower stood
    (:func:`reconstructed_pre`) and appends ``|offset - target|`` to a window of ``horizon``
    ticks, before the candidate learns from the tick. Scoring starts in the initial ticks,
    where nothing moves; each candidate's first ``burn_in`` scores are dropped (a least-squares
    model fitted on its minimum number of pairs says little about its later errors).
    ``propose`` follows, among the candidates with at least
    ``min_scores`` scores, the one with the lowest mean squared error over the ticks all of
    them were scored on (the same ticks for each: a late starter is not compared on fewer,
    luckier ticks); ties go to the earlier candidate.

    Safeguard (``trust``): the first candidate is the anchor (``persist``). A followed
    proposal may differ from the anchor's by at most ``trust`` times the largest error the
    anchor made within the window (the largest recent change of relative position), else the
    anchor is followed for that tick: a model that extrapolates wildly right after a change
    of regime is clipped to what the recent data have shown possible.
    """

    name = "auto"

    def __init__(self, candidates: list[Policy], horizon: int = 4, trust: float | None = 3.0,
                 min_scores: int = 1, burn_in: int = 1) -> None:
        if not candidates:
            raise ValueError("candidates must not be empty")
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        if not 1 <= min_scores <= horizon:
            raise ValueError(f"min_scores must be in [1, horizon], got {min_scores}")
        if trust is not None and trust <= 0:
            raise ValueError(f"trust must be positive or None, got {trust}")
        if burn_in < 0:
            raise ValueError(f"burn_in must be >= 0, got {burn_in}")
        names = [c.name for c in candidates]
        if len(set(names)) != len(names):
            raise ValueError(f"candidate names must be unique, got {names}")
        self.candidates = candidates
        self.trust = trust
        self.min_scores = min_scores
        self.burn_in = burn_in
        self.errors = [deque(maxlen=horizon) for _ in candidates]
        self.scored = [0] * len(candidates)  # ticks each candidate was scored on

    def choose(self, proposals: list[Proposal | None]) -> int:
        """Index of the candidate to follow, given each candidate's proposal (None: not ready)."""
        ready = [i for i, p in enumerate(proposals)
                 if p is not None and len(self.errors[i]) >= self.min_scores]
        if not ready:
            ready = [i for i, p in enumerate(proposals) if p is not None][:1]
        if not ready:
            raise NotFitted("no candidate of auto is ready")
        common = min(len(self.errors[i]) for i in ready)

        def score(i: int) -> float:
            recent = list(self.errors[i])[len(self.errors[i]) - common:]
            return math.fsum(e * e for e in recent) / common if common else math.inf

        chosen = min(ready, key=lambda i: (score(i), i))
        anchor = proposals[0]
        if self.trust is None or anchor is None or not self.errors[0] or chosen == 0:
            return chosen
        radius = self.trust * max(self.errors[0])
        if float(np.hypot(*(proposals[chosen].offset - anchor.offset))) <= radius:
            return chosen
        return 0

    def _proposals(self, pre: Sensing) -> list[Proposal | None]:
        out = []
        for cand in self.candidates:
            try:
                out.append(cand.propose(pre))
            except NotFitted:
                out.append(None)
        return out

    def propose(self, pre: Sensing) -> Proposal:
        proposals = self._proposals(pre)
        i = self.choose(proposals)
        return dataclasses.replace(proposals[i], followed=self.candidates[i].name)

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        if target is not None:
            proposals = self._proposals(reconstructed_pre(settled, target))
            for i, proposal in enumerate(proposals):
                if proposal is not None:
                    self.scored[i] += 1
                    if self.scored[i] > self.burn_in:
                        self.errors[i].append(float(np.hypot(*(proposal.offset - target))))
        measured = [cand.record(settled, target) for cand in self.candidates]
        return measured[0]

    def skip(self) -> None:
        for cand in self.candidates:
            cand.skip()
