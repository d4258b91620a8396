"""Mean required sensing range of every estimator, noise-free and noisy, with ratios.

``python bench/bench_estimator_table.py`` prints, for follower 1 (d = 3.57, 4 + 36 ticks):

1. noise-free, T_c = 1.28: stay, persist, the paper's EDMD-b, the classical baselines cv,
   kalman, arx, gp, the own-motion estimators gp-motion and gp-ratio, auto and auto-mix, with
   auto / EDMD-b and auto / best classical, and the same for auto-mix;
2. noise-free, per surface and comm period 0.32 ... 5.12: auto / best classical (and which
   baseline that is), auto / EDMD-b and auto's mean required range; the geometric mean of
   auto / best classical over the cells (target <= 0.75), the cells where auto is above the
   best classical baseline and, per comm period, the surfaces where it is at most 1/4 of
   EDMD-b; then the same for auto-mix;
3. noisy (range and bearing noise, paired levels: the issue's three and six held out),
   T_c = 1.28, mean over seeds 0-4: every estimator but stay, the sensing floor (the bound
   of design §6: the Kalman filter with every reading and the formation's true motion, of
   auto's runs; each table also checks it is below every estimator, each against the floor
   of its own runs), persist / auto and persist / auto-mix (target >= 1 everywhere; their
   geometric mean and minimum over the surfaces below; the geometric mean of persist / auto
   over the paper's surfaces, target >= 1.25 at 0.02/0.01), auto / best classical (and which)
   and auto / floor;
4. noisy at the long comm periods 2.56 and 5.12 (the issue's three levels): persist / auto and
   persist / auto-mix (not an issue target; where selection noise shows);
5. the middle level again with actuation noise on every move (sigma 0.01 and 0.05), which
   enters the follower's own recorded displacements.

Surfaces: the paper's three (used to choose auto's rules), and held out: ``gaussian-hill``,
``ripple`` and this benchmark's own ``crossed-waves`` and ``slanted-folds``
(``world/held_out.py``; never used to choose auto's rules, but the own-motion
candidates were screened on them too), ``dunes``, ``bowl-ridge``, ``egg-crate``,
``tilted-bump``, ``terraces`` and ``twin-hills``, defined later and among the cases auto-mix
and the leverage rule were weighed on, and ``twisted-saddle`` and ``long-waves``, defined after
the last change to auto and auto-mix and used for nothing else. Noise levels: the issue's
three and six held-out ones (the last defined with the last two surfaces).
``--random N --random-seed S`` runs every table on N surfaces drawn at random instead
(``world/random_waves.py``: seeds S ... S+N-1), a check on surfaces nobody chose;
``--surfaces A,B,...`` on yours (``--leader-start X,Y,VX,VY`` for every run, which a DEM
needs), and ``--noise-levels R/B,...`` at your noise levels.
Noise-free runs do not depend on the seed, so they run once. Runs use the in-memory layout,
whose numbers a test shows to be identical to the Zenoh layouts.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol.config import AUTO, CLASSICAL, FILTERS, OWN_MOTION, RunConfig  # noqa: E402
from swarm.cli import parse_leader_start  # noqa: E402
from swarm.local import run_local  # noqa: E402
from world import random_waves  # noqa: E402
from world.surfaces import make_surface  # noqa: E402

PAPER = ("elliptic", "hyperbolic", "wavy")
HELD_OUT = ("gaussian-hill", "ripple", "world.held_out:crossed_waves",
            "world.held_out:slanted_folds", "world.held_out:dunes",
            "world.held_out:bowl_ridge", "world.held_out:egg_crate",
            "world.held_out:tilted_bump", "world.held_out:terraces",
            "world.held_out:twin_hills", "world.held_out:twisted_saddle",
            "world.held_out:long_waves")
UNSEEN = HELD_OUT[-2:]  # defined after the last change to auto and auto-mix
ESTIMATORS = {"stay": {"estimator": "stay"}, "persist": {"estimator": "persist"},
              "edmd-b": {"estimator": "edmd", "dictionary": "b"},
              **{name: {"estimator": name} for name in CLASSICAL + FILTERS + OWN_MOTION + AUTO}}
# The model-based filters (ekf) model the declared sensor noise and enter auto only with it:
# the noise-free tables leave them out (and stay as they were).
NOISE_FREE = {name: options for name, options in ESTIMATORS.items() if name not in FILTERS}
TRACKERS = CLASSICAL + FILTERS  # what auto is compared with: "auto / best classical"
COMM_PERIODS = (0.32, 0.64, 1.28, 2.56, 5.12)
NOISE_LEVELS = ((0.005, 0.002), (0.02, 0.01), (0.05, 0.03))  # (range, bearing rad), paired
# the last one defined after the last change to auto and auto-mix
HELD_OUT_NOISE = ((0.01, 0.005), (0.035, 0.02), (0.0025, 0.001), (0.015, 0.04), (0.03, 0.005),
                  (0.012, 0.015))
ACTUATION = (0.01, 0.05)  # move noise sigma, with the middle sensor noise level
SEEDS = (0, 1, 2, 3, 4)


def short(surface: str) -> str:
    """A surface's name for a table: a DEM's file name, a Python surface's attribute."""
    if surface.startswith("dem:"):
        return Path(surface[4:]).name
    return surface.rsplit(":", 1)[-1].replace("_", "-")


