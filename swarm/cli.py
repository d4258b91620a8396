"""``python -m swarm``: run one case (``run``), and more subcommands as they come (SPEC §9)."""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from protocol.config import RunConfig, config_from_dict, load_config

# CLI flag -> (config field, argparse kwargs). Flags left unset do not override the file.
RUN_FLAGS: dict[str, tuple[str, dict]] = {
    "--surface": ("surface", {"help": "preset (elliptic, hyperbolic, wavy, plane, gaussian-hill, "
                                      "ripple, hemisphere), dem:PATH (a DEM raster) or "
                                      "package.module:name"}),
    "--followers": ("followers", {"type": int}),
    "--comm-period": ("comm_period", {"type": float, "help": "T_c, time between messages"}),
    "--spacing": ("spacing", {"type": float, "help": "rod length d (Riemannian)"}),
    "--ticks": ("ticks", {"type": int}),
    "--init-ticks": ("init_ticks", {"type": int}),
    "--estimator": ("estimator", {"choices": ("edmd", "stay", "persist", "auto")}),
    "--dictionary": ("dictionary", {"choices": tuple("abcdefg")}),
    "--velocity": ("velocity", {"choices": ("oracle", "lagged", "estimated")}),
    "--online": ("online", {"action": "store_const", "const": True}),
    "--delays": ("delays", {"type": int}),
    "--affine": ("affine", {"action": "store_const", "const": True}),
    "--forget": ("forget", {"type": float}),
    "--window": ("window", {"type": int, "help": "sliding window of pairs (0 = all)"}),
    "--ridge": ("ridge", {"type": float}),
    "--gps": ("gps", {"action": "store_const", "const": True}),
    "--noise-range": ("noise_range", {"type": float}),
    "--noise-bearing": ("noise_bearing", {"type": float}),
    "--noise-velocity": ("noise_velocity", {"type": float}),
    "--noise-move": ("noise_move", {"type": float}),
    "--side": ("side", {"choices": ("left", "right")}),
    "--leader-start": ("leader_start", {"metavar": "X,Y,VX,VY"}),
    "--seed": ("seed", {"type": int}),
    "--sensing-range": ("sensing_range", {"type": float, "help": "R_s (inf = unlimited)"}),
    "--mode": ("mode", {"choices": ("lockstep", "realtime")}),
    "--time-scale": ("time_scale", {"type": float}),
    "--agent-timeout": ("agent_timeout", {"type": float}),
    "--run-id": ("run_id", {}),
}


def add_run_flags(p: argparse.ArgumentParser) -> None:
    for flag, (dest, kwargs) in RUN_FLAGS.items():
        p.add_argument(flag, dest=dest, default=None, **kwargs)
    p.add_argument("--smoothing", type=float, default=None,
                   help="DEM surfaces: scipy's spline smoothing s (0 = interpolate; TOML: "
                        "surface_params.smoothing)")
    p.add_argument("--config", help="TOML file with any of the options; flags override it")


def config_from_args(args: argparse.Namespace) -> RunConfig:
    """Defaults, then the ``--config`` file, then the flags given (ValueError on bad input)."""
    from swarm.launch import new_run_id

    base = load_config(args.config) if args.config else RunConfig(run_id=new_run_id())
    data = base.to_dict()
    for dest, _ in RUN_FLAGS.values():
        value = getattr(args, dest)
        if value is not None:
            data[dest] = value
    if isinstance(data.get("leader_start"), str):
        data["leader_start"] = parse_leader_start(data["leader_start"])
    if args.smoothing is not None:
        data["surface_params"] = {**data.get("surface_params", {}), "smoothing": args.smoothing}
    if args.config and args.run_id is None and "run_id" not in _file_keys(args.config):
        data["run_id"] = new_run_id()
    return config_from_dict(data)


def parse_leader_start(text: str) -> tuple[float, ...]:
    """``"X,Y,VX,VY"`` -> four floats (ValueError naming --leader-start otherwise)."""
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 4:
        raise ValueError(f"--leader-start must be X,Y,VX,VY numbers, got {text!r}")
    return values


def _file_keys(path: str) -> set[str]:
    import tomllib

    with open(path, "rb") as fh:
        return set(tomllib.load(fh))


