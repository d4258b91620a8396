"""``python -m swarm``: run one case (``run``), and more subcommands as they come (design §9)."""
from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from protocol.cli import (
    FAILED,
    INTERRUPTED,
    REFUSED,
    add_log_level_flag,
    add_results_flags,
    default_out,
    ends_with,
    refuse,
    run_command,
    run_failures,
    setup_logging,
)
from protocol.config import (
    OPTIONS,
    Option,
    RunConfig,
    applies_to,
    config_from_dict,
    config_from_file,
    file_options,
    flag_of,
    with_env_domain,
)
from protocol.distribution import DISTRIBUTION, version
from protocol.folder import FolderLock, check_out_dir
from protocol.session import add_connection_flags, connection_config


def option_help(declared: Option) -> str:
    """``--help`` of a run option: its meaning, where it applies, and (for a value) its
    default and unit, e.g. ``rod length d (Riemannian) [default 3.57 m]``."""
    where = applies_to(declared)
    text = f"{declared.meaning}; {where}" if where else declared.meaning
    if declared.kind is bool:
        return text
    unit = {"": "", "1": ", dimensionless"}.get(declared.unit, f" {declared.unit}")
    if declared.name in CLI_DEFAULTS:
        default, unit = CLI_DEFAULTS[declared.name], unit and f"; in{unit.lstrip(',')}"
    else:
        default = declared.show(declared.default)
    return f"{text} [default {default}{unit}]".replace("%", "%%")


CLI_DEFAULTS = {"run_id": "a new one from the clock", "leader_start": "the surface's",
                "max_speed": "twice the leader's speed",
                "max_accel": "4 × max speed / comm period"}
"""What ``swarm run`` takes for an option it is not given, where that is not the option's
declared default."""


def add_run_flags(p: argparse.ArgumentParser) -> None:
    """One flag per declared run option (:data:`protocol.config.OPTIONS`), unset by default
    so that only the flags given override the ``--config`` file; ``--smoothing``, and
    ``--config``."""
    for declared in OPTIONS.values():
        flag = flag_of(declared)
        if flag is None:
            continue
        if declared.kind is bool:  # a switch sets the opposite of the default
            kind = {"action": "store_const", "const": not declared.default}
        elif declared.choices and declared.name != "estimator":
            kind = {"choices": declared.choices}
        else:
            kind = {"type": declared.kind} if declared.kind in (int, float) else {}
        p.add_argument(flag, dest=declared.name, default=None, help=option_help(declared),
                       metavar=declared.metavar, **kind)
    p.add_argument("--smoothing", type=float, default=None,
                   help="DEM surfaces: scipy's spline smoothing s (0 = interpolate; TOML: "
                        "surface_params.smoothing) (default 0 m²)")
    p.add_argument("--config", metavar="FILE",
                   help="TOML file with any of the options; flags override it")


def options_from_args(args: argparse.Namespace, file: Mapping[str, Any]) -> dict:
    """The run options the user gave: ``file``'s (the ``--config`` file's,
    :func:`config_file`), then the flags given (ValueError on bad input). A value equal to its
    default counts as not given."""
    data = dict(file)
    for name in OPTIONS:
        value = getattr(args, name, None)
        if value is not None:
            data[name] = value
    if isinstance(data.get("leader_start"), str):
        data["leader_start"] = parse_leader_start(data["leader_start"])
    if args.smoothing is not None:
        data["surface_params"] = {**data.get("surface_params", {}), "smoothing": args.smoothing}
    return data


def config_from_args(args: argparse.Namespace) -> RunConfig:
    """Defaults, then the ``--config`` file, then the flags given (ValueError on bad input);
    a new run id unless one is given."""
    from swarm.launch import new_run_id

    file = config_file(args)
    data = with_env_domain(options_from_args(args, file))
    data.setdefault("run_id", new_run_id())
    try:
        return config_from_dict(data)
    except ValueError:
        if args.config:  # the file alone is at fault: say so, naming it
            config_from_file(file, args.config)
        raise


