"""Where a driving column's heading errors come from (issue #30's open cells):
``python bench/bench_drive_heading.py [--surface wavy] [--followers 5] [--noise 0/0]``.

1. **The settled rods.** One in-process drive run (:mod:`swarm.local`, persist): at every
   tick, the angle (chart, rad) from the end tangent of agent ``k−1``'s actual rod (the world's
   geometry, from its settled pose) to the rod follower ``k`` settled with. Its mean and rms
   per follower is the heading error the follower passes down the column (``d ×`` it at the
   next rod end); with no noise it is the goal heading's own error (the fit's lag), since the
   robot executes its heading exactly.
   Split in two: the **goal heading** the controller steered for at its last step (its
   estimate of where to settle, :func:`agents.drive.goal_heading` through
   :class:`agents.drive.Track`) against the heading of the ideal rod end (design §3,
   :func:`world.geometry.heading_at_rod_end`), and the **execution**: the heading it settled
   with against that goal heading (its heading filter, the turn limit, the actuation noise).
   Median, rms and worst of each; the rms of a few ticks far off can exceed the median many
   times.
2. **Rules on the ideal column** (no robot): along the ideal formation of the same surface,
   the error of two estimates of a rod's end tangent ``u`` from what a follower at the rod end
   could know — the chord alone (``χ``, the direction from the rod's start to its end) and the
   circular-arc rule ``2χ − n`` (``n`` the rod's start direction). A goal heading built on a
   rule inherits its error at every follower, noise-free.
3. **Local against global** (the same case driving and teleporting): each follower's mean
   distance from the rod end of its predecessor's *actual* pose (local: how well it keeps
   its own rod end) and from the ideal formation (global: issue #30's formation error). A
   driving follower's heading error turns its rod and moves every rod end behind it, so the
   global error grows down a driving column faster than the local one (docs/drive.md,
   *Stop 47*). The global error split in two, rms over the ticks: **along the travel** (the
   ideal heading's direction, across the ideal rod) and **along the rod** — a heading error
   turns a rod and so moves every rod end behind it along the travel, while a follower's
   landing errors move it both ways (*Stop 49*).

Figures depend on nothing but the configuration; nothing here is asserted.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents import drive, follower  # noqa: E402
from protocol.config import RunConfig  # noqa: E402
from swarm.local import run_local  # noqa: E402
from world import geometry  # noqa: E402
from world.surfaces import make_surface, surface_leader_start  # noqa: E402


def _angle(v: np.ndarray) -> float:
    return math.atan2(v[1], v[0])


def _wrap(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


@contextlib.contextmanager
def _noting_goal_headings(noted: dict[tuple[int, int], float]):
    """Meanwhile, note in ``noted[(agent, tick)]`` the goal heading of each driving tick's last
    control step (the controller's own functions wrapped from outside, for this figure only)."""
    last: list[float] = []
    plain_command, plain_tick = drive.step_command, follower.drive_tick

    def command(position, heading, slope, goal, goal_heading, *args, **kwargs):
        last[:] = [goal_heading]
        return plain_command(position, heading, slope, goal, goal_heading, *args, **kwargs)

    def tick(act, pre, *args, **kwargs):
        driven = plain_tick(act, pre, *args, **kwargs)
        noted[act.__self__.agent, pre.tick] = last[0]  # act: a swarm.local.LocalLink's
        return driven

    drive.step_command, follower.drive_tick = command, tick
    try:
        yield
    finally:
        drive.step_command, follower.drive_tick = plain_command, plain_tick


def _poses(rows: list[dict]) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]:
    """Each agent's settled pose per tick, ``(tick, agent) -> (position, heading)``."""
    return {(r["tick"], r["agent"]): (np.array([r["pos_x"], r["pos_y"]]),
                                      np.array([r["heading_x"], r["heading_y"]]))
            for r in rows}


def noted_drive(config: RunConfig) -> tuple[list[dict], dict[tuple[int, int], float]]:
    """The driving run's ticks and each driving tick's last goal heading
    (:func:`_noting_goal_headings`)."""
    noted: dict[tuple[int, int], float] = {}
    with _noting_goal_headings(noted):
        _, rows = run_local(config)
    return rows, noted


def settled_rod_errors(config: RunConfig, rows: list[dict], noted: dict[tuple[int, int], float]
                       ) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray],
                                  dict[int, np.ndarray]]:
    """Per follower, one per tick (initial ticks included), from the driving run's ``rows``
    and goal headings ``noted`` (:func:`noted_drive`): the chart angle from its
    predecessor's actual rod end tangent to its own settled rod; the goal heading's error
    (against the heading at the actual rod end); the execution's (settled against goal)."""
    surface = make_surface(config.surface)
    pose = _poses(rows)
    ticks = sorted({t for t, _ in pose})
    errors: dict[int, np.ndarray] = {}
    goals: dict[int, np.ndarray] = {}
    executions: dict[int, np.ndarray] = {}
    for k in range(1, config.followers + 1):
        series, goal, execution = [], [], []
        for j in ticks:
            (p0, h0), (p1, h1) = pose[j, k - 1], pose[j, k]
            end, u = geometry.rod_end(surface, p0, h0, config.spacing, config.side_sign)
            n = geometry.rod_normal(surface, p1, h1, config.side_sign)
            series.append(_wrap(_angle(n) - _angle(u)))
            ideal = _angle(geometry.heading_at_rod_end(surface, end, u, config.side_sign))
            goal.append(_wrap(noted[k, j] - ideal))
            execution.append(_wrap(_angle(h1) - noted[k, j]))
        errors[k], goals[k], executions[k] = map(np.array, (series, goal, execution))
    return errors, goals, executions