def format_summary(summary: dict) -> str:
    """The per-follower table printed at the end of a run."""
    head = (f"{'follower':>8}  {'required (' + summary['estimator'] + ')':>20}  {'rmse':>8}  "
            f"{'stay':>8}  {'persist':>8}  {'lost':>4}  {'missed':>6}")
    lines = [head, "-" * len(head)]
    for k, s in summary["followers"].items():
        lines.append(f"{k:>8}  {_num(s['mean_required_range']):>20}  {_num(s['rmse']):>8}  "
                     f"{_num(s['mean_stay_range']):>8}  {_num(s['mean_persist_range']):>8}  "
                     f"{s['lost_ticks']:>4}  {s['missed_ticks']:>6}")
    state = "complete" if summary["complete"] else f"INCOMPLETE: {summary['reason']}"
    lines.append(f"surface {summary['surface']}, comm period {summary['comm_period']}, "
                 f"{summary['ticks_completed']} ticks, {summary['wall_time']:.1f} s wall, {state}")
    return "\n".join(lines)


def _num(x: float | None) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.4f}"


def cmd_run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from swarm.launch import launch

    try:
        config = config_from_args(args)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else Path("runs") / config.run_id
    if (out / "summary.json").exists():
        print(f"error: {out} already holds a run's results; choose another --out "
              "(nothing was overwritten)", file=sys.stderr)
        return 2
    bar = tqdm(total=config.ticks, desc=f"{config.surface} {config.estimator}", unit="tick",
               disable=None)
    try:
        summary = launch(config, out, in_process=args.in_process, on_tick=lambda j: bar.update(1))
    except (ValueError, RuntimeError) as exc:
        bar.close()
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        bar.close()
        print(f"interrupted: partial result in {out}", file=sys.stderr)
        return 130
    bar.close()
    print(format_summary(summary))
    print(f"results: {out}")
    if args.plot:
        from swarm.plots import plot_run

        for path in plot_run(out):
            print(f"figure: {path}")
    return 0 if summary["complete"] else 1


def cmd_experiment(args: argparse.Namespace) -> int:
    """``experiment paper``: the paper's Section 4 grid, tables, figures and report;
    ``experiment terrain --dem PATH``: the terrain study (:mod:`swarm.terrain`)."""
    from swarm.experiment import FULL, QUICK, run_paper_experiment

    if args.workers is not None and args.workers < 1:
        print(f"error: --workers must be at least 1, got {args.workers}", file=sys.stderr)
        return 2
    if args.name == "terrain":
        return cmd_terrain(args)
    if args.dem is not None:
        print("error: --dem applies only to `experiment terrain`", file=sys.stderr)
        return 2
    args.out = args.out or "runs/experiment-paper"
    try:
        result = run_paper_experiment(args.out, QUICK if args.quick else FULL,
                                      workers=args.workers)
    except KeyboardInterrupt:
        print(f"interrupted: finished runs are in {Path(args.out) / 'runs'}", file=sys.stderr)
        return 130
    for path in result["tables"].values():
        print(f"table: {path}")
    for path in result["figures"].values():
        print(f"figure: {path}")
    print(f"report: {result['report']}")
    for name, reason in result["figure_problems"].items():
        print(f"figure {name} not drawn: {reason}", file=sys.stderr)
    for outcome in result["failed"]:
        print(f"FAILED {outcome.run.folder}: {outcome.error}", file=sys.stderr)
    timing = result["timing"]
    print(f"wall time {timing['total']:.1f} s (runs {timing['runs']:.1f} s, "
          f"figures {timing['figures']:.1f} s)")
    return 1 if result["failed"] else 0