def config_file(args: argparse.Namespace) -> dict:
    """The options of the ``--config`` file (none without), read under the input limits
    (ValueError naming the file)."""
    return file_options(args.config) if args.config else {}


def comma_numbers(text: str, count: int) -> tuple[float, ...] | None:
    """``text`` as ``count`` comma-separated numbers, or None if it is not that."""
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        return None
    return values if len(values) == count else None


def parse_leader_start(text: str) -> tuple[float, ...]:
    """``"X,Y,VX,VY"`` -> four floats (ValueError naming --leader-start otherwise)."""
    values = comma_numbers(text, 4)
    if values is None:
        raise ValueError(f"--leader-start must be X,Y,VX,VY numbers, got {text!r}")
    return values


def format_summary(summary: dict) -> str:
    """The per-follower table printed at the end of a run: the estimator's required range,
    the baselines (persist from the same noisy readings, its ratio, the noise-free persist
    counterfactual), the formation's health (mean and worst formation error, ticks beyond
    the tolerance) and what ``auto`` followed."""
    from swarm.grid import table_number  # not at start-up: grid brings the process pool

    label = "required (" + summary["estimator"] + ")"
    width = max(20, len(label))
    head = (f"{'follower':>8}  {label:>{width}}  {'rmse':>8}  {'stay':>8}  {'persist':>8}  "
            f"{'/persist':>8}  {'persist*':>8}  {'lost':>4}  {'missed':>6}  {'fallback':>8}  "
            f"{'formation':>9}  {'worst':>8}  {'broken':>6}")
    lines = [head, "-" * len(head)]
    shares = []
    for k, s in summary["followers"].items():
        required, persist = s["mean_required_range"], s["mean_persist_range"]
        ratio = required / persist if required is not None and persist else None
        ranges = [table_number(x).rjust(8) for x in (
            s["rmse"], s["mean_stay_range"], persist, ratio,
            s.get("mean_persist_range_noise_free"))]
        lines.append(f"{k:>8}  {table_number(required):>{width}}  " + "  ".join(ranges)
                     + f"  {s['lost_ticks']:>4}  {s['missed_ticks']:>6}  "
                     f"{s.get('fallback_ticks', 0):>8}  "
                     f"{table_number(s.get('mean_formation_error')):>9}  "
                     f"{table_number(s.get('worst_formation_error')):>8}  "
                     f"{s.get('broken_ticks', 0):>6}")
        followed = s.get("followed") or {}
        if len(followed) > 1:
            shares.append(f"follower {k} followed " + ", ".join(
                f"{name} {share:.0%}" for name, share in followed.items()))
    lines.append("persist: from the same (noisy) readings; persist*: its noise-free "
                 "counterfactual; /persist: required over persist; formation, worst: mean and "
                 "worst distance from the ideal formation; broken: ticks beyond "
                 f"{summary.get('formation_tolerance', math.inf):g} m")
    if summary.get("motion") == "drive":
        lines += [f"follower {k} drove {s['path_length']:.4g} m: reach error "
                  f"{table_number(s['mean_reach_error'])}, snap error "
                  f"{table_number(s['mean_snap_error'])}, formation error "
                  f"{table_number(s['mean_formation_error'])}, {s['saturated_steps']} steps "
                  "at a limit" for k, s in summary["followers"].items()]
    lines += shares
    state = "complete" if summary["complete"] else f"INCOMPLETE: {summary['reason']}"
    if summary.get("formation_broken"):
        broken = sum(s.get("broken_ticks", 0) for s in summary["followers"].values())
        state += (f", FORMATION BROKEN: {broken} follower-ticks beyond "
                  f"{summary['formation_tolerance']:g} m")
    lines.append(f"surface {summary['surface']}, comm period {summary['comm_period']}, "
                 f"{summary['ticks_completed']} ticks, {summary['wall_time']:.1f} s wall, {state}")
    return "\n".join(lines)


