"""``auto`` and ``auto-mix``: run several candidate policies side by side and score each on every
tick; ``auto`` uses the one with the lowest recent one-step error (design §6), ``auto-mix`` their
exponentially weighted mixture; one of the candidates is the blend of the others (beyond the
paper)."""
from __future__ import annotations

import dataclasses
import functools
import math
from collections import deque
from statistics import NormalDist

import numpy as np

from agents.estimators import NotFitted
from agents.policies.base import (
    DIVERGED,
    Before,
    LearnsTick,
    Policy,
    Proposal,
    drivable,
    reconstructed_pre,
    relative,
)
from protocol.config import AUTO
from protocol.messages import Sensing

BLEND = "blend"
COMBINE = dict(zip(AUTO, ("best", "weights")))  # estimator name -> how it follows


def student_within(t: float, dof: int) -> float:
    """``P(|T| <= t)`` for Student's t with ``dof`` >= 1 degrees of freedom (``t`` >= 0), in
    closed form (Abramowitz and Stegun 26.7.3-4).

    >>> round(student_within(1.0, 1), 12), round(student_within(2.919986, 2), 6)
    (0.5, 0.9)
    """
    theta = math.atan(t / math.sqrt(dof))
    c2, sine = math.cos(theta) ** 2, math.sin(theta)
    if dof % 2:  # odd: 2/pi (theta + sin cos (1 + 2/3 cos^2 + 2*4/(3*5) cos^4 + ...))
        term, total = 1.0, 1.0 if dof > 1 else 0.0
        for k in range(1, (dof - 1) // 2):
            term *= 2 * k / (2 * k + 1) * c2
            total += term
        return 2.0 / math.pi * (theta + sine * math.cos(theta) * total)
    term, total = 1.0, 1.0  # even: sin (1 + 1/2 cos^2 + 1*3/(2*4) cos^4 + ...)
    for k in range(1, dof // 2):
        term *= (2 * k - 1) / (2 * k) * c2
        total += term
    return sine * total


@functools.cache  # a bisection; auto asks it every tick with a handful of arguments
def family_threshold(z: float, tests: int, dof: int) -> float:
    """The one-sided threshold of a paired t-test with ``dof`` degrees of freedom that keeps
    the chance of any of ``tests`` false alarms at that of one normal test at ``z`` standard
    errors (Bonferroni).

    >>> round(family_threshold(2.0, 1, 10**4), 2), round(family_threshold(2.0, 15, 3), 2)
    (2.0, 8.86)
    """
    tail = (1.0 - NormalDist().cdf(z)) / max(tests, 1)  # each test's false-alarm chance
    low, high = 0.0, 1.0
    while (1.0 - student_within(high, dof)) / 2.0 > tail:
        high *= 2.0
    for _ in range(60):
        mid = 0.5 * (low + high)
        low, high = (mid, high) if (1.0 - student_within(mid, dof)) / 2.0 > tail else (low, mid)
    return high


def _weighted(pre: Sensing, proposals: list[Proposal | None], weights: dict[int, float],
              followed: str) -> Proposal:
    """The weighted mean of the proposals' offsets (weights by index, summing to 1). The
    candidates' predictions live in different lifted spaces: the mean's is the predicted
    relative position (xy) its offset implies."""
    offset = np.sum([w * proposals[i].offset for i, w in sorted(weights.items())], axis=0)
    return Proposal(offset, tuple(float(v) for v in relative(pre) - offset), followed=followed)


def _sum(values) -> float:
    """``math.fsum`` of ``values``, infinite where it overflows (the scores of an estimate that
    diverged), NaN where infinities of both signs meet."""
    try:
        return math.fsum(values)
    except OverflowError:
        return math.inf
    except ValueError:  # -inf + inf
        return math.nan


def _learned(cand: Policy, settled: Sensing, target: np.ndarray | None,
             before: Before | None) -> None:
    """``cand`` learns the tick; if its arithmetic fails (:data:`DIVERGED`) the other
    candidates learn on, and it proposes again when it can."""
    try:
        cand.learn(settled, target, before)
    except DIVERGED:
        pass


def _exact(losses: dict[int, float]) -> dict[int, float]:
    """Equal weights (summing to 1) over the candidates, by index, whose loss is nil."""
    exact = [i for i, loss in losses.items() if loss == 0.0]
    return {i: 1.0 / len(exact) for i in exact}


class Auto(LearnsTick):
    """Follow the candidates by their recent one-step errors (design §6); with ``blend=True`` the
    candidates include their own *blend*: the weighted mean of their proposals with weights
    inversely proportional to their mean squared errors over the window (Bates and Granger's
    forecast combination), scored like any other candidate.

    How the scored candidates (the blend among them) are followed, ``combine``:

    - ``"best"`` (the default, ``auto``, design §6): the one candidate with the lowest mean squared
      error over the window (follow the leader);
    - ``"weights"`` (``auto-mix``): the exponentially weighted mixture of their proposals. Each
      candidate's loss ``L`` is the discounted mean of its squared errors (each tick
      ``L <- memory L + (1 - memory) e**2``) and its weight is proportional to
      ``exp(-sharpness (L - L_min) / L_min)``: a candidate whose loss is twice the lowest gets
      ``exp(-sharpness)`` of the best one's weight, one ten times worse practically none, so
      with one clearly better candidate this is that candidate, and among candidates of
      similar loss it averages instead of switching on the luck of the last few ticks (the
      exponentially weighted average forecaster of prediction with expert advice, scale-free
      by ``L_min``). ``followed`` names the candidate with the largest weight.

    Every candidate is scored each tick once the true ideal position is seen (``target``):
    ``record`` asks each candidate what it would have proposed from where the follower stood
    (:func:`reconstructed_pre`) and appends ``|offset - target|`` to a window of ``horizon``
    ticks, before the candidate learns from the tick; the blend is scored with the weights it
    had at that moment. Scoring starts in the initial ticks, where nothing moves; each
    candidate's first ``burn_in`` scores are dropped (a least-squares model fitted on its
    minimum number of pairs says little about its later errors). ``propose`` uses the
    candidates with at least ``min_scores`` scores. The blend's weights and ``"best"`` compare
    them over the ticks all of them were scored on (the same ticks for each: a late starter is
    not compared on fewer, luckier ticks; ties to the earlier candidate, the blend last); the
    ``"weights"`` mixture uses each candidate's own discounted loss.

    Why a blend among the candidates: candidates whose errors are of similar size and not fully
    correlated average to a smaller error than any one of them, so the blend is often the best
    candidate; when one candidate is clearly better, it is followed alone. Why ``auto-mix``:
    following the lowest of 15 noisy 4-tick scores chases luck where no candidate is clearly
    better (large comm periods, sensor noise); the README has the comparison.

    Why ``significance`` (``"best"`` only): the lowest of many candidates' window means is
    biased low — with noisy scores some candidate is always lucky (the winner's curse), and
    following it replaces the blend's averaging with one candidate's noise. So a candidate is
    followed instead of the blend only when it beat the blend significantly over their common
    window: the mean of the paired differences of squared errors below zero by more than
    ``significance`` standard errors (a one-sided paired test; 2 is the usual ~95 % level).
    Systematic differences (noise-free, or one candidate clearly right) pass it; luck does
    not. ``None`` follows the lowest score as it is.

    Why ``default`` (``"best"`` only; None: the blend): the candidate followed unless another
    beats it significantly, in place of the blend; all the other candidates challenge it, so
    the best of them must pass the family-wise threshold of that many one-sided paired
    t-tests on the window's few ticks (:func:`family_threshold`): otherwise one of 15
    candidates passes by luck most ticks. (The blend's one challenger keeps the normal
    threshold the noise-free rules were chosen with.) ``make_auto`` names the model-based filter
    (``ekf``) when the run declares sensor noise: its errors follow from a model of the motion
    and of the declared noise, not from a fit to the window, and its proposal already averages
    every reading of the tick; blending it with the model-free candidates, whose errors all
    carry the pre reading's noise unaveraged, adds back the noise it removed (inverse-MSE
    weights assume independent errors, which they are not).

    Why ``made`` (False: scores from :func:`reconstructed_pre`): with it, a candidate is scored
    on the proposal it made, from the tick's own ``pre`` reading (``propose`` is pure and the
    candidates have not learnt yet, so asking again gives the same proposal), whenever
    ``learn`` is given it. The reconstruction adds the target's own error to the pre reading,
    which cancels in the score of a candidate that proposes the reading plus an offset (all
    the model-free ones) but not in that of a filter that weighs the reading against its track
    (``ekf``): its scores then carry a share of the target's error the others' do not, a bias
    against it that is largest exactly where it is best. From the real reading every
    candidate's score carries the target's error alike (independent of the proposals, it
    leaves their paired differences unbiased). ``make_auto`` sets it when the run declares
    sensor noise; noise-free runs keep the reconstruction (and their numbers).

    Safeguard (``trust``): the first candidate is the anchor (``persist``). A proposal that
    differs from the anchor's by more than ``trust`` times the largest error the anchor made
    within the window (the largest recent change of relative position) is left out (of the
    blend too): a model that extrapolates wildly right after a change of regime is not
    followed; if no other candidate remains, the anchor is followed. The ``default`` is exempt:
    a filter that weighs the tick's ``pre`` reading against its motion model departs from the
    anchor (which takes the reading as it is) by that reading's error, and an outlying reading
    is exactly when it departs farthest and is most right; the radius, scaled by the anchor's
    past errors, cannot tell that from a wild extrapolation. (Measured: held-out
    ``twisted_saddle`` at σ 0.015/0.04, seed 4, one tick with a reading ~3.5 σ off left ``ekf``
    out, and ``auto`` followed the blend 0.5 off: its mean 0.026 against ``ekf``'s 0.011.)
    """

    def __init__(self, candidates: list[Policy], horizon: int = 4, trust: float | None = 3.0,
                 min_scores: int = 1, burn_in: int = 1, blend: bool = True,
                 combine: str = "best", sharpness: float = 1.0, memory: float = 0.6,
                 noise_floor: float = 0.0, significance: float | None = 2.0,
                 default: str | None = None, made: bool = False,
                 name: str | None = None) -> None:
        if not candidates:
            raise ValueError("candidates must not be empty")
        if combine not in COMBINE.values():
            raise ValueError(f"combine must be one of {tuple(COMBINE.values())}, "
                             f"got {combine!r}")
        if not sharpness > 0:
            raise ValueError(f"sharpness must be positive, got {sharpness}")
        if not 0 <= memory < 1:
            raise ValueError(f"memory must be in [0, 1), got {memory}")
        if not 0 <= noise_floor < math.inf:
            raise ValueError(f"noise_floor must be finite and >= 0, got {noise_floor}")
        if significance is not None and not 0 <= significance < math.inf:
            raise ValueError(f"significance must be finite and >= 0 or None, got {significance}")
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
        if default is not None and default not in names:
            raise ValueError(f"default must name a candidate ({names}), got {default!r}")
        self.default = None if default is None else names.index(default)
        self.candidates = candidates
        self.trust = trust
        self.min_scores = min_scores
        self.burn_in = burn_in
        self.blend = blend
        self.combine, self.sharpness, self.memory = combine, sharpness, memory
        self.noise_floor = noise_floor
        self.significance = significance
        self.made = made
        self.name = name or next(n for n, how in COMBINE.items() if how == combine)
        # one score window per candidate, the blend's last
        self.errors = [deque(maxlen=horizon) for _ in range(len(candidates) + 1)]
        self.loss: list[float | None] = [None] * (len(candidates) + 1)  # discounted e**2
        # each score's leverage (Policy.leverage) when it was made, aligned with the windows
        self.levels = [deque(maxlen=horizon) for _ in range(len(candidates) + 1)]
        self.scored = [0] * (len(candidates) + 1)  # ticks each was scored on
        # the last propose()'s reading, leverages and proposals, until learn or skip
        self._asked: tuple[Sensing, list, list] | None = None

    def _eligible(self, proposals: list[Proposal | None]) -> list[int]:
        """Candidates (by index) with enough scores and a proposal within the trust radius
        (the anchor and the ``default`` are trusted)."""
        ready = [i for i, p in enumerate(proposals)
                 if p is not None and len(self.errors[i]) >= self.min_scores]
        anchor = proposals[0]
        if ready and self.trust is not None and anchor is not None and self.errors[0]:
            radius = self.trust * max(self.errors[0])
            ready = [i for i in ready if i in (0, self.default) or float(
                np.hypot(*(proposals[i].offset - anchor.offset))) <= radius]
        return ready

    def _leverages(self, pre: Sensing) -> list[float | None]:
        """Each candidate's :meth:`Policy.leverage` for ``pre`` while its score window is not
        yet full, the only time it is used; None otherwise (and for the blend)."""
        return [cand.leverage(pre) if len(self.errors[i]) < self.errors[i].maxlen else None
                for i, cand in enumerate(self.candidates)] + [None]

    def _young(self, i: int, now: list[float | None] | None) -> bool:
        """Candidate ``i`` reports a leverage and its score window is not yet full."""
        return now is not None and now[i] is not None and (
            len(self.errors[i]) < self.errors[i].maxlen)

    def _adjusted(self, i: int, now: list[float | None] | None) -> list[float]:
        """Candidate ``i``'s scores as judged for the coming proposal.

        While the window of a candidate with a leverage (a least-squares model fitted on few
        pairs) is not yet full, the part of each squared score above the noise floor ``f`` is
        scaled by ``s**2``, ``s = min(1, now / then)`` of its leverages:
        ``sqrt(f + max(0, e**2 - f) s**2)``. Its next error shrinks with how much less the
        coming regressor sticks out of the data than the scored one did; the sensor noise's
        share of a score does not. Otherwise the scores as they are."""
        errors = list(self.errors[i])
        if not self._young(i, now):
            return errors
        floor, out = self.noise_floor, []
        for e, then in zip(errors, self.levels[i]):
            scale = min(1.0, now[i] / then) if then else 1.0
            out.append(math.sqrt(floor + max(0.0, e * e - floor) * scale * scale))
        return out

    def _mse(self, ready: list[int], now: list[float | None] | None = None) -> dict[int, float]:
        common = min(len(self.errors[i]) for i in ready)
        return {i: _sum(e * e for e in self._adjusted(i, now)[-common:]) / common
                for i in ready}

    def _beats(self, i: int, j: int, now: list[float | None] | None,
               challengers: int = 1) -> bool:
        """Candidate ``i``'s squared errors were lower than ``j``'s over their common window
        by more than ``significance`` standard errors of the paired differences (always,
        with ``significance`` None); with several ``challengers`` of ``j`` (``i`` the best of
        them), by the family-wise threshold of a paired t-test on the window
        (:func:`family_threshold`)."""
        if self.significance is None:
            return True
        common = min(len(self.errors[i]), len(self.errors[j]))
        if common < 2:
            return False
        level = self.significance if challengers == 1 else family_threshold(
            self.significance, challengers, common - 1)
        mine, theirs = self._adjusted(i, now)[-common:], self._adjusted(j, now)[-common:]
        diffs = [a * a - b * b for a, b in zip(mine, theirs)]
        mean = _sum(diffs) / common
        if not math.isfinite(mean):  # one side's errors overflowed (a diverged estimate)
            return mean < 0.0
        spread = math.sqrt(_sum((d - mean) * (d - mean) for d in diffs) / (common - 1))
        return mean < -level * spread / math.sqrt(common)

    def weights(self, proposals: list[Proposal | None],
                now: list[float | None] | None = None) -> dict[int, float]:
        """The blend's weight (summing to 1) of each candidate that enters it, by index
        (``now``: the candidates' leverages for this proposal, see :meth:`_adjusted`)."""
        ready = self._eligible(proposals)
        if not ready:
            raise NotFitted("no candidate of auto is scored yet")
        mse = self._mse(ready, now)
        best = min(ready, key=lambda i: (mse[i], i))
        if not math.isfinite(mse[best]):
            raise NotFitted("every scored candidate of auto has diverged")
        if mse[best] == 0.0:
            return _exact(mse)
        inverse = {i: mse[best] / mse[i] for i in ready}  # in (0, 1], 1 for the best
        total = math.fsum(inverse.values())
        return {i: w / total for i, w in inverse.items()}

    def _loss(self, i: int, now: list[float | None] | None) -> float:
        """Candidate ``i``'s discounted loss, from its adjusted scores while its window is not
        yet full (it then holds all of them)."""
        if not self._young(i, now):
            return self.loss[i]
        loss = None
        for e in self._adjusted(i, now):
            loss = self._discounted(loss, e)
        return loss

    def _discounted(self, loss: float | None, error: float) -> float:
        """A discounted loss after one more ``error`` (its square alone for the first)."""
        return error * error if loss is None else (
            self.memory * loss + (1.0 - self.memory) * error * error)

    def mixture(self, ready: list[int],
                now: list[float | None] | None = None) -> dict[int, float]:
        """The ``"weights"`` mixture's weight (summing to 1) of each ready candidate, by index."""
        losses = {i: self._loss(i, now) for i in ready}
        lowest = min(losses.values())
        if not math.isfinite(lowest):
            raise NotFitted("every scored candidate of auto has diverged")
        if lowest == 0.0:
            return _exact(losses)
        raw = {i: math.exp(-self.sharpness * (loss - lowest) / lowest)
               for i, loss in losses.items()}
        total = math.fsum(raw.values())
        return {i: w / total for i, w in raw.items() if w > 0.0}

    def _name(self, index: int) -> str:
        return BLEND if index == len(self.candidates) else self.candidates[index].name

    def _blended(self, pre: Sensing, proposals: list[Proposal | None],
                 now: list[float | None] | None) -> Proposal | None:
        """The blend's proposal, or None while fewer than two candidates enter it."""
        if not self.blend:
            return None
        try:
            weights = self.weights(proposals, now)
        except NotFitted:
            return None
        if len(weights) < 2:
            return None
        return _weighted(pre, proposals, weights, BLEND)

    def _proposals(self, pre: Sensing,
                   now: list[float | None] | None = None) -> list[Proposal | None]:
        """Each candidate's proposal (None: not ready), the blend's last."""
        out = []
        for cand in self.candidates:
            try:
                proposal = cand.propose(pre)
            except (NotFitted, *DIVERGED):  # not ready, or its arithmetic failed this tick
                proposal = None
            out.append(proposal if proposal is None or drivable(proposal) else None)
        return out + [self._blended(pre, out, now)]

    def _asked_for(self, pre: Sensing) -> tuple[list, list]:
        """The leverages and proposals for ``pre``: those the last :meth:`propose` had if it
        was for ``pre`` and nothing was learnt since (the candidates are pure until they
        learn, so scoring the proposals made, ``made``, need not ask them again)."""
        if self._asked is not None and self._asked[0] == pre:
            return self._asked[1], self._asked[2]
        now = self._leverages(pre)
        return now, self._proposals(pre, now)

    def propose(self, pre: Sensing) -> Proposal:
        now = self._leverages(pre)
        proposals = self._proposals(pre, now)
        self._asked = (pre, now, proposals)
        if all(p is None for p in proposals):
            raise NotFitted("no candidate of auto is ready")
        ready = self._eligible(proposals)
        if not ready:  # nothing scored or trusted: the anchor, else whoever is ready
            top = 0 if proposals[0] is not None else next(
                i for i, p in enumerate(proposals) if p is not None)
        elif self.combine == "best":
            mse = self._mse(ready, now)
            top = min(ready, key=lambda i: (mse[i], i))
            blend = len(self.candidates)
            if self.default is None:  # the blend, challenged by the best candidate
                default, challengers = blend, 1
            else:  # a named candidate, challenged by all the others
                default, challengers = self.default, len(ready) - 1
            if top != default and default in ready and not self._beats(top, default, now,
                                                                         challengers):
                top = default
        else:
            weights = self.mixture(ready, now)
            top = min(weights, key=lambda i: (-weights[i], i))
            if len(weights) > 1:
                return _weighted(pre, proposals, weights, self._name(top))
        return dataclasses.replace(proposals[top], followed=self._name(top))

    def learn(self, settled: Sensing, target: np.ndarray | None,
              before: Before | None = None) -> tuple[float, ...]:
        """Score every candidate on the tick (from :func:`reconstructed_pre`, or with ``made``
        from the tick's own ``pre`` reading; see the class), then let each learn from it,
        ``before`` included."""
        if target is not None:
            pre = before.pre if self.made and before is not None else reconstructed_pre(
                settled, target)
            now, proposals = self._asked_for(pre)
            for i, proposal in enumerate(proposals):
                if proposal is not None:
                    self.scored[i] += 1
                    if self.scored[i] > self.burn_in:
                        error = float(np.hypot(*(proposal.offset - target)))
                        self.errors[i].append(error)
                        self.levels[i].append(now[i])
                        self.loss[i] = self._discounted(self.loss[i], error)
        self._asked = None
        anchor, *others = self.candidates
        measured = anchor.learn(settled, target, before)  # auto records the anchor's
        for cand in others:
            _learned(cand, settled, target, before)
        return measured

    def skip(self) -> None:
        self._asked = None
        for cand in self.candidates:
            cand.skip()
