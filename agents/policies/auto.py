"""``auto``: run several candidate policies side by side and blend their proposals by their
recent one-step errors (beyond the paper)."""
from __future__ import annotations

import dataclasses
import math
from collections import deque

import numpy as np

from agents.estimators import NotFitted
from agents.policies.base import Policy, Proposal, reconstructed_pre, relative
from protocol.messages import Sensing


class Auto(Policy):
    """Blend the candidates' proposals with weights inversely proportional to their mean
    squared one-step error over recent ticks (Bates and Granger's forecast combination).

    Every candidate is scored each tick once the true ideal position is seen (``target``):
    ``record`` asks each candidate what it would have proposed from where the follower stood
    (:func:`reconstructed_pre`) and appends ``|offset - target|`` to a window of ``horizon``
    ticks, before the candidate learns from the tick. Scoring starts in the initial ticks,
    where nothing moves; each candidate's first ``burn_in`` scores are dropped (a least-squares
    model fitted on its minimum number of pairs says little about its later errors).
    ``propose`` weighs the candidates with at least ``min_scores`` scores by the inverse of
    their mean squared error over the ticks all of them were scored on (the same ticks for
    each: a late starter is not compared on fewer, luckier ticks). With ``blend=False`` it
    follows the lowest error alone (ties to the earlier candidate). Candidates with zero
    error share the weight equally, the others get none (the limit of inverse weights).

    Why a blend: candidates whose errors are of similar size and not fully correlated
    average to a smaller error than any one of them, and a weight that moves smoothly with
    the scores does not flip between candidates on the noise of a 4-tick score; a candidate
    far worse than the best gets a negligible weight.

    Safeguard (``trust``): the first candidate is the anchor (``persist``). A proposal that
    differs from the anchor's by more than ``trust`` times the largest error the anchor made
    within the window (the largest recent change of relative position) gets no weight: a model
    that extrapolates wildly right after a change of regime is left out; if no other candidate
    remains, the anchor is followed.
    """

    name = "auto"

    def __init__(self, candidates: list[Policy], horizon: int = 4, trust: float | None = 3.0,
                 min_scores: int = 1, burn_in: int = 1, blend: bool = True) -> None:
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
        self.blend = blend
        self.errors = [deque(maxlen=horizon) for _ in candidates]
        self.scored = [0] * len(candidates)  # ticks each candidate was scored on

    def weights(self, proposals: list[Proposal | None]) -> dict[int, float]:
        """Weight (summing to 1) of each candidate that enters the proposal, by index, given
        each candidate's proposal (None: not ready)."""
        available = [i for i, p in enumerate(proposals) if p is not None]
        if not available:
            raise NotFitted("no candidate of auto is ready")
        ready = [i for i in available if len(self.errors[i]) >= self.min_scores]
        anchor = proposals[0]
        if ready and self.trust is not None and anchor is not None and self.errors[0]:
            radius = self.trust * max(self.errors[0])
            ready = [i for i in ready if i == 0 or float(
                np.hypot(*(proposals[i].offset - anchor.offset))) <= radius]
        if not ready:
            return {0 if anchor is not None else available[0]: 1.0}
        common = min(len(self.errors[i]) for i in ready)
        mse = {i: math.fsum(e * e for e in list(self.errors[i])[len(self.errors[i]) - common:])
               / common for i in ready}
        best = min(ready, key=lambda i: (mse[i], i))
        if not self.blend:
            return {best: 1.0}
        if mse[best] == 0.0:
            exact = [i for i in ready if mse[i] == 0.0]
            return {i: 1.0 / len(exact) for i in exact}
        inverse = {i: mse[best] / mse[i] for i in ready}  # in (0, 1], 1 for the best
        total = math.fsum(inverse.values())
        return {i: w / total for i, w in inverse.items()}

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
        weights = self.weights(proposals)
        top = min(weights, key=lambda i: (-weights[i], i))
        followed = self.candidates[top].name
        if len(weights) == 1:
            return dataclasses.replace(proposals[top], followed=followed)
        offset = np.sum([w * proposals[i].offset for i, w in sorted(weights.items())], axis=0)
        # the candidates' predictions live in different lifted spaces: the blend's is the
        # predicted relative position (xy) its offset implies
        return Proposal(offset, tuple(float(v) for v in relative(pre) - offset),
                        followed=followed)

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