def empty_followers(summary: dict, init_ticks: int) -> list[str]:
    """One line per follower that missed every tick or estimated none (a run that only
    looks complete)."""
    lines, n = [], summary["ticks_completed"]
    for k, s in summary["followers"].items():
        if n and s["missed_ticks"] >= n:
            lines.append(f"follower {k} missed every tick ({s['missed_ticks']} of {n}): "
                         "it never settled in time, its numbers measure nothing it did")
        elif s["estimated_ticks"] == 0 and s.get("fallback_ticks"):
            lines.append(f"follower {k} estimated no tick: its estimator was never ready, "
                         f"persist stood in on all {s['fallback_ticks']} ticks from tick "
                         f"{init_ticks} (does it need more samples than the run has?)")
        elif s["estimated_ticks"] == 0:
            lines.append(f"follower {k} estimated no tick: estimation starts at tick "
                         f"{init_ticks} and the run has {n} ticks ({s['missed_ticks']} missed)")
    return lines


def cmd_run(args: argparse.Namespace) -> int:
    setup_logging(args.log_level)
    live = endpoint = None
    with ends_with(REFUSED, ValueError, RuntimeError):
        config = config_from_args(args)
        from world.main import require_extras

        require_extras(config)  # before anything runs
        out = Path(args.out) if args.out else default_out(config.run_id)
        if args.live:  # its arguments are checked before anything is written
            from protocol.session import free_tcp_endpoint
            from swarm.live.observer import LiveView

            live = LiveView(port=args.live_port, run_id=config.run_id)
            endpoint = free_tcp_endpoint()
        check_out_dir(out)
    lock = FolderLock(out, config.run_id)
    try:  # the folder is checked under its one-writer lock, held until the run ends
        with ends_with(REFUSED, ValueError, OSError):
            lock.acquire()
            if (out / "summary.json").exists() and not args.force:
                raise ValueError(f"{out} already holds a run's results; choose another --out "
                                 "or replace them with --force (nothing was overwritten)")
        if live is not None:
            with ends_with(REFUSED, RuntimeError):
                print(f"live view: {live.start()}", flush=True)
        return _run_and_report(args, config, out, live, endpoint, lock)
    finally:
        lock.release()
        if live is not None:
            live.close()


def _run_and_report(args: argparse.Namespace, config: RunConfig, out: Path, live, endpoint,
                    lock: FolderLock) -> int:
    from tqdm import tqdm

    from swarm.launch import launch

    def observe(credentials) -> None:  # the live view joins as the run's observer user
        from protocol.session import zenoh_config
        from swarm.deploy import OBSERVER

        live.connect(zenoh_config("client", connect=[endpoint], user=OBSERVER,
                                  password=credentials.passwords[OBSERVER]))

    bar = tqdm(total=config.ticks, desc=f"{config.surface} {config.estimator}", unit="tick",
               disable=None)
    try:
        with run_failures(out):  # e.g. a raster larger than the limit: refused, nothing ran
            summary = launch(config, out, in_process=args.in_process,
                             on_tick=lambda j: bar.update(1), endpoint=endpoint,
                             force=args.force, lock=lock,
                             before_agents=None if live is None else observe)
    except KeyboardInterrupt:
        print(f"interrupted: partial result in {out}", file=sys.stderr)
        return INTERRUPTED
    finally:
        bar.close()
    print(format_summary(summary))
    print(f"results: {out}", flush=True)
    if args.plot:
        from swarm.plots import plot_run

        for path in plot_run(out):
            print(f"figure: {path}")
    # a run that ended early says why in one line; its empty followers are no news then
    empty = empty_followers(summary, config.init_ticks) if summary["complete"] else []
    for line in empty:
        print(f"warning: {line}", file=sys.stderr)
    if not summary["complete"]:
        print(f"error: run incomplete: {summary['reason']}", file=sys.stderr)
    elif summary.get("formation_broken"):  # one line says why: incompleteness first
        print("error: the formation broke (a follower settled beyond --formation-tolerance)",
              file=sys.stderr)
    if live is not None:
        print(f"live view still at {live.server.url} (Ctrl-C to quit)", flush=True)
        live.serve_until_interrupted()
    return FAILED if empty or not summary["complete"] or summary.get("formation_broken") else 0


