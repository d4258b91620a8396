"""A follower: estimates its leader's rod end, moves there, snaps on it
(``python -m agents.follower``).

One tick (design §4): sense the leader (the pre-move sensing, once; it carries the rod end
only if the follower looks for it: always in an initial tick, else if its policy
``looks_before_moving``, and the look then counts in the tick's required range) and ask the
policy for its estimate; from tick ``init_ticks`` on, move there (the reply is the sensing
after the move, which looks for the rod end); snap onto the rod end if it is in range, else
count a lost tick (the reply is the settled sensing); record the measurement; publish the
observation and the rod. Three round trips to the world per tick.

With ``--motion drive`` the move and the snap are control steps (:mod:`agents.drive`: one
round trip each, to the estimate — in the initial ticks to the rod end sensed at ``pre`` —
then onto the rod end), and the snap request only settles the follower where it stands. The
controller's state lives within the tick (its dead reckoning starts afresh at every tick) but
for its track of past displacements, which it learns from the settled sensing as the policy
does, so the replay log rebuilds both: a tick redone after a restart is driven again from its
start.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zenoh

from agents.checkpoint import Entry, StateLog, replay
from agents.cli import parser, run_cli
from agents.drive import Driven, Limits, Track, beyond_noise, drive_tick
from agents.link import AgentAbort, AgentLink, MarkedMissed, Rejoin, RunFinished
from agents.policies import (
    Before,
    NotReady,
    Policy,
    looks_before_moving,
    make_policy,
    move_variance,
    reading_variance,
    relative,
)
from protocol.cli import exit_process, program
from protocol.config import AgentSettings
from protocol.messages import Move, Observation, Sensing, Snap

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TickOutcome:
    """What one follower tick produced: the observation it publishes, and what its policy
    learnt from (the settled sensing, the target and what came before in the tick), which the
    replay log keeps."""

    observation: Observation
    settled: Sensing
    target: np.ndarray | None
    before: Before


def displacement(offset: np.ndarray, pre: Sensing, moved: Sensing,
                 settings: AgentSettings) -> np.ndarray:
    """Where the follower's ideal position was relative to where it stood before moving (the
    ``target`` its policy learns from), as well as the follower can tell: the offset it
    commanded (a driving follower: the displacement its odometry summed) plus the rod end it
    read after the move (a noisy reading, design §5), corrected for the move's actuation noise
    (a driving follower: its odometry's error).

    The move landed ``eta`` off the command (declared variance ``noise_move**2`` per
    coordinate), which would enter the target whole. The two readings of the leader around the
    move see it: ``relative(pre) - relative(moved) - offset = eta +`` their sensor noise
    (variance twice :func:`agents.policies.reading_variance`), so the estimate is added with
    the minimum-variance weight ``w = s_m / (s_m + 2 s_r)``: all of it without sensor noise,
    none without actuation noise (the target is then ``offset + rod``).
    """
    target = offset + np.asarray(moved.rod)
    actuation = move_variance(settings)
    if actuation == 0.0:
        return target
    weight = actuation / (actuation + 2.0 * reading_variance(settings))
    return target + weight * (relative(pre) - relative(moved) - offset)


def at_rod_end(settled: Sensing, driven: Driven) -> Sensing:
    """The settled sensing of a driving follower as seen from the rod end it drove onto: the
    leader reading, fused from every look of the tick
    (:meth:`agents.drive.Driven.settled_leader`; without noise, the settled reading as it is),
    shifted by the follower's best estimate of the rod end's offset
    (:class:`agents.drive.Driven`), weighted ``|e|² / (|e|² + 9 var)`` by its declared variance
    (:func:`agents.drive.beyond_noise`).

    A follower that settled off its rod end would otherwise give its estimator a relative
    position the formation never had; its estimator learns the formation's relative motion
    (design §6), and the follower's own offset is what its next estimate corrects for anyway
    (it is sensed from where it stands). The weight leaves a settle within the reading's
    noise as it is (a shift would only add that noise) and shifts one clearly off by its whole
    offset; without noise, by the exact offset."""
    residual = driven.residual
    if residual is None:
        return settled
    x, y = (driven.settled_leader(relative(settled))
            - beyond_noise(residual, driven.residual_variance))
    return dataclasses.replace(settled, r=math.hypot(x, y), theta=math.atan2(y, x))


def follower_tick(link: AgentLink, policy: Policy, settings: AgentSettings, tick: int,
                  limits: Limits | None = None, track: Track | None = None) -> TickOutcome:
    """Run one tick of the follower; a driving follower's ``limits`` (built once,
    :meth:`agents.drive.Limits.from_settings`) must be given, and its ``track`` (its last
    displacements, :class:`agents.drive.Track`) may be: the tick's settled sensing is added
    to it."""
    pre = link.sense(tick, look=tick < settings.init_ticks or looks_before_moving(policy))
    try:  # during the initial ticks the prediction is only scored, not followed
        proposal = policy.propose(pre)
        offset, prediction = proposal.offset, proposal.prediction
        followed, fallback = proposal.followed, proposal.fallback
    except NotReady:
        offset, prediction, followed, fallback = np.zeros(2), None, "", False
    driven = None
    if settings.drives:  # control steps to the estimate, then onto the rod end
        if limits is None:
            raise ValueError("a driving follower's limits must be given")
        goal = np.asarray(pre.rod) if tick < settings.init_ticks else offset
        driven = drive_tick(link.act, pre, goal, settings, limits, track)
        offset, moved = driven.travelled, driven.moved
    elif tick < settings.init_ticks:
        offset, moved = np.zeros(2), pre
    else:
        moved = link.act(Move(tick=tick, offset=(float(offset[0]), float(offset[1])))).sensing
    snapped = link.act(Snap(tick=tick, heading=None if driven is None else driven.told))
    lost, settled = not snapped.moved, snapped.sensing
    if driven is not None and not lost:
        settled = at_rod_end(settled, driven)
    target = None if lost or moved.rod is None else displacement(offset, pre, moved, settings)
    before = Before(pre=pre, moved=None if moved is pre else moved,
                    offset=(float(offset[0]), float(offset[1])))
    measurement = policy.learn(settled, target, before)
    if track is not None:
        track.record(settled)
    observation = Observation(tick=tick, estimator=policy.name, measurement=measurement,
                              prediction=prediction, lost=lost, followed=followed,
                              fallback=fallback)
    return TickOutcome(observation, settled, target, before)


def _replay_track(track: Track, entries: list[Entry]) -> None:
    """Rebuild a driving follower's track from its replay log (a missed tick breaks it, as it
    does in the loop of :func:`run_follower`)."""
    for entry in entries:
        if entry.skips or entry.settled is None:
            track.skip()
        if entry.settled is not None:
            track.record(entry.settled)


def _join(link: AgentLink, settings: AgentSettings, agent_id: int, policy: Policy, last: int,
          state_dir: str | Path | None, again: bool, track: Track | None
          ) -> tuple[StateLog | None, Policy, int, int, AgentSettings]:
    """Join the run, or join it ``again`` after :class:`agents.link.Rejoin`; return the state
    log (None without a state dir), the policy, the last tick it is through, the last tick
    the world has this agent through, and the settings with what the world resolved (a drive
    run's top speed). ``policy`` is through every tick up to ``last`` (-1:
    none): it learnt from them, skipped them or missed them.

    The world says where this agent stands (the last tick it has the agent through, and up to
    which tick the agent may act now). Log entries past that point describe ticks the world
    will run again (it restarted from its checkpoint, this agent died before reporting, or its
    session was cut while it stalled), so they are dropped and the policy is rebuilt from the
    rest (and a driving follower's ``track`` with it): the ticks are redone from the same state
    and the numbers are those of an uninterrupted run. Without a state dir the policy can go
    on only if the world has the agent through every tick the policy is through.
    """
    joined = link.join(settings.start_timeout)
    through = joined.through
    if joined.max_speed is not None:
        settings = dataclasses.replace(settings, max_speed=joined.max_speed)
    if not state_dir:
        if last > through:
            raise AgentAbort(f"follower {agent_id} cannot rejoin: the world redoes tick "
                             f"{through + 1}, which its estimator has learnt from, and it keeps "
                             "no state dir to roll back to (see --state-dir)")
        return None, policy, last, through, settings
    if again:  # the log holds what to learn from
        policy = make_policy(settings)
    state, entries = StateLog.open(state_dir, settings.run_id, agent_id, joined.start)
    kept = [e for e in entries if e.tick <= through]
    if len(kept) != len(entries):
        log.info("follower %d: rolling back to tick %d (the world redoes tick %d)",
                 agent_id, through, through + 1)
        state.rewrite(kept)
    last = kept[-1].tick if kept else -1
    if last < through:  # ticks it was not there for (realtime misses): bridged
        kept.append(Entry(tick=through, skips=through - last - 1, settled=None, target=None))
        state.append(kept[-1])
        last = through
    replay(policy, kept)
    if track is not None:
        track.reset()
        _replay_track(track, kept)
    if entries:
        log.info("follower %d: restored %d ticks of history from %s", agent_id, len(kept),
                 state.path)
    return state, policy, last, through, settings


def run_follower(session: zenoh.Session, settings: AgentSettings, agent_id: int,
                 state_dir: str | Path | None = None) -> None:
    """Lockstep/realtime follower loop; returns by raising RunFinished when the world is done.

    With ``state_dir`` every tick is appended to the follower's replay log
    (:mod:`agents.checkpoint`) before it is reported, and a restarted follower rebuilds its
    policy from it, so it continues with its whole history; ticks it missed meanwhile are
    bridged by the policy's own predictions (``Policy.skip``). A follower whose session to the
    world was cut (it stalled) joins again the same way. The log is deleted once the run is
    complete.
    """
    if not 1 <= agent_id <= settings.followers:
        raise ValueError(f"--id must be in 1..{settings.followers} for this run, got {agent_id}")
    policy = make_policy(settings)
    track = Track.for_follower(settings)
    link = AgentLink.for_agent(session, settings, agent_id)
    state, last, again = None, -1, False
    try:
        while True:
            state, policy, last, tick, settings = _join(link, settings, agent_id, policy, last,
                                                        state_dir, again, track)
            limits = Limits.from_settings(settings) if settings.drives else None
            timeout = settings.start_timeout
            try:
                while True:
                    tick = link.wait_step(tick, timeout)
                    timeout = settings.step_timeout
                    skips = tick - last - 1
                    if tick >= settings.ticks:
                        raise AgentAbort(f"tick {tick} is past this run's {settings.ticks} ticks")
                    for _ in range(skips):
                        policy.skip()
                        if track is not None:
                            track.skip()
                    last = tick - 1
                    try:
                        outcome = follower_tick(link, policy, settings, tick, limits, track)
                    except MarkedMissed:  # the tick passed without it: bridged, as replay does
                        policy.skip()
                        if track is not None:
                            track.skip()
                        entry = Entry(tick=tick, skips=skips, settled=None, target=None)
                        outcome = None
                    else:
                        target = outcome.target
                        entry = Entry(tick=tick, skips=skips, settled=outcome.settled,
                                      target=None if target is None else (float(target[0]),
                                                                          float(target[1])),
                                      before=outcome.before)
                    last = tick
                    if state is not None:
                        try:
                            state.append(entry)
                        except OSError as exc:  # a run must not die for its safety net
                            log.error("follower %d: cannot write its state file %s (%s); going "
                                      "on without", agent_id, state.path, exc.strerror)
                            state = None
                    if outcome is not None:
                        link.publish_obs(outcome.observation)
                        link.publish_rod(tick, settings.spacing, settings.side_sign)
            except Rejoin as cut:
                log.warning("follower %d: %s", agent_id, cut)
                again = True
    except RunFinished as end:
        if state is not None and end.complete:
            state.remove()
        raise
    finally:
        link.close()


def main(argv: list[str] | None = None) -> int:
    p = parser(program("agents.follower", "swarm-follower"),
               "Follower agent of a column-formation run.")
    p.add_argument("--id", type=int, help="follower id K (1 = behind the leader), which must "
                                          "match its brief's [default the brief's]")
    p.add_argument("--state-dir", help="where to keep this follower's state (replay log) "
                                        "('none' disables); removed at the end of a complete "
                                        "run if then empty [default <brief's folder>/state]")
    args = p.parse_args(argv)
    if args.id is not None and args.id < 1:
        p.error(f"argument --id: a follower's id is 1 or more, got {args.id}")
    state = args.state_dir or str(Path(args.config).resolve().parent / "state")
    state = None if state == "none" else state
    return run_cli(args, args.id, lambda session, brief: run_follower(
        session, brief.settings, brief.agent, state))


def console() -> None:
    """The installed script's entry: :func:`main`, then :func:`protocol.cli.exit_process`."""
    exit_process(main())


if __name__ == "__main__":
    console()
