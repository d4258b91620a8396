"""Weigh ``auto`` variants offline: record every candidate's answers once, replay any rule.

A follower snaps onto the rod end each tick, so what its candidates see, propose and report
does not depend on which of them ``auto`` follows (up to the world's 1e-8 geodesic accuracy,
which matters only in cells whose errors are that small). So one run per case records:

- the follower's calls to its policy: ``propose(pre)``, ``record(settled, target)``,
  ``skip()``;
- each candidate's answers, in call order: ``propose(pre)`` (or "not ready") with its
  ``leverage(pre)``.

:func:`replay` then drives the real :class:`agents.policies.Auto`, with any options, over
stand-in candidates that give back the recorded answers in the same order, and returns the
mean required range the variant would have had: ``|offset - target|`` over the estimated
ticks, which is what the world measures when there is no actuation noise. A variant that
asked its candidates about other sensings would get an error, not a wrong number.

``python bench/replay_auto.py`` records the paper's and the held-out surfaces noise-free at
every comm period, and at the issue's middle noise level (seeds 0-4); ``--random N
--random-seed S`` records N surfaces drawn at random instead (``bench/random_surfaces.py``),
``--surfaces A,B,...`` yours (with ``--leader-start`` for every run). It then prints a few
variants side by side: ``auto``, ``auto-mix``, the leverage rule switched off, other windows
and sharpness. Recording takes a few minutes; each variant then takes seconds.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.estimators import NotFitted  # noqa: E402
from agents.policies import (FallbackToPersist, Policy, Proposal,  # noqa: E402
                             auto_candidates, make_auto)
from protocol.config import CLASSICAL, AgentSettings, RunConfig  # noqa: E402
from protocol.messages import Sensing  # noqa: E402
from swarm.local import run_local  # noqa: E402

NOT_READY = "not ready"


def _key(pre: Sensing) -> tuple[int, float, float]:
    return (pre.tick, pre.r, pre.theta)


class _Recorded(Policy):
    """A candidate that logs, for each sensing it is asked about, its proposal's offset (or
    NOT_READY) and its leverage there (taken whether or not ``auto`` asked: it is pure, and a
    variant with another window asks on other ticks)."""

    def __init__(self, policy: Policy) -> None:
        self.policy, self.name = policy, policy.name
        self.answers: list[tuple[tuple, object, float | None]] = []

    def leverage(self, pre: Sensing) -> float | None:
        return self.policy.leverage(pre)

    def propose(self, pre: Sensing) -> Proposal:
        leverage = self.policy.leverage(pre)
        try:
            proposal = self.policy.propose(pre)
        except NotFitted:
            self.answers.append((_key(pre), NOT_READY, leverage))
            raise
        self.answers.append((_key(pre), proposal.offset.copy(), leverage))
        return proposal

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        return self.policy.record(settled, target)

    def skip(self) -> None:
        self.policy.skip()


class _Replayed(Policy):
    """Gives back one candidate's recorded answers in order; learns nothing. With
    ``leverage=False`` it reports no leverage (the leverage rule switched off)."""

    def __init__(self, name: str, answers: list[tuple[tuple, object, float | None]],
                 leverage: bool = True) -> None:
        self.name, self.answers, self.at, self.with_leverage = name, answers, 0, leverage

    def _answer(self, pre: Sensing) -> tuple[tuple, object, float | None]:
        """The recorded answer for ``pre``: the next one, which must be about that sensing."""
        if self.at >= len(self.answers) or self.answers[self.at][0] != _key(pre):
            had = self.answers[self.at][0] if self.at < len(self.answers) else "nothing"
            raise RuntimeError(f"replay of {self.name!r} diverged at call {self.at}: the "
                               f"variant asked about sensing {_key(pre)}, the recording has "
                               f"{had}")
        return self.answers[self.at]

    def leverage(self, pre: Sensing) -> float | None:
        return self._answer(pre)[2] if self.with_leverage else None

    def propose(self, pre: Sensing) -> Proposal:
        offset = self._answer(pre)[1]
        self.at += 1
        if isinstance(offset, str):
            raise NotFitted(f"{self.name} was not ready")
        return Proposal(np.array(offset))

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        return (settled.r, settled.theta)


class _Calls(Policy):
    """Logs the follower's calls to its policy (the recorded ``auto``) and forwards them."""

    def __init__(self, policy: Policy) -> None:
        self.policy, self.name = policy, policy.name
        self.calls: list[tuple] = []

    def propose(self, pre: Sensing) -> Proposal:
        self.calls.append(("propose", pre))
        return self.policy.propose(pre)

    def record(self, settled: Sensing, target: np.ndarray | None) -> tuple[float, ...]:
        self.calls.append(("record", settled, None if target is None else np.array(target)))
        return self.policy.record(settled, target)

    def skip(self) -> None:
        self.calls.append(("skip",))
        self.policy.skip()