def cmd_terrain(args: argparse.Namespace) -> int:
    """``experiment terrain --dem PATH --leader-start X,Y,VX,VY [--leader-start ...]``."""
    from swarm.terrain import TerrainSpec, quick, run_terrain_experiment

    if args.dem is None:
        print("error: experiment terrain needs --dem PATH", file=sys.stderr)
        return 2
    if not args.leader_start:
        print("error: experiment terrain needs --leader-start X,Y,VX,VY (repeat it for several "
              "starts): a DEM has no preset leader start", file=sys.stderr)
        return 2
    try:
        options = {"leader_starts": tuple(parse_leader_start(s) for s in args.leader_start)}
        for name in ("spacing", "followers", "ticks", "smoothing"):
            if getattr(args, name) is not None:
                options[name] = getattr(args, name)
        if args.estimators:
            options["estimators"] = tuple(args.estimators.split(","))
        if args.comm_periods:
            options["comm_periods"] = tuple(float(x) for x in args.comm_periods.split(","))
            options["position_periods"] = tuple(
                p for p in TerrainSpec.position_periods if p in options["comm_periods"]
            ) or options["comm_periods"][:1]
        spec = TerrainSpec(**options)
        spec = quick(spec) if args.quick else spec
        result = run_terrain_experiment(args.dem, args.out or "runs/experiment-terrain", spec,
                                        workers=args.workers)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    for path in result["tables"].values():
        print(f"table: {path}")
    for path in result["figures"].values():
        print(f"figure: {path}")
    print(f"report: {result['report']}")
    for name, reason in result["figure_problems"].items():
        print(f"figure {name} not drawn: {reason}", file=sys.stderr)
    for outcome in result["failed"]:
        print(f"FAILED {outcome.run.folder}: {outcome.error}", file=sys.stderr)
    print(f"wall time {result['wall_time']:.1f} s (runs)")
    return 1 if result["failed"] else 0


def cmd_dem_from_npz(args: argparse.Namespace) -> int:
    """``dem-from-npz OUT.tif [--npz PATH]``: matplotlib's Jacksboro DEM as a GeoTIFF."""
    from swarm.terrain import dem_from_npz

    try:
        path = dem_from_npz(args.out, args.npz)
    except (ValueError, OSError, KeyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"dem: {path}")
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    """``plot RUN_DIR``: draw one run's figures into RUN_DIR/figures."""
    from swarm.plots import plot_run

    try:
        paths = plot_run(args.run_dir)
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    for path in paths:
        print(f"figure: {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m swarm",
                                description="Column formation on an unknown surface over Zenoh.")
    sub = p.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run one case (default: the paper's type I case)")
    add_run_flags(run)
    layout = run.add_mutually_exclusive_group()
    layout.add_argument("--processes", dest="in_process", action="store_false",
                        help="agents as separate processes (default)")
    layout.add_argument("--in-process", dest="in_process", action="store_true",
                        help="agents as sessions in this process")
    run.add_argument("--out", help="results folder (default runs/<run_id>)")
    run.add_argument("--plot", action="store_true", help="draw the run's figures at the end")
    run.set_defaults(func=cmd_run, in_process=False)
    experiment = sub.add_parser("experiment", help="regenerate the paper's tables, figures and report")
    experiment.add_argument("name", choices=("paper", "terrain"), help="which experiment")
    experiment.add_argument("--out", default=None,
                            help="output folder D: D/runs, D/tables, D/figures, D/report.md "
                                 "(default runs/experiment-<name>)")
    experiment.add_argument("--quick", action="store_true",
                            help="reduced grid to check the pipeline")
    terrain = experiment.add_argument_group("terrain (experiment terrain only)")
    terrain.add_argument("--dem", help="DEM raster (GeoTIFF or ESRI ASCII grid)")
    terrain.add_argument("--leader-start", metavar="X,Y,VX,VY", action="append",
                         help="leader start on the DEM (m, m/s); required; repeat it to "
                              "average over several starts")
    terrain.add_argument("--spacing", type=float, help="rod length (m), default 40")
    terrain.add_argument("--followers", type=int, help="column length, default 10")
    terrain.add_argument("--ticks", type=int, help="ticks per run, default 40")
    terrain.add_argument("--smoothing", type=float, help="spline smoothing s, default 0")
    terrain.add_argument("--estimators", help="comma-separated, default stay,persist,edmd-b,auto")
    terrain.add_argument("--comm-periods", help="comma-separated, default 0.32,0.64,1.28,2.56,5.12")
    experiment.add_argument("--workers", type=int, default=None,
                            help="runs in parallel (default min(2, CPU count))")
    experiment.set_defaults(func=cmd_experiment)
    dem = sub.add_parser("dem-from-npz", help="write matplotlib's sample DEM (Jacksboro fault, "
                                              "USGS, public domain) as a GeoTIFF")
    dem.add_argument("out", metavar="OUT.tif")
    dem.add_argument("--npz", help="another .npz in the same layout (default: the sample)")
    dem.set_defaults(func=cmd_dem_from_npz)
    plot = sub.add_parser("plot", help="draw one run's figures into RUN_DIR/figures")
    plot.add_argument("run_dir", metavar="RUN_DIR", help="a results folder of `swarm run`")
    plot.set_defaults(func=cmd_plot)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)
