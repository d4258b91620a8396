"""The streaming interface every follower policy implements, the baselines, and fallback.

A policy sees only the :class:`protocol.messages.Sensing` replies of its own sensors. Each tick
the follower loop calls

1. :meth:`Policy.propose` with the pre-move sensing: returns a :class:`Proposal`, the xy offset
   (local frame) to the estimated ideal position plus what was predicted. It is a pure read of
   the policy's state: calling it twice, or not at all, changes nothing. The pre-move sensing
   carries the rod end only if the policy looks for it before moving
   (:attr:`Policy.looks_before_moving`), and a look costs its distance (design §4);
2. :meth:`Policy.learn` with the settled sensing, ``target``, the ideal position relative
   to where the follower stood before moving (None when it lost the rod), and ``before``, what
   the follower sensed and did earlier in the tick (:class:`Before`): the policy learns. Its
   default is :meth:`Policy.record` ``(settled, target)``, which is what most policies (and
   plug-ins) implement; a policy that uses the tick's earlier readings overrides ``learn``
   (:class:`LearnsTick`);
3. :meth:`Policy.skip` for a tick it did not take part in.

State changes only in ``learn`` (``record``) and ``skip``, and a policy is a deterministic
function of that call sequence, so a follower's state is the log of those calls (replayed
after a crash).
"""
from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np

from agents.estimators import NotFitted
from protocol.messages import Sensing

log = logging.getLogger(__name__)

DIVERGED = (ArithmeticError, np.linalg.LinAlgError)
"""What a numeric estimator raises when its arithmetic has failed (an overflow, a division by
zero, a singular system): that tick it has no estimate, as if it were not fitted, and the
follower does not stop for it (design §6)."""

# The policy-level name of "too little history to propose"; StreamingEDMD raises the same.
NotReady = NotFitted


@dataclass(frozen=True)
class Before:
    """What a follower sensed and did in one tick before it settled, in its local frame.

    Attributes
    ----------
    pre : Sensing
        The sensing before the move (the leader's range and bearing; its rod field, if any, is
        no reading a policy may use: the rod end is looked for after the move, design §5).
    moved : Sensing or None
        The sensing after the move, which the snap went by (its rod field: the rod end as seen
        from there); None in a tick without a move (the initial ticks).
    offset : tuple of float, shape (2,)
        The move the follower commanded (a driving follower: the displacement its odometry
        summed over the move phase); zeros without a move.
    """

    pre: Sensing
    moved: Sensing | None
    offset: tuple[float, float]


@dataclass(frozen=True)
class Proposal:
    """What a policy proposes for one tick.

    Attributes
    ----------
    offset : ndarray, shape (2,)
        Local-frame xy offset from where the follower stands to its estimated ideal position.
    prediction : tuple of float, optional
        The predicted lifted measurement (for the record).
    followed : str
        Name of the policy whose estimate this is (``auto``'s candidate, or ``persist`` when
        a policy that is not ready falls back); empty means the policy itself.
    fallback : bool
        True when the policy was not ready and ``persist`` proposed instead.
    """

    offset: np.ndarray
    prediction: tuple[float, ...] | None = None
    followed: str = ""
    fallback: bool = False


def drivable(proposal: Proposal) -> bool:
    """Whether ``proposal``'s offset is a place a robot can be sent to: two finite numbers (an
    estimate that overflowed or divided by zero is NaN or infinite, and is no estimate)."""
    offset = np.asarray(proposal.offset, dtype=float)
    return offset.shape == (2,) and bool(np.isfinite(offset).all())


def polar(r: float, theta: float) -> np.ndarray:
    """Vector (2,) of length ``r`` at bearing ``theta`` (radians)."""
    return np.array([r * math.cos(theta), r * math.sin(theta)])


def relative(s: Sensing) -> np.ndarray:
    """The sensed leader position relative to the follower, xy (2,)."""
    return polar(s.r, s.theta)


def reconstructed_pre(settled: Sensing, target: np.ndarray) -> Sensing:
    """The leader as seen from where the follower stood before moving, approximated from the
    settled reading: ``relative(settled) + target``.

    ``target`` is the follower's ideal position relative to where it stood, so the sum is exact
    only if it settled exactly there and ``target`` is exact: with no noise, a teleport snap.
    Otherwise it carries, besides the settled reading's sensor noise (in place of the pre
    reading's), the distance from where the follower settled to its ideal position (a snap's
    landing error; a driving follower's shortfall after its correction window) and the error
    of ``target`` (the rod-end reading after the move, and the move's actuation noise or a
    driving follower's odometry error as far as :func:`agents.follower.displacement` does not
    correct them). This lets ``record`` score what a policy would have proposed without
    keeping anything from ``propose``.

    Examples
    --------
    >>> s = reconstructed_pre(Sensing(tick=5, r=3.0, theta=0.0), np.array([0.0, 4.0]))
    >>> round(s.r, 12), round(s.theta, 12)  # leader 3 east of the follower, which came 4 north
    (5.0, 0.927295218002)
    """
    x, y = relative(settled) + np.asarray(target, dtype=float)
    return Sensing(tick=settled.tick, r=math.hypot(x, y), theta=math.atan2(y, x),
                   velocity=settled.velocity)


def looks_before_moving(policy: object) -> bool:
    """Whether ``policy`` (a :class:`Policy`, or a plug-in that need not subclass it) looks
    for its rod end before moving (:attr:`Policy.looks_before_moving`; default False)."""
    return bool(getattr(policy, "looks_before_moving", False))