@dataclass
class Trace:
    """One recorded run of follower 1: its calls, each candidate's answers, the settings."""

    config: RunConfig
    settings: AgentSettings
    calls: list[tuple]
    answers: dict[str, list[tuple[str, object]]] = field(default_factory=dict)
    recorded_mean: float = math.nan  # the run's own mean required range (``auto``)


def record(config: RunConfig) -> Trace:
    """Run ``config`` with ``auto`` and record follower 1's calls and its candidates' answers.

    Raises ValueError for a run with actuation noise (its required range is not
    ``|offset - target|``) or without a follower.
    """
    if config.noise_move:
        raise ValueError("record needs noise_move = 0: with actuation noise the required "
                         "range is not |offset - target|")
    if config.followers < 1:
        raise ValueError("record needs at least one follower")
    made: list[tuple[_Calls, list[_Recorded]]] = []

    def factory(settings: AgentSettings) -> Policy:
        candidates = [_Recorded(c) for c in auto_candidates(settings)]
        calls = _Calls(make_auto(settings, candidates))
        made.append((calls, candidates))
        return FallbackToPersist(calls)

    summary, _ = run_local(dataclasses.replace(config, estimator="auto"),
                           policy_factory=factory)
    calls, candidates = made[0]
    return Trace(config, AgentSettings.from_config(config), calls.calls,
                 {c.name: c.answers for c in candidates},
                 summary["followers"]["1"]["mean_required_range"])


def _errors(trace: Trace, propose, record, skip) -> dict[int, float]:
    """Walk ``trace``'s calls: ``propose(pre)`` gives an offset (None: nothing to go by),
    ``record(settled, target)`` and ``skip()`` follow the rest; returns ``|offset - target|``
    per estimated tick (from ``init_ticks`` on)."""
    first = trace.config.init_ticks
    errors, pending = {}, None
    for call in trace.calls:
        if call[0] == "propose":
            offset = propose(call[1])
            pending = None if offset is None else (call[1].tick, offset)
        elif call[0] == "record":
            _, settled, target = call
            if pending is not None and target is not None and pending[0] >= first:
                errors[pending[0]] = float(np.hypot(*(np.asarray(pending[1]) - target)))
            pending = None
            record(settled, target)
        else:
            pending = None
            skip()
    return errors


def replay_errors(trace: Trace, leverage: bool = True, **options) -> dict[int, float]:
    """Per estimated tick, the required range (``|offset - target|``) :class:`Auto` with
    ``options`` would have had in ``trace`` (``noise_floor`` defaults to the run's, as
    ``make_policy`` sets it; ``leverage=False`` switches the leverage rule off)."""
    auto = FallbackToPersist(make_auto(trace.settings, [
        _Replayed(name, answers, leverage) for name, answers in trace.answers.items()],
        **options))

    def propose(pre: Sensing) -> np.ndarray | None:
        try:
            return auto.propose(pre).offset
        except NotFitted:  # nothing to go by yet (the first tick), as in the run
            return None

    return _errors(trace, propose, auto.record, auto.skip)