def cmd_watch(args: argparse.Namespace) -> int:
    """``watch``: the live view of a run assembled elsewhere, as a read-only observer. It
    connects first (retrying up to Zenoh's connect timeout while the router is not up yet),
    so no page is announced without a router behind it."""
    from swarm.live.observer import LiveView

    with ends_with(REFUSED, ValueError):
        conf = connection_config(args)
        live = LiveView(port=args.live_port, run_id=args.run_id)
    return _serve(live, conf)


def cmd_replay(args: argparse.Namespace) -> int:
    """``replay RUN_DIR``: the same page for a finished run, with a tick slider."""
    from swarm.live.observer import LiveView
    from swarm.live.store import load_run

    with ends_with(REFUSED, ValueError):
        live = LiveView(port=args.live_port, store=load_run(args.run_dir), replay=True)
    return _serve(live, None)


def _serve(live, conf) -> int:
    """Serve ``live`` (connected with ``conf`` first unless None) until Ctrl-C."""
    try:
        with ends_with(FAILED, RuntimeError):
            if conf is not None:
                live.connect(conf)
            print(f"live view: {live.start()} (Ctrl-C to quit)", flush=True)
        live.serve_until_interrupted()
    finally:
        live.close()
    return 0


TERRAIN_ONLY = ("dem", "leader_start", "spacing", "followers", "ticks", "smoothing",
                "estimators", "comm_periods")
"""The flags of ``experiment terrain`` that ``experiment paper`` refuses."""


def cmd_experiment(args: argparse.Namespace) -> int:
    """``experiment paper``: the paper's Section 4 grid, tables, figures and report;
    ``experiment terrain --dem PATH``: the terrain study (:mod:`swarm.terrain`)."""
    from swarm.experiment import FULL, QUICK, run_paper_experiment

    with ends_with(REFUSED, ValueError):
        _check_workers(args.workers)
    if args.name == "terrain":
        return cmd_terrain(args)
    if args.name == "drive":
        return cmd_drive_study(args)
    _refuse_terrain_flags(args)
    args.out = args.out or "runs/experiment-paper"
    result = _run_grid(lambda: run_paper_experiment(
        args.out, QUICK if args.quick else FULL, workers=args.workers, scheduler=args.scheduler),
        args.out)
    timing = result["timing"]
    return _print_experiment(result, f"wall time {timing['total']:.1f} s (runs "
                                     f"{timing['runs']:.1f} s, figures {timing['figures']:.1f} s)")


def _refuse_terrain_flags(args: argparse.Namespace, allowed: tuple[str, ...] = ()) -> None:
    """Refuse a flag of ``experiment terrain`` (:data:`TERRAIN_ONLY`) given to another
    experiment, but those in ``allowed``."""
    for name in TERRAIN_ONLY:
        if name not in allowed and getattr(args, name) is not None:
            refuse(f"--{name.replace('_', '-')} applies only to `experiment terrain`")


def _print_experiment(result: dict, wall_line: str) -> int:
    """Print what an experiment wrote and what failed; its exit status."""
    for path in result["tables"].values():
        print(f"table: {path}")
    for path in result["figures"].values():
        print(f"figure: {path}")
    print(f"report: {result['report']}")
    for name, reason in result["figure_problems"].items():
        print(f"figure {name} not drawn: {reason}", file=sys.stderr)
    status = _print_failed(result["failed"])
    print(wall_line)
    return status