class Unwrapper:
    """Keeps a bearing sequence continuous: each new angle within pi of the previous one."""

    def __init__(self) -> None:
        self.last: float | None = None

    def peek(self, theta: float) -> float:
        """``theta`` unwrapped against the last angle, without storing it."""
        if self.last is None:
            return theta
        return self.last + math.remainder(theta - self.last, 2 * math.pi)

    def __call__(self, theta: float) -> float:
        self.last = self.peek(theta)
        return self.last


class Policy:
    """Base class; subclasses implement :meth:`propose` and :meth:`record`.

    ``looks_before_moving``: the follower looks for its rod end before it moves, so the
    pre-move sensing carries it (when in range); the tick's required range is then at least
    the distance it looked from (design §4). False for every built-in policy (the paper's
    metric: the rod end is looked for after the move); a plug-in may set it.
    """

    name = "policy"
    looks_before_moving = False

    def propose(self, pre: Sensing) -> Proposal:
        """The move for this tick from the pre-move sensing (no side effects).

        Raises
        ------
        NotFitted
            When the policy has too little history to propose.
        """
        raise NotImplementedError

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        """Learn from the settled sensing; returns the measurement it recorded."""
        raise NotImplementedError

    def learn(self, settled: Sensing, target: np.ndarray | None,
              before: Before | None = None) -> tuple[float, ...]:
        """Learn from the tick: the settled sensing, ``target`` and, when the follower has
        them, the tick's earlier readings and its move (``before``; None when replaying a
        tick logged without them). The default ignores ``before``: :meth:`record`."""
        return self.record(settled, target)

    def skip(self) -> None:
        """A tick went by without this follower (it missed it or was restarting)."""

    def leverage(self, pre: Sensing) -> float | None:
        """For a least-squares model fitted on few data: how far the regressor of the coming
        proposal lies outside the span of the fitted ones (0 to 1); None (the default) for
        every other policy. ``auto`` uses it while a candidate has few scores (a pure read,
        like ``propose``)."""
        return None


class LearnsTick(Policy):
    """Base of a policy that implements :meth:`Policy.learn` (it uses the tick's earlier
    readings): its :meth:`record` is ``learn`` without them."""

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        return self.learn(settled, target)


class Stay(Policy):
    """No estimation: wait where the last tick ended (the paper's "without EDMD")."""

    name = "stay"

    def __init__(self) -> None:
        self.unwrap = Unwrapper()

    def propose(self, pre: Sensing) -> Proposal:
        return Proposal(np.zeros(2))

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        return (settled.r, self.unwrap(settled.theta))


class Persist(Policy):
    """Assume the relative position to the leader does not change (dictionary b with K = I)."""

    name = "persist"

    def __init__(self) -> None:
        self.unwrap = Unwrapper()
        self.last: tuple[float, float] | None = None

    def propose(self, pre: Sensing) -> Proposal:
        if self.last is None:
            raise NotFitted("persist needs one settled measurement")
        return Proposal(relative(pre) - polar(*self.last), self.last)

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        rel = (settled.r, self.unwrap(settled.theta))
        if target is not None or self.last is None:  # lost: keep believing the last one
            self.last = rel
        return self.last


class FallbackToPersist(LearnsTick):
    """``policy``, or ``persist``'s proposal (flagged ``fallback``) while it is not ready or
    its estimate has diverged.

    The ticks a policy could not predict are then neither silent ``stay`` ticks nor reported as
    estimated: the proposal says ``fallback=True`` and ``followed="persist"`` (design §6). A
    policy whose arithmetic fails (:data:`DIVERGED`) or that proposes no finite offset
    (:func:`drivable`) has not predicted either: the robot does not drive towards NaN or stop
    for an overflow, and the first such tick is logged (a warning: the counts are in the
    summary's ``fallback_ticks``).
    """

    def __init__(self, policy: Policy) -> None:
        self.policy = policy
        self.persist = Persist()
        self.name = policy.name
        self.looks_before_moving = looks_before_moving(policy)
        self.diverged = 0  # ticks whose proposal or learning failed arithmetically

    def _fallback(self, pre: Sensing) -> Proposal:
        return dataclasses.replace(self.persist.propose(pre), followed=self.persist.name,
                                   fallback=True)

    def _diverged(self, tick: int, what: str) -> None:
        if not self.diverged:
            log.warning("estimator %s diverged at tick %d (%s); persist stands in for it "
                        "(counted as fallback ticks)", self.name, tick, what)
        self.diverged += 1

    def propose(self, pre: Sensing) -> Proposal:
        try:
            proposal = self.policy.propose(pre)
        except NotFitted:
            return self._fallback(pre)
        except DIVERGED as exc:
            self._diverged(pre.tick, f"{type(exc).__name__}: {exc}")
            return self._fallback(pre)
        if not drivable(proposal):
            self._diverged(pre.tick, f"it proposed {np.asarray(proposal.offset).tolist()}")
            return self._fallback(pre)
        if proposal.followed:
            return proposal
        return dataclasses.replace(proposal, followed=self.policy.name)

    def learn(self, settled: Sensing, target: np.ndarray | None,
              before: Before | None = None) -> tuple[float, ...]:
        kept = self.persist.record(settled, target)
        try:
            return self.policy.learn(settled, target, before)
        except DIVERGED as exc:
            self._diverged(settled.tick, f"learning: {type(exc).__name__}: {exc}")
            return kept

    def skip(self) -> None:
        self.persist.skip()
        self.policy.skip()