def rule_errors(name: str, followers: int, ticks: int, spacing: float,
                comm_period: float) -> dict[str, np.ndarray]:
    """On the ideal column: the errors of the chord and of the circular-arc rule as estimates
    of the rod end tangent, over every rod and every other tick."""
    surface = make_surface(name)
    start = np.asarray(surface_leader_start(surface), dtype=float)
    chord, arc = [], []
    for j in range(0, ticks, 2):
        try:
            p, v = geometry.integrate_geodesic(surface, start[:2], start[2:], j * comm_period)
            positions, headings = geometry.column(surface, p, v, followers, spacing)
        except geometry.SurfaceDomainError:
            break
        for k in range(followers):
            n = geometry.rod_normal(surface, positions[k], headings[k])
            end, u = geometry.rod_end(surface, positions[k], headings[k], spacing)
            chi = _angle(end - positions[k])
            chord.append(_wrap(chi - _angle(u)))
            arc.append(_wrap(2.0 * chi - _angle(n) - _angle(u)))
    return {"chord": np.array(chord), "arc rule": np.array(arc)}


def local_and_global(config: RunConfig, rows: list[dict]
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per follower of the run whose ticks are ``rows``, the mean over the ticks of its
    distance from the rod end of its predecessor's actual pose, and of its formation error
    (the ideal formation's distance; ticks without one left out); and the rms over the ticks
    of its offset from its ideal position along the travel and along the rod (the offset's
    components across and along the chord from its ideal predecessor to it)."""
    surface = make_surface(config.surface)
    pose = _poses(rows)
    ticks = sorted({t for t, _ in pose})
    ideal = geometry.ideal_formation(surface, config.leader_start, config.followers,
                                     config.spacing, config.comm_period, max(ticks) + 1,
                                     config.side_sign)
    formation_errors = {(r["tick"], r["agent"]): r["formation_error"] for r in rows
                        if r["agent"] > 0}  # the leader's row has positions only
    local, formation, travel, rod = [], [], [], []
    for k in range(1, config.followers + 1):
        near, far, parts = [], [], []
        for j in ticks:
            end, _ = geometry.rod_end(surface, *pose[j, k - 1], config.spacing,
                                      config.side_sign)
            near.append(float(np.hypot(*(pose[j, k][0] - end))))
            if formation_errors[j, k] is not None:
                far.append(formation_errors[j, k])
                chord = ideal[k, j, :2] - ideal[k - 1, j, :2]
                chord = chord / np.hypot(*chord)
                offset = pose[j, k][0] - ideal[k, j, :2]
                parts.append((chord[0] * offset[1] - chord[1] * offset[0], chord @ offset))
        local.append(np.mean(near))
        formation.append(np.mean(far))
        travel_rod = np.sqrt(np.mean(np.square(parts), axis=0))
        travel.append(travel_rod[0])
        rod.append(travel_rod[1])
    return np.array(local), np.array(formation), np.array(travel), np.array(rod)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--surface", default="wavy")
    p.add_argument("--followers", type=int, default=5)
    p.add_argument("--noise", default="0/0", help="σ_r/σ_θ")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--ticks", type=int, default=150)
    args = p.parse_args()
    sigma_r, sigma_t = (float(x) for x in args.noise.split("/"))
    config = RunConfig(run_id="heading", surface=args.surface, followers=args.followers,
                       ticks=args.ticks, seed=args.seed, noise_range=sigma_r,
                       noise_bearing=sigma_t, estimator="persist", motion="drive")
    print(f"{args.surface}, {args.followers} followers, σ {args.noise}, seed {args.seed}: "
          "settled rod vs its predecessor's end tangent (rad), estimated ticks")
    print("| follower | mean | rms | worst | goal heading: median / rms / worst | "
          "execution: median / rms / worst |\n|---|---|---|---|---|---|")
    rows, noted = noted_drive(config)
    errors, goals, executions = settled_rod_errors(config, rows, noted)

    def spread(e: np.ndarray) -> str:
        return (f"{np.median(np.abs(e)):.4f} / {math.sqrt((e * e).mean()):.4f} / "
                f"{np.abs(e).max():.4f}")

    for k, e in errors.items():
        e, goal, execution = (x[config.init_ticks:] for x in (e, goals[k], executions[k]))
        print(f"| {k} | {e.mean():+.4f} | {math.sqrt((e * e).mean()):.4f} | "
              f"{np.abs(e).max():.4f} | {spread(goal)} | {spread(execution)} |")
    print(f"\nrules on the ideal {args.surface} column (rad)")
    print("| rule | mean abs | worst |\n|---|---|---|")
    for rule, e in rule_errors(args.surface, args.followers, args.ticks, config.spacing,
                               config.comm_period).items():
        print(f"| {rule} | {np.abs(e).mean():.4f} | {np.abs(e).max():.4f} |")
    print(f"\nlocal against global, mean over the ticks (m), followers 1-{args.followers}")
    print("| motion | local | global | global along the travel (rms) | along the rod (rms) |"
          "\n|---|---|---|---|---|")
    teleport = dataclasses.replace(config, motion="teleport")
    for motion, ticks in (("drive", rows), ("teleport", run_local(teleport)[1])):
        print(f"| {motion} | " + " | ".join(" ".join(f"{x:.3f}" for x in part)
                                            for part in local_and_global(config, ticks)) + " |")


if __name__ == "__main__":
    main()
