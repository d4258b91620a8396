"""What a driving follower's heading costs the column, and what sharing headings would give:
``python bench/bench_heading_share.py [--cells wavy:5:0.05:0.03] [--seeds 3]``.

Since stop 51 each driving follower weighs the heading its leader tells
(``agents.drive.Track.fuse``, the ``versus`` rule below without the leader's heading): that is
``today``; ``unshared`` leaves it out, as before stop 51 (docs/drive.md quotes those figures
as "today"). Two probes, each run in memory (:mod:`swarm.local`) in a fresh process per
run, ``persist``, 150 ticks, against the same runs unpatched ("today") and teleporting
(issue #30's bound, 2 × teleport's last-follower mean + 0.05 m). Neither is a feature: both
patch the code they probe from here, for measuring only.

- ``exact:K+…`` — the world settles followers ``K+…`` with the exact heading of design §3 at
  their true rod end (teleport's), the others driving as they do: how much each follower's
  heading is worth to the column behind it.
- ``share:S`` / ``share:judged`` (``…/noleader`` without the leader's heading) — each driving
  follower fuses its predecessor's settled heading estimate (the predecessor's heading filter,
  with the filter's declared variance) into the heading its track settles with, as one more
  reading of it. ``S`` (mrad) is a fixed spread added to the reading's variance for what the
  estimate does not say (the rod's transport in the chart, the predecessor's own error against
  the formation); ``declared`` adds the predecessor's settled goal's declared variance
  instead; ``versus`` judges the told heading as the track judges its own tangents, against
  the follower's lag-free tangent through each past rod end (so its variance holds the rod's
  transport, the predecessor's error and what the two share), and weighs it against the
  track's own judged error; ``judged`` weighs both ends by the mean squared error their tracks
  judged of their path tangents against the lag-free one (``Track.errors``), from the third
  judged tick on. The leader's heading, where shared, is its exact one (variance 0): the world
  drives it exactly.

Per cell it prints the last follower's mean formation error (mean over the seeds), the worst
tick of any follower over every seed and every follower's mean (m). docs/drive.md (*Stop 51*)
quotes ``--seeds 3`` on the cells named there. Figures depend on nothing but the cells and
seeds; nothing here is asserted.
"""
from __future__ import annotations

import argparse
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol.config import RunConfig, estimator_options  # noqa: E402

TICKS = 150
PRESETS = ("elliptic", "hyperbolic", "wavy", "gaussian-hill", "ripple")
VARIANTS = ("today", "unshared", "exact:1", "exact:1+2", "exact:1+2+3+4", "share:20", "share:30",
            "share:20/noleader", "share:judged/noleader")


def _exact(followers: set[int]) -> None:
    """The world settles ``followers`` with the exact §3 heading at their true rod end."""
    from world import geometry, sim

    plain = sim.WorldSim._settle_driven

    def settle(self, agent: int, tick: int) -> bool:
        if agent in followers:
            end, tangent = self._leader_rod(agent, tick)
            self.agents[agent].heading = geometry.heading_at_rod_end(self.surface, end, tangent,
                                                                     self.side)
        return plain(self, agent, tick)

    sim.WorldSim._settle_driven = settle


def _share(spread: float | str | None, leader: bool) -> None:
    """Each driving follower fuses its predecessor's settled heading estimate into
    ``Track.fuse``'s result: a reading with the predecessor filter's declared variance plus
    ``spread``² (rad); with ``spread`` None, both ends weighed by their tracks' judged mean
    squared path-tangent error; with ``"declared"``, the predecessor's settled goal's declared
    variance added instead of a spread."""
    from agents import drive, follower
    from world import sim

    worlds: list = []
    plain_init = sim.WorldSim.__init__

    def init(self, *args, **kwargs):
        plain_init(self, *args, **kwargs)
        worlds.append(self)

    sim.WorldSim.__init__ = init
    headings: dict[tuple[int, int], tuple[float, float]] = {}  # (agent, tick): its estimate
    judged: dict[int, float] = {}  # agent: its track's judged mean squared tangent error
    declared: dict[tuple[int, int], float] = {}  # (agent, tick): its settled goal's variance
    owner: dict[int, int] = {}  # id(track): agent
    now: dict[str, object] = {}  # the driving agent and tick, and its last heading filter

    class Filter(drive.HeadingFilter):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            now["filter"] = self

    drive.HeadingFilter = Filter
    plain_tick = follower.drive_tick

    def drive_tick(act, pre, goal, settings, limits, track=None):
        agent = act.__self__.agent
        owner[id(track)], now["at"] = agent, (agent, pre.tick)
        if agent == 1 and leader:
            h = worlds[-1].agents[0].heading
            headings[(0, pre.tick)] = (math.atan2(h[1], h[0]), 0.0)
        driven = plain_tick(act, pre, goal, settings, limits, track)
        headings[(agent, pre.tick)] = (now["filter"].heading, now["filter"].variance)
        return driven

    follower.drive_tick = drive_tick
    plain_fuse, plain_record = drive.Track.fuse, drive.Track.record

    def fuse(self, path, variance, step, chord, told=None):  # the built rule replaced
        own = plain_fuse(self, path, variance, step, chord)
        agent = owner.get(id(self))
        if agent is None or now.get("at", (None,))[0] != agent or self.chord_variance == 0:
            return own
        shared = headings.get((agent - 1, now["at"][1]))
        if shared is None:
            return own
        if spread == "versus":  # both judged against the follower's own lag-free tangents
            theirs, mine = versus.get(agent), judged.get(agent)
            if theirs is None or mine is None:
                return own
            reading, weight_own = theirs[0] / theirs[1], mine
        elif spread == "declared":  # the predecessor's settled goal's declared variance
            theirs = 0.0 if agent == 1 else declared.get((agent - 1, now["at"][1]))
            if theirs is None:
                return own
            reading, weight_own = shared[1] + theirs, own.variance
        elif spread is None:
            theirs = 0.0 if agent == 1 else judged.get(agent - 1)
            mine = judged.get(agent)
            if theirs is None or mine is None:
                return own
            reading, weight_own = shared[1] + theirs, mine
        else:
            reading, weight_own = shared[1] + spread * spread, own.variance
        gain = weight_own / (weight_own + reading) if weight_own + reading > 0 else 0.0
        heading = drive.wrap(own.heading + gain * drive.wrap(shared[0] - own.heading))
        return drive.Settled(heading, (1.0 - gain) * own.variance, own.chord)

    plain_judge = drive.Track._judge

    def judge(self, step, previous, both):
        agent = owner.get(id(self))
        told = None if agent is None else headings.get((agent - 1, settled_tick[0] - 1))
        if told is not None and previous:
            middle = drive.middle_tangent(previous[-1], step)
            off = drive.axial(told[0] - math.atan2(middle[1], middle[0]))
            total = versus.get(agent, (0.0, 0))
            versus[agent] = (total[0] + off * off, total[1] + 1)
        return plain_judge(self, step, previous, both)

    drive.Track._judge = judge
    settled_tick = [0]
    versus: dict[int, tuple[float, int]] = {}  # agent: the told headings' squared errors, count

    def record(self, settled):
        settled_tick[0] = settled.tick
        plain_record(self, settled)
        agent = owner.get(id(self))
        if agent is not None and self.settled is not None:
            declared[(agent, settled.tick)] = self.settled.variance
        if agent is not None and self.judged >= 3:
            judged[agent] = float(min(self.errors)) / self.judged

    drive.Track.fuse, drive.Track.record = fuse, record