class IncompleteRun(RuntimeError):
    """A run of the table ended early (e.g. the leader left a DEM): its mean would not be
    comparable with the others."""


def follower_means(surface: str, comm_period: float = 1.28, seeds=(0,), **options) -> dict:
    """Means over ``seeds`` of follower 1's summary figures (IncompleteRun if a run ends
    early): ``required`` (mean required sensing range) and ``floor`` (the sensing floor's)."""
    values: dict[str, list[float]] = {"required": [], "floor": []}
    for seed in seeds:
        summary, _ = run_local(RunConfig(surface=surface, comm_period=comm_period,
                                         seed=seed, **options))
        if not summary["complete"]:
            raise IncompleteRun(f"{surface} at T_c {comm_period}, seed {seed}: "
                                f"{summary['reason']}")
        follower = summary["followers"]["1"]
        values["required"].append(follower["mean_required_range"])
        values["floor"].append(follower["mean_floor_range"])
    return {key: sum(v) / len(v) for key, v in values.items()}


def required(surface: str, comm_period: float = 1.28, seeds=(0,), **options) -> float:
    """Mean over ``seeds`` of follower 1's mean required sensing range."""
    return follower_means(surface, comm_period, seeds, **options)["required"]


BY_PERIOD = ("edmd-b", *CLASSICAL, *AUTO)  # what the by-T_c tables read


def noise_free(surfaces, comm_periods, base: dict | None = None) -> dict:
    """Every estimator at T_c = 1.28 (the first table), those of ``BY_PERIOD`` elsewhere
    (``base``: options of every run, e.g. the leader start)."""
    return {(s, tc): {name: required(s, tc, **opts, **(base or {}))
                      for name, opts in NOISE_FREE.items() if tc == 1.28 or name in BY_PERIOD}
            for s in surfaces for tc in comm_periods}


def noisy(surfaces, levels, seeds, noise_move: float = 0.0, comm_period: float = 1.28,
          names=None, base: dict | None = None) -> dict:
    """Per (surface, level): each estimator's mean required range, ``floor``: the sensing
    floor of ``auto``'s runs (the minimum-mean-square estimator that knows the formation's true
    motion and has every reading the follower had; design §6), and ``below``: whether each
    estimator's floor (of its own runs) is below its mean required range."""
    names = names or [n for n in ESTIMATORS if n != "stay"]
    table = {}
    for s in surfaces:
        for level in levels:
            row: dict = {"below": True}
            for name in names:
                means = follower_means(s, comm_period, seeds, noise_range=level[0],
                                       noise_bearing=level[1], noise_move=noise_move,
                                       **ESTIMATORS[name], **(base or {}))
                row[name] = means["required"]
                row["below"] = row["below"] and means["floor"] < means["required"]
                if name == "auto":
                    row["floor"] = means["floor"]
            table[(s, level)] = row
    return table


