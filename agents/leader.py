"""The leader: drives its geodesic tick by tick and holds its rod out
(``python -m agents.leader``)."""
from __future__ import annotations

import logging

import zenoh

from agents.cli import parser, run_cli
from agents.link import AgentLink, MarkedMissed, Rejoin
from protocol.cli import exit_process, program
from protocol.config import AgentSettings
from protocol.messages import Drive

log = logging.getLogger(__name__)


def run_leader(session: zenoh.Session, settings: AgentSettings) -> None:
    """Lockstep leader loop; returns by raising RunFinished when the world is done."""
    link = AgentLink.for_agent(session, settings, 0)
    try:
        while True:
            # a restarted leader, or one whose session was cut (it stalled), redoes the tick in
            # progress if the world has not recorded its rod (the world rolled its drive
            # back), else waits for the next tick
            tick = link.join(settings.start_timeout).through
            timeout = settings.start_timeout
            try:
                while True:
                    tick = link.wait_step(tick, timeout)
                    timeout = settings.step_timeout
                    t = tick * settings.comm_period
                    try:
                        link.act(Drive(tick=tick, t=t))
                    except MarkedMissed:  # realtime: too late for this tick; the pose is kept
                        continue
                    link.publish_rod(tick, settings.spacing, settings.side_sign)
            except Rejoin as cut:
                log.warning("leader: %s", cut)
    finally:
        link.close()


def main(argv: list[str] | None = None) -> int:
    args = parser(program("agents.leader", "swarm-leader"),
                  "Leader agent of a column-formation run.").parse_args(argv)
    return run_cli(args, 0, lambda session, brief: run_leader(session, brief.settings))


def console() -> None:
    """The installed script's entry: :func:`main`, then :func:`protocol.cli.exit_process`."""
    exit_process(main())


if __name__ == "__main__":
    console()