def _unshared() -> None:
    """Each driving follower leaves out the heading its leader tells (before stop 51)."""
    from agents import drive

    plain = drive.Track.fuse

    def fuse(self, path, variance, step, chord, told=None):
        return plain(self, path, variance, step, chord)

    drive.Track.fuse = fuse


def install(variant: str) -> None:
    """Patch this process for ``variant`` (module docstring). A ``share:`` rule replaces the
    built one (it fuses into ``Track.fuse``'s result without the told heading)."""
    kind, _, rest = variant.partition(":")
    if variant == "unshared":
        _unshared()
    elif kind == "exact":
        _exact({int(k) for k in rest.split("+")})
    elif kind == "share":
        value, _, leader = rest.partition("/")
        _share(value if value in ("declared", "versus") else None if value == "judged"
               else float(value) / 1000.0, leader != "noleader")
    elif variant != "today":
        raise ValueError(f"unknown variant {variant!r}")


def _run(job: tuple) -> tuple[tuple, list[float], float]:
    """One run: its job, each follower's mean formation error and the worst tick."""
    variant, surface, followers, sigma_r, sigma_t, seed = job
    from swarm.local import run_local

    motion = {} if variant == "teleport" else {"motion": "drive"}
    if variant != "teleport":
        install(variant)
    name = surface if surface in PRESETS or ":" in surface else f"world.held_out:{surface}"
    config = RunConfig(run_id="share", surface=name, followers=followers, ticks=TICKS,
                       seed=seed, noise_range=sigma_r, noise_bearing=sigma_t,
                       **estimator_options("persist"), **motion)
    summary, _ = run_local(config)
    stats = [summary["followers"][k] for k in sorted(summary["followers"], key=int)]
    return (job, [s["mean_formation_error"] for s in stats],
            max(s["worst_formation_error"] for s in stats))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cells", default="wavy:5:0.05:0.03,egg_crate:5:0.05:0.03",
                   help="comma-separated SURFACE:FOLLOWERS:SIGMA_R:SIGMA_THETA (a held-out "
                        "surface by its bare name) [default: %(default)s]")
    p.add_argument("--variants", default=",".join(VARIANTS))
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--workers", type=int, default=2)
    args = p.parse_args()
    cells = []
    for cell in args.cells.split(","):
        surface, followers, sigma_r, sigma_t = cell.rsplit(":", 3)
        cells.append((surface, int(followers), float(sigma_r), float(sigma_t)))
    variants = ["teleport", *args.variants.split(",")]
    jobs = [(v, *cell, seed) for cell in cells for v in variants for seed in range(args.seeds)]
    # a fresh process per run: a probe patches the process it runs in
    with ProcessPoolExecutor(args.workers, max_tasks_per_child=1) as pool:
        results = {job: (means, worst) for job, means, worst in pool.map(_run, jobs)}
    for cell in cells:
        runs = {v: [results[(v, *cell, s)] for s in range(args.seeds)] for v in variants}
        teleport = sum(r[0][-1] for r in runs["teleport"]) / args.seeds
        surface, followers, sigma_r, sigma_t = cell
        print(f"\n{surface}, {followers} followers, σ {sigma_r:g}/{sigma_t:g}, persist, "
              f"seeds 0–{args.seeds - 1}: bound {2 * teleport + 0.05:.3f} m")
        print("| variant | last follower's mean | worst tick | means, follower 1 → last |")
        print("| --- | --- | --- | --- |")
        for v in variants:
            means = [sum(r[0][k] for r in runs[v]) / args.seeds for k in range(followers)]
            worst = max(r[1] for r in runs[v])
            print(f"| {v} | {means[-1]:.3f} | {worst:.3f} | "
                  f"{', '.join(f'{m:.3f}' for m in means)} |")


if __name__ == "__main__":
    main()