def num(value: float) -> str:
    """Five decimals, or two significant digits below 1e-4."""
    return f"{value:>9.5f}" if value >= 1e-4 or value == 0 else f"{value:>9.1e}"


def best_classical(row: dict) -> tuple[str, float]:
    """The classical tracker of ``row`` with the lowest required range (the model-based
    filters among them where the row has them: the noisy tables)."""
    name = min((n for n in TRACKERS if n in row), key=lambda n: row[n])
    return name, row[name]


def add_surface_arguments(parser: argparse.ArgumentParser) -> None:
    """Instead of the fixed surfaces: ``--random N`` and ``--random-seed S`` (surfaces drawn at
    random), or ``--surfaces A,B,...`` (yours), with ``--leader-start`` for every run."""
    parser.add_argument("--random", type=int, default=0, metavar="N",
                        help="instead of the fixed surfaces, N surfaces drawn at random "
                             "(world/random_waves.py)")
    parser.add_argument("--random-seed", type=int, default=0, metavar="S",
                        help="the first random surface's seed (with --random; default 0)")
    parser.add_argument("--surfaces", metavar="A,B,...",
                        help="instead of the fixed surfaces, these (presets, package.module:name "
                             "or dem:PATH, as --surface of swarm run)")
    parser.add_argument("--leader-start", metavar="X,Y,VX,VY",
                        help="the leader's start in every run (a DEM has no default)")


def chosen_surfaces(parser: argparse.ArgumentParser, args: argparse.Namespace,
                    fixed: tuple[str, ...]) -> tuple[tuple[str, ...], dict]:
    """The surfaces ``args`` ask for (``fixed`` by default) and the options of every run
    (the leader start); a bad value ends with the parser's error."""
    if args.random < 0 or args.random_seed < 0:
        parser.error("--random and --random-seed must be >= 0")
    if args.random and args.surfaces:
        parser.error("--random and --surfaces exclude each other")
    base = {}
    if args.leader_start:
        try:
            base["leader_start"] = parse_leader_start(args.leader_start)
        except ValueError as exc:
            parser.error(str(exc))
    if args.surfaces:
        surfaces = tuple(s.strip() for s in args.surfaces.split(",") if s.strip())
        if not surfaces:
            parser.error("--surfaces names no surface")
        try:  # every surface loads and every run is valid before hours of runs start
            for surface in surfaces:
                RunConfig(surface=surface, **base)
                make_surface(surface)
        except (ValueError, OSError, ImportError, AttributeError) as exc:
            parser.error(f"--surfaces: {exc}")
        return surfaces, base
    if not args.random:
        return fixed, base
    print(f"random surfaces: seeds {args.random_seed}-{args.random_seed + args.random - 1}")
    return tuple(random_waves.name(args.random_seed + i) for i in range(args.random)), base


def parse_levels(parser: argparse.ArgumentParser, text: str,
                 flag: str = "--noise-levels") -> tuple[tuple[float, float], ...]:
    """``flag R/B,R/B,...`` -> ((range sigma, bearing sigma rad), ...), each pair within the
    run configuration's bounds (``parser`` refuses anything else, naming ``flag``)."""
    try:
        levels = tuple(tuple(float(x) for x in pair.split("/")) for pair in text.split(","))
        if not levels or any(len(level) != 2 for level in levels):
            raise ValueError("not RANGE/BEARING pairs")
        for r, b in levels:
            RunConfig(noise_range=r, noise_bearing=b)
    except ValueError as exc:
        parser.error(f"{flag} must be RANGE/BEARING sigma pairs, comma-separated, "
                     f"e.g. 0.02/0.01,0.05/0.03; got {text!r} ({exc})")
    return levels