def _run_grid(run, out) -> dict:
    """``run()``'s result. An output folder that cannot hold results, or a grid that cannot
    start (an unreachable scheduler), is refused; Ctrl-C ends the command, naming where the
    finished runs are kept."""
    with ends_with(REFUSED, ValueError):
        check_out_dir(out)
    try:
        with ends_with(REFUSED, RuntimeError):
            return run()
    except KeyboardInterrupt:
        print(f"interrupted: finished runs are in {Path(out) / 'runs'}", file=sys.stderr)
        raise


def _print_failed(failed) -> int:
    """One ``FAILED`` line per failed run; the command's status (1 if any failed)."""
    for outcome in failed:
        print(f"FAILED {outcome.run.folder}: {outcome.error}", file=sys.stderr)
    return FAILED if failed else 0


def _run_sweep_and_print(name, base, axes, out, follower, workers, scheduler=None) -> int:
    from swarm.sweep import format_means, run_sweep

    result = _run_grid(lambda: run_sweep(name, base, axes, out, follower=follower,
                                         workers=workers, scheduler=scheduler), out)
    print(format_means(result["means"], result["keys"]))
    for path in result["tables"].values():
        print(f"table: {path}")
    return _print_failed([o for o in result["outcomes"] if not o.ok])


def _check_workers(workers: int | None) -> None:
    if workers is not None and workers < 1:
        raise ValueError(f"--workers must be at least 1, got {workers}")


def cmd_compare(args: argparse.Namespace) -> int:
    """``compare``: one setup (``run``'s flags), several estimators and seeds, one table.
    Each estimator runs with the options of the setup that it uses (the others keep their
    defaults in its runs); an option no estimator uses is refused."""
    from swarm.grid import expand
    from swarm.launch import new_run_id
    from swarm.sweep import compare_axes

    if args.estimator is not None:
        refuse("compare takes --estimators (comma-separated), not --estimator")
    with ends_with(REFUSED, ValueError):
        _check_workers(args.workers)
        base = options_from_args(args, config_file(args))
        if args.seeds:
            try:
                seeds = [int(x) for x in args.seeds.split(",")]
            except ValueError:
                raise ValueError(f"--seeds must be comma-separated integers, got "
                                 f"{args.seeds!r}") from None
        else:
            seeds = [base.pop("seed", OPTIONS["seed"].default)]
        axes = compare_axes([e for e in args.estimators.split(",") if e], seeds)
        runs = expand("compare", base, axes)  # every combination is valid before anything runs
        followers = runs[0].config.followers
        if not 1 <= args.follower <= followers:
            raise ValueError(f"--follower must be in 1..{followers}, got {args.follower}")
    out = Path(args.out or Path("runs") / f"compare-{base.get('run_id') or new_run_id()}")
    return _run_sweep_and_print("compare", base, axes, out, args.follower, args.workers,
                                args.scheduler)


def cmd_sweep(args: argparse.Namespace) -> int:
    """``sweep GRID.toml``: any grid of options, one table (``experiment paper`` is one)."""
    from swarm.sweep import load_grid

    with ends_with(REFUSED, ValueError):
        _check_workers(args.workers)
        name, base, axes, follower = load_grid(args.grid)
    out = Path(args.out) if args.out else Path("runs") / f"sweep-{name}"
    return _run_sweep_and_print(name, base, axes, out, follower, args.workers, args.scheduler)


def cmd_terrain(args: argparse.Namespace) -> int:
    """``experiment terrain --dem PATH --leader-start X,Y,VX,VY [--leader-start ...]``."""
    from swarm.terrain import TerrainSpec, quick, run_terrain_experiment

    if args.dem is None:
        refuse("experiment terrain needs --dem PATH")
    if not args.leader_start:
        refuse("experiment terrain needs --leader-start X,Y,VX,VY (repeat it for several "
               "starts): a DEM has no preset leader start")
    with ends_with(REFUSED, ValueError):  # the options, the DEM or a leader start
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
        out = args.out or "runs/experiment-terrain"
        result = _run_grid(lambda: run_terrain_experiment(args.dem, out, spec,
                                                          workers=args.workers), out)
    return _print_experiment(result, f"wall time {result['wall_time']:.1f} s (runs)")


