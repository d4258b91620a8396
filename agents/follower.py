"""A follower: estimates its leader's rod end, moves there, snaps on it (``python -m agents.follower``).

One tick (SPEC §4): sense the leader (``pre``) and ask the policy for its estimate; from tick
``init_ticks`` on, move there and sense again (``moved``); snap onto the rod end if it is in range (else
count a lost tick); sense once more (``settled``) and record the measurement; publish the
observation and the rod.
"""
from __future__ import annotations

import logging
import sys
from pathlib import Path

import numpy as np
import zenoh

from agents import checkpoint
from agents.cli import parser, run_cli
from agents.link import QUERY_TIMEOUT_S, AgentLink, RunFinished, TickMissed
from agents.policies import NotReady, Policy, make_policy
from protocol.config import AgentSettings
from protocol.messages import ActRequest, Observation

log = logging.getLogger(__name__)


def follower_tick(link: AgentLink, policy: Policy, settings: AgentSettings, tick: int) -> Observation:
    """Run one tick of the follower; returns the observation it publishes."""
    pre = link.sense(tick, "pre")
    try:  # during the initial ticks the prediction is only scored, not followed
        proposal = policy.propose(pre)
        offset, prediction = proposal.offset, proposal.prediction
        followed, fallback = proposal.followed, proposal.fallback
    except NotReady:
        offset, prediction, followed, fallback = np.zeros(2), None, "", False
    if tick < settings.init_ticks:
        offset, rod = np.zeros(2), pre.rod
    else:
        link.act(ActRequest(tick=tick, action="move", offset=(float(offset[0]), float(offset[1]))))
        rod = link.sense(tick, "moved").rod
    lost = not link.act(ActRequest(tick=tick, action="snap")).moved
    settled = link.sense(tick, "settled")
    target = None if lost or rod is None else offset + np.asarray(rod)
    measurement = policy.record(settled, target)
    return Observation(tick=tick, estimator=policy.name, measurement=measurement,
                       prediction=prediction, lost=lost, followed=followed, fallback=fallback)


def run_follower(session: zenoh.Session, settings: AgentSettings, agent_id: int,
                 state_dir: str | Path | None = None) -> None:
    """Lockstep/realtime follower loop; returns by raising RunFinished when the world is done.

    With ``state_dir`` the policy is checkpointed after every tick and restored at start, so
    a follower killed and restarted with the same id continues with its whole history; ticks
    it missed meanwhile are bridged by the policy's own predictions (``Policy.skip``).
    """
    if not 1 <= agent_id <= settings.followers:
        raise ValueError(f"--id must be in 1..{settings.followers} for this run, got {agent_id}")
    saved = checkpoint.load(state_dir, settings.run_id, agent_id) if state_dir else None
    policy = saved.policy if saved else make_policy(settings)
    last = saved.tick if saved else -1
    link = AgentLink(session, settings.run_id, agent_id, agent_id - 1,
                     query_timeout=max(settings.agent_timeout, QUERY_TIMEOUT_S))
    try:
        tick, timeout = last, settings.start_timeout
        while True:
            tick = link.wait_step(tick, timeout)
            timeout = settings.step_timeout
            for _ in range(tick - last - 1):
                policy.skip()
            last = tick
            try:
                obs = follower_tick(link, policy, settings, tick)
            except TickMissed:
                continue
            if state_dir:
                try:
                    checkpoint.save(state_dir, checkpoint.Checkpoint(settings.run_id, agent_id,
                                                                     tick, policy))
                except OSError as exc:  # a run must not die for its safety net
                    log.error("follower %d: cannot write its checkpoint (%s); going on without",
                              agent_id, exc)
                    state_dir = None
            link.publish_obs(obs)
            link.publish_rod(tick, settings.spacing, settings.side)
    except RunFinished:
        if state_dir:
            checkpoint.remove(state_dir, agent_id)
        raise
    finally:
        link.close()


def main(argv: list[str] | None = None) -> int:
    p = parser("Follower agent of a column-formation run.")
    p.add_argument("--id", type=int, required=True, help="follower id K (1 = behind the leader)")
    p.add_argument("--state-dir", help="where to keep this follower's checkpoint "
                                        "(default: <config dir>/state; 'none' disables)")
    args = p.parse_args(argv)
    state = args.state_dir or str(Path(args.config).resolve().parent / "state")
    state = None if state == "none" else state
    return run_cli(args, lambda session, settings: run_follower(session, settings, args.id, state))


if __name__ == "__main__":
    sys.exit(main())