def replay(trace: Trace, leverage: bool = True, **options) -> float:
    """The mean of :func:`replay_errors`: the mean required range of that variant."""
    return _mean(replay_errors(trace, leverage, **options))


def _mean(errors: dict[int, float]) -> float:
    return math.fsum(errors.values()) / len(errors) if errors else math.nan


def candidate_errors(trace: Trace, name: str) -> dict[int, float]:
    """Per estimated tick, the required range of candidate ``name`` on its own (what
    ``--estimator name`` needs, up to the world's 1e-8): its recorded proposal at each
    ``propose``, ``persist``'s (the first candidate) while it was not ready.

    ``auto`` asks every candidate once per ``propose`` and once per ``record`` with a
    target (to score it), in that order; the recording is walked the same way."""
    if name not in trace.answers:
        raise ValueError(f"no candidate {name!r} in the recording: {sorted(trace.answers)}")
    anchor = next(iter(trace.answers))
    walks = {n: iter(trace.answers[n]) for n in (anchor, name)}

    def propose(pre: Sensing) -> object:
        answers = {n: next(walk) for n, walk in walks.items()}
        if any(a[0] != _key(pre) for a in answers.values()):
            raise RuntimeError(f"the recording of {name!r} does not follow its calls")
        own = answers[name][1]
        return answers[anchor][1] if isinstance(own, str) else own

    def record(settled: Sensing, target: np.ndarray | None) -> None:
        if target is not None:
            for walk in walks.values():
                next(walk)  # the scoring answer

    return _errors(trace, propose, record, lambda: None)


def where_it_loses(auto: dict[int, float], best: dict[int, float],
                   startup: int = 4) -> tuple[float, float]:
    """A cell's excess of ``auto``'s mean over the best classical baseline's (per-tick errors
    of both, over the same ticks) and the part of it from the first ``startup`` estimated
    ticks."""
    ticks = sorted(auto)
    excess = [(auto[t] - best[t]) / len(ticks) for t in ticks]
    return math.fsum(excess), math.fsum(excess[:startup])


def oracle_startup_above(auto: dict[int, float], best: dict[int, float], startup: int) -> bool:
    """Whether ``auto``'s mean would still be above ``best``'s if, on the first ``startup``
    estimated ticks, it had never been worse than ``best`` (an oracle no rule can be)."""
    ticks = sorted(auto)
    mine = [min(auto[t], best[t]) if i < startup else auto[t] for i, t in enumerate(ticks)]
    return math.fsum(mine) > math.fsum(best[t] for t in ticks)


VARIANTS = {
    "auto": {},
    "auto-mix": {"combine": "weights"},
    "auto, no leverage rule": {"leverage": False},
    "auto-mix, no leverage rule": {"combine": "weights", "leverage": False},
    "auto, 8-tick window": {"horizon": 8},
    "auto-mix, sharpness 3": {"combine": "weights", "sharpness": 3.0},
    "auto-mix, memory 0.8": {"combine": "weights", "memory": 0.8},
    "auto-mix, no blend": {"combine": "weights", "blend": False},
}