def cmd_drive_study(args: argparse.Namespace) -> int:
    """``experiment drive [--quick] [--dem PATH --leader-start X,Y,VX,VY]``: the study of
    driving followers (:mod:`swarm.drive_study`)."""
    from swarm.drive_study import DriveStudySpec, quick, run_drive_study

    _refuse_terrain_flags(args, allowed=("dem", "leader_start"))
    spec = DriveStudySpec()
    if args.dem is not None:
        if not args.leader_start or len(args.leader_start) != 1:
            refuse("experiment drive --dem needs one --leader-start X,Y,VX,VY")
        with ends_with(REFUSED, ValueError):
            spec = DriveStudySpec(dem=args.dem,
                                  dem_start=parse_leader_start(args.leader_start[0]))
    spec = quick(spec) if args.quick else spec
    out = args.out or "runs/experiment-drive"
    with ends_with(REFUSED, ValueError):  # the options or the DEM
        result = _run_grid(lambda: run_drive_study(
            out, spec, workers=args.workers,
            on_run=lambda done, total: print(f"\rrun {done}/{total}", end="", file=sys.stderr,
                                             flush=True)), out)
    print(file=sys.stderr)
    return _print_experiment({**result, "figure_problems": {}, "failed": []},
                             f"wall time {result['wall_time']:.1f} s ({result['runs']} runs in "
                             f"{result['runs_time']:.1f} s)")


def cmd_dem_crop(args: argparse.Namespace) -> int:
    """``dem-crop IN OUT.tif [--bounds XMIN,YMIN,XMAX,YMAX]``: a rectangle of a DEM with data
    at every node."""
    from swarm.terrain import crop_dem

    with ends_with(REFUSED, ValueError, OSError):
        crop = crop_dem(args.source, args.out, args.bounds, force=args.force,
                        max_cells=args.max_cells)
    (i0, i1), (j0, j1) = crop.columns, crop.rows
    print(f"dem: {crop.path}: {i1 - i0 + 1} × {j1 - j0 + 1} nodes (columns {i0}–{i1}, rows "
          f"{j0}–{j1} from the south of {args.source}; {crop.dropped} no-data node(s) left out)")
    print(f"its frame: x ∈ [0, {crop.size[0]:.6g}], y ∈ [0, {crop.size[1]:.6g}] m; origin at "
          f"({crop.origin[0]:.6g}, {crop.origin[1]:.6g}) m of {args.source}'s frame "
          "(subtract it from a leader start given there)")
    return 0


def _bounds(text: str) -> tuple[float, float, float, float]:
    """``--bounds XMIN,YMIN,XMAX,YMAX`` (argparse type)."""
    values = comma_numbers(text, 4)
    if values is None or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected four finite numbers XMIN,YMIN,XMAX,YMAX, "
                                         f"got {text!r}")
    return values


def cmd_dem_from_npz(args: argparse.Namespace) -> int:
    """``dem-from-npz OUT.tif [--npz PATH] [--force]``: matplotlib's Jacksboro DEM as a
    GeoTIFF."""
    from swarm.terrain import dem_from_npz

    with ends_with(REFUSED, ValueError), ends_with(FAILED, OSError):
        path = dem_from_npz(args.out, args.npz, force=args.force)
    print(f"dem: {path}")
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    """``plot RUN_DIR [--force]``: draw one run's figures into RUN_DIR/figures."""
    from swarm.plots import plot_run

    with ends_with(REFUSED, ValueError), ends_with(FAILED, OSError):
        paths = plot_run(args.run_dir, force=args.force)
    for path in paths:
        print(f"figure: {path}")
    return 0