def main() -> None:
    try:
        tables()
    except IncompleteRun as exc:
        sys.exit(f"error: a run ended early, {exc}; every table needs complete runs (for a "
                 "DEM, a --leader-start whose 40 ticks stay on it at T_c 5.12)")


def tables() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="T_c = 1.28 only, seeds 0-1")
    p.add_argument("--noise-free", action="store_true", help="the noise-free tables only")
    p.add_argument("--noise-levels", metavar="R/B,...",
                   help="instead of the nine fixed levels, these range/bearing sigma pairs "
                        "(the middle one of them for the actuation and long-period tables)")
    add_surface_arguments(p)
    args = p.parse_args()
    surfaces, base = chosen_surfaces(p, args, PAPER + HELD_OUT)
    given = parse_levels(p, args.noise_levels) if args.noise_levels else None
    periods = (1.28,) if args.quick else COMM_PERIODS
    seeds = SEEDS[:2] if args.quick else SEEDS
    table = noise_free(surfaces, periods, base)

    print("noise-free, follower 1, T_c = 1.28: mean required sensing range")
    names = list(NOISE_FREE)
    print(f"{'surface':<15}" + "".join(f"{n:>10}" for n in names)
          + "".join(f"{a + '/edmd-b':>16}{a + '/best cl.':>18}" for a in AUTO))
    for s in surfaces:
        row = table[(s, 1.28)]
        tag = ("" if s in PAPER else "  (unseen)" if s in UNSEEN
               else "  (random)" if args.random else "  (given)" if args.surfaces
               else "  (held out)")
        print(f"{short(s):<15}" + "".join(" " + num(row[n]) for n in names)
              + "".join(f"{row[a] / row['edmd-b']:>16.3f}{row[a] / best_classical(row)[1]:>18.3f}"
                        for a in AUTO) + tag)

    if not args.quick:
        for estimator in AUTO:
            print(f"\nnoise-free: {estimator} / best classical baseline (geometric mean over "
                  "the cells: target <= 0.75) "
                  f"[{estimator} / edmd-b] {estimator}'s mean required range, by T_c")
            print(f"{'surface':<15}" + "".join(f"{tc:>26}" for tc in periods))
            above, quarter, ratios = 0, dict.fromkeys(periods, 0), []
            for s in surfaces:
                cells = []
                for tc in periods:
                    row = table[(s, tc)]
                    name, best = best_classical(row)
                    value = row[estimator]
                    above += value > best
                    ratios.append(value / best)
                    quarter[tc] += value <= 0.25 * row["edmd-b"]
                    cells.append(f"{value / best:.2f} {name:<6}[{value / row['edmd-b']:.2f}] "
                                 f"{value:.1e}")
                print(f"{short(s):<15}" + "".join(f"{c:>26}" for c in cells))
            print(f"{estimator} / best classical baseline, geometric mean over the cells: "
                  f"{geometric_mean(ratios):.3f}")
            print(f"{estimator} above the best classical baseline in {above} of "
                  f"{len(surfaces) * len(periods)} cells; <= 1/4 of edmd-b on "
                  + ", ".join(f"{n} of {len(surfaces)} at {tc}" for tc, n in quarter.items()))
    if args.noise_free:
        return

    levels = given or NOISE_LEVELS + HELD_OUT_NOISE
    print_noisy(surfaces, noisy(surfaces, levels, seeds, base=base), levels, seeds)
    if not args.quick:
        print_long_periods(surfaces, seeds, given or NOISE_LEVELS, base)
    middle = given[len(given) // 2] if given else NOISE_LEVELS[1]
    for sigma in ACTUATION:
        print(f"\nwith actuation noise: move sigma {sigma} on top of the middle sensor level")
        print_noisy(surfaces, noisy(surfaces, [middle], seeds, noise_move=sigma, base=base),
                    [middle], seeds)


def print_noisy(surfaces, noisy_table: dict, levels, seeds) -> None:
    print(f"\nnoisy, T_c = 1.28, mean over seeds {seeds[0]}-{seeds[-1]}: "
          "mean required sensing range, the sensing floor, persist / auto and persist / "
          "auto-mix (target >= 1 everywhere; geometric mean over the paper's surfaces >= 1.25 "
          "at 0.02/0.01), auto / best classical (target <= 1 at 0.02/0.01) and auto / floor "
          "(how far from the limit)")
    names = [n for n in ESTIMATORS if n != "stay"]
    for level in levels:
        tag = ("" if level in NOISE_LEVELS else "  (held-out level)" if level in HELD_OUT_NOISE
               else "  (given level)")
        print(f"\nrange sigma {level[0]}, bearing sigma {level[1]} rad{tag}")
        print(f"{'surface':<15}" + "".join(f"{n:>10}" for n in names) + f"{'floor':>10}"
              + "".join(f"{'persist/' + a:>18}" for a in AUTO)
              + f"{'auto/best cl.':>15}{'auto/floor':>12}")
        gains = {a: [] for a in AUTO}
        paper = []
        for s in surfaces:
            row = noisy_table[(s, level)]
            for a in AUTO:
                gains[a].append(row["persist"] / row[a])
            if s in PAPER:
                paper.append(gains["auto"][-1])
            cl_name, cl_best = best_classical(row)
            print(f"{short(s):<15}" + "".join(" " + num(row[n]) for n in names)
                  + " " + num(row["floor"]) + "".join(f"{gains[a][-1]:>18.3f}" for a in AUTO)
                  + f"{row['auto'] / cl_best:>9.3f} {cl_name:<5}"
                  + f"{row['auto'] / row['floor']:>12.2f}")
        for label, reduce in (("geometric mean", geometric_mean), ("min", min)):
            print(f"{label:<15}" + " " * 10 * (len(names) + 1)
                  + "".join(f"{reduce(g):>18.3f}" for g in gains.values()))
        if len(paper) == len(PAPER):
            print(f"persist / auto, geometric mean over {', '.join(PAPER)}: "
                  f"{geometric_mean(paper):.3f}")
        versus = {n: geometric_mean(noisy_table[(s, level)]["auto"] / noisy_table[(s, level)][n]
                                    for s in surfaces) for n in TRACKERS}
        print("auto / each classical tracker, geometric mean over the surfaces (target <= 1): "
              + ", ".join(f"{n} {v:.3f}" for n, v in versus.items()))
        below = all(noisy_table[(s, level)]["below"] for s in surfaces)
        print(f"the floor is below every estimator in every row: {'yes' if below else 'NO'}")


def geometric_mean(values) -> float:
    values = list(values)
    return math.exp(math.fsum(math.log(v) for v in values) / len(values))


def print_long_periods(surfaces, seeds, levels=NOISE_LEVELS, base: dict | None = None) -> None:
    """persist / auto and persist / auto-mix at T_c 2.56 and 5.12 (the issue's noise levels
    unless others are given)."""
    print(f"\nnoisy at long comm periods, mean over seeds {seeds[0]}-{seeds[-1]}: "
          "persist / auto | persist / auto-mix (not an issue target)")
    cells = [(tc, level) for tc in (2.56, 5.12) for level in levels]
    tables = {tc: noisy(surfaces, levels, seeds, comm_period=tc, names=["persist", *AUTO],
                        base=base) for tc in (2.56, 5.12)}
    print(f"{'surface':<15}" + "".join(f"{f'{tc} {lv[0]}/{lv[1]}':>18}" for tc, lv in cells))
    below = {a: 0 for a in AUTO}
    for s in surfaces:
        out = []
        for tc, level in cells:
            row = tables[tc][(s, level)]
            ratios = [row["persist"] / row[a] for a in AUTO]
            for a, r in zip(AUTO, ratios):
                below[a] += r < 1
            out.append(f"{ratios[0]:.2f} | {ratios[1]:.2f}")
        print(f"{short(s):<15}" + "".join(f"{c:>18}" for c in out))
    print("below 1: " + ", ".join(f"{a} {n} of {len(surfaces) * len(cells)}"
                                  for a, n in below.items()))


if __name__ == "__main__":
    main()