def main() -> None:
    from bench.bench_estimator_table import (COMM_PERIODS, HELD_OUT, NOISE_LEVELS, PAPER,
                                             add_surface_arguments, chosen_surfaces, required)

    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="the paper's surfaces, T_c 1.28, seed 0")
    add_surface_arguments(p)
    args = p.parse_args()
    surfaces, base = chosen_surfaces(p, args, PAPER if args.quick else PAPER + HELD_OUT)
    periods = (1.28,) if args.quick else COMM_PERIODS
    seeds = (0,) if args.quick else (0, 1, 2, 3, 4)
    start = time.perf_counter()
    clean = {(s, tc): record(RunConfig(surface=s, comm_period=tc, **base)) for s in surfaces
             for tc in periods}
    noisy = {(s, seed): record(RunConfig(surface=s, seed=seed, noise_range=NOISE_LEVELS[1][0],
                                         noise_bearing=NOISE_LEVELS[1][1], **base))
             for s in surfaces for seed in seeds}
    best = {cell: min(required(cell[0], cell[1], estimator=name, **base) for name in CLASSICAL)
            for cell in clean}
    print(f"recorded {len(clean) + len(noisy)} runs and the classical baselines in "
          f"{time.perf_counter() - start:.0f} s (persist below: the same seeds)")
    persist = {s: required(s, 1.28, seeds, estimator="persist", noise_range=NOISE_LEVELS[1][0],
                           noise_bearing=NOISE_LEVELS[1][1], **base) for s in surfaces}
    print(f"{'variant':<30}{'noise-free > best classical':>30}{'geo-mean ratio':>16}"
          f"{'noisy persist/x min':>21}{'median':>8}   (middle level {NOISE_LEVELS[1]})")
    replayed = {}  # per-tick errors of auto and auto-mix, for the start-up report
    for label, options in VARIANTS.items():
        start = time.perf_counter()
        clean_errors = {cell: replay_errors(t, **options) for cell, t in clean.items()}
        if label in STARTUP_REPORTED:
            replayed[label] = clean_errors
        clean_means = {cell: _mean(errors) for cell, errors in clean_errors.items()}
        noisy_means = {key: replay(t, **options) for key, t in noisy.items()}
        if not options:  # auto itself: the check that replay reproduces the runs
            mismatch = max(abs(means[key] - t.recorded_mean) / t.recorded_mean
                           for means, traces in ((clean_means, clean), (noisy_means, noisy))
                           for key, t in traces.items())
        ratios = [clean_means[cell] / best[cell] for cell in clean]
        gains = [persist[s] / np.mean([m for (surface, _), m in noisy_means.items()
                                       if surface == s]) for s in surfaces]
        print(f"{label:<30}{f'{sum(r > 1 for r in ratios)} of {len(ratios)}':>30}"
              f"{math.exp(sum(map(math.log, ratios)) / len(ratios)):>16.3f}"
              f"{min(gains):>21.2f}{float(np.median(gains)):>8.1f}"
              f"   ({time.perf_counter() - start:.1f} s)")
    print(f"replaying auto reproduces the recorded runs to {mismatch:.1e} (relative)")
    print(startup_report(clean, replayed))


STARTUP_REPORTED = ("auto", "auto-mix")


def startup_report(clean: dict, replayed: dict, startup: int = 4,
                   oracles: tuple[int, ...] = (1, 2, 4)) -> str:
    """Where ``auto`` and ``auto-mix`` lose to the best classical baseline, noise-free (their
    per-tick errors in ``replayed[label][cell]``): in how many of those cells the first
    ``startup`` estimated ticks hold at least the whole excess, and how many would remain if,
    on the first k ticks, the estimator had never been worse than that baseline (an oracle
    start-up; each k of ``oracles``)."""
    lines = ["where they lose (best classical baseline per cell from the recorded candidates; "
             "oracle k: never worse than it on the first k estimated ticks)"]
    best = {}
    for cell, trace in clean.items():
        errors = [candidate_errors(trace, name) for name in CLASSICAL]
        best[cell] = min(errors, key=lambda e: math.fsum(e.values()))
    for label in STARTUP_REPORTED:
        mine = replayed[label]
        excess = {cell: where_it_loses(mine[cell], best[cell], startup) for cell in clean}
        above = [cell for cell, (total, _) in excess.items() if total > 0]
        early = sum(1 for cell in above if excess[cell][1] >= excess[cell][0])
        left = ", ".join(
            f"oracle {k}: {sum(oracle_startup_above(mine[c], best[c], k) for c in above)}"
            for k in oracles)
        lines.append(f"{label:<10} above in {len(above)} of {len(clean)}; the first {startup} "
                     f"estimated ticks hold the whole excess in {early}; still above with {left}")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