def cmd_deploy(args: argparse.Namespace) -> int:
    """``deploy``: write a locked-down docker-compose deployment of one run into ``--out``."""
    from swarm.deploy import write_deployment
    from swarm.launch import new_run_id

    with ends_with(REFUSED, ValueError), ends_with(FAILED, OSError):
        ros = {} if args.ros_domain is None else {"ros2": True, "ros_domain": args.ros_domain}
        config = RunConfig(run_id=args.run_id or new_run_id(), followers=args.followers,
                           start_timeout=args.start_timeout, agent_timeout=args.agent_timeout,
                           **ros)
        written = write_deployment(args.out, config, force=args.force)
    print(f"deployment of run {config.run_id} ({config.followers} followers): "
          f"{len(written)} files in {args.out}; secrets in {Path(args.out) / 'secrets'} "
          "(keep them out of version control)")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    """``export RUN_DIR [--out BAG_DIR] [--force]``: a finished run as a rosbag2/MCAP bag."""
    from swarm.ros2_export import export_run

    with ends_with(REFUSED, ValueError), ends_with(FAILED, OSError):
        bag = export_run(args.run_dir, args.out, force=args.force)
    print(f"bag: {bag}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m swarm",
                                description="Column formation on an unknown surface over Zenoh.")
    p.add_argument("--version", action="version", version=f"{DISTRIBUTION} {version()}")
    sub = p.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run one case (default: the paper's type I case)")
    add_run_flags(run)
    layout = run.add_mutually_exclusive_group()
    layout.add_argument("--processes", dest="in_process", action="store_false",
                        help="agents as separate processes (default)")
    layout.add_argument("--in-process", dest="in_process", action="store_true",
                        help="agents as sessions in this process")
    add_results_flags(run)
    run.add_argument("--plot", action="store_true", help="draw the run's figures at the end")
    run.add_argument("--live", action="store_true",
                     help="serve a live view of the run on localhost (kept up until Ctrl-C)")
    add_live_port(run)
    add_log_level_flag(run)
    run.set_defaults(func=cmd_run, in_process=False)
    experiment = sub.add_parser("experiment",
                                help="regenerate the paper's tables, figures and report")
    experiment.add_argument("name", choices=("paper", "terrain", "drive"),
                            help="which experiment")
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
    terrain.add_argument("--estimators", help="comma-separated, default "
                                              "stay,persist,edmd-b,cv,kalman,arx,gp,auto")
    terrain.add_argument("--comm-periods", help="comma-separated, default 0.32,0.64,1.28,2.56,5.12")
    add_grid_flags(experiment)
    experiment.set_defaults(func=cmd_experiment)
    compare = sub.add_parser("compare", help="one setup, several estimators and seeds, one table")
    add_run_flags(compare)
    compare.add_argument("--estimators", default="persist,edmd-b,cv,kalman,arx,gp,auto",
                         help="comma-separated: edmd-<letter>, a built-in name, or "
                              "package.module:Name (default: %(default)s)")
    compare.add_argument("--seeds", help="comma-separated seeds (default: --seed)")
    compare.add_argument("--follower", type=int, default=1, help="whose metrics (default 1)")
    compare.add_argument("--out", help="output folder (default runs/compare-<run id>)")
    add_grid_flags(compare)
    compare.set_defaults(func=cmd_compare)
    sweep = sub.add_parser("sweep", help="run a grid file (surfaces × estimators × ...)")
    sweep.add_argument("grid", metavar="GRID.toml", help="the grid: [base] options and [axes]")
    sweep.add_argument("--out", help="output folder (default runs/sweep-<name>)")
    add_grid_flags(sweep)
    sweep.set_defaults(func=cmd_sweep)
    dem = sub.add_parser("dem-from-npz", help="write matplotlib's sample DEM (Jacksboro fault, "
                                              "USGS, public domain) as a GeoTIFF")
    dem.add_argument("out", metavar="OUT.tif")
    dem.add_argument("--npz", help="another .npz in the same layout (default: the sample)")
    dem.add_argument("--force", action="store_true", help="replace OUT if it exists")
    dem.set_defaults(func=cmd_dem_from_npz)
    crop = sub.add_parser("dem-crop", help="keep a rectangle of a DEM without no-data nodes "
                                           "(by default the largest) as a GeoTIFF")
    crop.add_argument("source", metavar="IN", help="a DEM raster (GeoTIFF, .asc, ...)")
    crop.add_argument("out", metavar="OUT.tif")
    crop.add_argument("--bounds", type=_bounds, metavar="XMIN,YMIN,XMAX,YMAX",
                      help="keep these nodes instead (m, in IN's frame: origin at its "
                           "south-west node)")
    crop.add_argument("--force", action="store_true", help="replace OUT if it exists")
    crop.add_argument("--max-cells", type=int, default=None, metavar="N",
                      help="refuse a raster of more cells than N (default: twice what a run "
                           "loads; see docs/reliability.md)")
    crop.set_defaults(func=cmd_dem_crop)
    plot = sub.add_parser("plot", help="draw one run's figures into RUN_DIR/figures")
    plot.add_argument("run_dir", metavar="RUN_DIR", help="a results folder of `swarm run`")
    plot.add_argument("--force", action="store_true", help="draw the figures anew if they exist")
    plot.set_defaults(func=cmd_plot)
    deploy = sub.add_parser("deploy", help="write a locked-down docker-compose deployment "
                                           "(router rules, credentials, TLS, compose, run.toml)")
    deploy.add_argument("--followers", type=int, required=True, help="number of followers N")
    deploy.add_argument("--out", required=True, help="folder to write (deploy/README.md)")
    deploy.add_argument("--run-id", help="the run id the router's rules admit (default: new)")
    deploy.add_argument("--start-timeout", type=float, default=60.0,
                        help="seconds the world waits for the agents (containers start slowly)")
    deploy.add_argument("--agent-timeout", type=float, default=30.0)
    deploy.add_argument("--ros-domain", type=int, help="the world publishes the run's ROS 2 "
                                                       "topics on this domain, 0-232 (default: "
                                                       "no ROS 2; the rules admit domain 0)")
    deploy.add_argument("--force", action="store_true",
                        help="replace the passwords and keys already in OUT/secrets")
    deploy.set_defaults(func=cmd_deploy)
    export = sub.add_parser("export", help="a finished run as a rosbag2 bag (MCAP) for ROS 2 "
                                           "tools (needs the [ros] extra)")
    export.add_argument("run_dir", metavar="RUN_DIR", help="a complete results folder")
    export.add_argument("--out", metavar="BAG_DIR", help="the bag folder (default RUN_DIR/bag)")
    export.add_argument("--force", action="store_true", help="replace an existing bag folder")
    export.set_defaults(func=cmd_export)
    watch = sub.add_parser("watch", help="live view of a running run, as a read-only observer")
    watch.add_argument("--run-id", required=True, help="the run to watch")
    add_connection_flags(watch, connect_required=True)
    add_live_port(watch)
    watch.set_defaults(func=cmd_watch)
    replay = sub.add_parser("replay", help="the live view of a finished run, with a tick slider")
    replay.add_argument("run_dir", metavar="RUN_DIR", help="a results folder")
    add_live_port(replay)
    replay.set_defaults(func=cmd_replay)
    return p


def add_grid_flags(parser: argparse.ArgumentParser) -> None:
    """``--workers`` and ``--scheduler``: where a grid of runs executes (swarm.grid.run_grid)."""
    parser.add_argument("--workers", type=int, default=None,
                        help="runs in parallel (default min(2, CPU count))")
    parser.add_argument("--scheduler", metavar="ADDRESS", default=None,
                        help="address of a dask scheduler (tcp://host:8786): each run is one "
                             "task on its workers (default: a local process pool); finished "
                             "runs in --out are not run again")


def add_live_port(parser: argparse.ArgumentParser) -> None:
    from swarm.live import DEFAULT_PORT

    parser.add_argument("--live-port", type=int, default=DEFAULT_PORT,
                        help=f"port of the page on 127.0.0.1 (default {DEFAULT_PORT}, "
                             "0 = any free)")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_command(lambda: args.func(args))
