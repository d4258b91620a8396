"""``python -m swarm``: run one case (``run``), and more subcommands as they come (design §9)."""
from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from protocol.cli import (
    FAILED,
    INTERRUPTED,
    REFUSED,
    NewFolder,
    Parser,
    add_log_level_flag,
    add_results_flags,
    default_out,
    ends_with,
    exit_process,
    program,
    quantity,
    refuse,
    run_command,
    run_failures,
    setup_logging,
)
from protocol.config import (
    OPTIONS,
    AgentBrief,
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
from swarm.ros2_join import add_ros2_listen_flag, check_ros2_listen

if TYPE_CHECKING:  # for annotations only: the world is imported when a run needs it
    from world.surfaces import Surface


def option_help(declared: Option) -> str:
    """``--help`` of a run option: its meaning, where it applies, and (for a value) its
    default and unit, e.g. ``rod length d (Riemannian) [default 3.57 m]``."""
    where = applies_to(declared)
    text = f"{declared.meaning}; {where}" if where else declared.meaning
    if declared.kind is bool:
        return text
    unit = {"": "", "1": ", dimensionless"}.get(declared.unit, f" {declared.unit}")
    if declared.name in CLI_DEFAULTS:
        default = CLI_DEFAULTS[declared.name] + (unit and f"; in{unit.lstrip(',')}")
    elif declared.unit in ("", "1"):
        default = declared.show(declared.default) + unit
    else:  # a counted unit in the singular for one: [default 1 agent]
        default = quantity(declared.show(declared.default), declared.unit)
    return f"{text} [default {default}]".replace("%", "%%")


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
                        "surface_params.smoothing) [default 0 m²]")
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
        from world.results import broken_ticks

        state += (f", FORMATION BROKEN: {broken_ticks(summary)} follower-ticks beyond "
                  f"{summary['formation_tolerance']:g} m")
    lines.append(f"surface {summary['surface']}, comm period {summary['comm_period']} s, "
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
        surface = prepare_run(config)
        check_ros2_listen(args.ros2_listen, config.ros2)
        out = Path(args.out) if args.out else default_out(config.run_id)
        if args.live:  # its arguments are checked before anything is written
            from protocol.session import free_tcp_endpoint
            from swarm.live.observer import LiveView

            live = LiveView(port=args.live_port, run_id=config.run_id)
            endpoint = free_tcp_endpoint()
    folder = NewFolder(out, config.run_id)
    lock = FolderLock(out, config.run_id)
    try:  # the folder is checked under its one-writer lock, held until the run ends
        with folder.undone_if_refused():
            try:
                with ends_with(REFUSED, ValueError, OSError):
                    check_out_dir(out)
                    lock.acquire()
                    if (out / "summary.json").exists() and not args.force:
                        raise ValueError(f"{out} already holds a run's results; choose another "
                                         "--out or replace them with --force (nothing was "
                                         "overwritten)")
                if live is not None:
                    with ends_with(REFUSED, RuntimeError):
                        print(f"live view: {live.start()}", flush=True)
                return _run_and_report(args, config, surface, out, live, endpoint, lock,
                                       folder)
            finally:
                lock.release()
    finally:
        if live is not None:
            live.close()


def prepare_run(config: RunConfig) -> Surface:
    """Everything ``config`` can be refused for before a run writes anything (ValueError,
    one line; a missing extra): the extras it needs, its surface, raster and start
    (:func:`world.main.resolve_with_surface`) and that a plug-in estimator is importable here
    (found, none of its code run: the world's process never runs an agent's code). Returns
    its surface, built once (the run is given it)."""
    from protocol.config import PLUGIN_ESTIMATOR
    from protocol.imports import user_module_exists
    from world.main import require_extras, resolve_with_surface

    require_extras(config)
    if PLUGIN_ESTIMATOR.match(config.estimator):
        module = config.estimator.split(":")[0]
        if not user_module_exists(module):
            raise ValueError(f"estimator {config.estimator!r}: no module {module!r} is "
                             "importable here (the installed packages and the current folder)")
    return resolve_with_surface(config)[1]


def _run_and_report(args: argparse.Namespace, config: RunConfig, surface, out: Path, live,
                    endpoint, lock: FolderLock, folder: NewFolder) -> int:
    from tqdm import tqdm

    from swarm.launch import launch
    from world.results import run_failure

    def observe(credentials) -> None:  # the live view joins as the run's observer user
        from protocol.session import zenoh_config
        from swarm.deploy import OBSERVER

        live.connect(zenoh_config("client", connect=[endpoint], user=OBSERVER,
                                  password=credentials.passwords[OBSERVER]))

    bar = tqdm(total=config.ticks, desc=f"{config.surface} {config.estimator}", unit="tick",
               disable=None)
    ticks = 0  # recorded so far

    def on_tick(tick: int) -> None:
        nonlocal ticks
        ticks += 1
        bar.update(1)

    try:
        with run_failures(out):  # e.g. a raster larger than the limit: refused, nothing ran
            summary = launch(config, out, in_process=args.in_process, on_tick=on_tick,
                             endpoint=endpoint, force=args.force, lock=lock, surface=surface,
                             ros2_listen=args.ros2_listen,
                             before_agents=None if live is None else observe)
    except KeyboardInterrupt:
        bar.close()
        if not ticks and folder.made:  # nothing recorded: nothing is kept
            lock.release()
            folder.discard()
            print(f"interrupted before the first tick: nothing kept ({out} removed)",
                  file=sys.stderr)
        else:
            print(f"interrupted: partial result in {out} ({ticks} ticks)", file=sys.stderr)
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
    if (failure := run_failure(summary)) is not None:  # one line says why
        print(f"error: {failure}", file=sys.stderr)
    if live is not None:
        print(f"live view still at {live.server.url} (Ctrl-C to quit)", flush=True)
        live.serve_until_interrupted()
    return FAILED if empty or failure is not None else 0


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


def cmd_experiment(args: argparse.Namespace) -> int:
    """``experiment paper``: the paper's Section 4 grid, tables, figures and report;
    ``experiment terrain --dem PATH``: the terrain study (:mod:`swarm.terrain`); ``experiment
    drive``: the study of driving followers (:mod:`swarm.drive_study`)."""
    from swarm.experiment import FULL, QUICK, run_paper_experiment

    with ends_with(REFUSED, ValueError):
        _check_workers(args.workers)
    if args.name == "terrain":
        return cmd_terrain(args)
    if args.name == "drive":
        return cmd_drive_study(args)
    args.out = args.out or "runs/experiment-paper"
    result = _run_grid(lambda: run_paper_experiment(
        args.out, QUICK if args.quick else FULL, workers=args.workers, scheduler=args.scheduler),
        args.out)
    timing = result["timing"]
    return _print_experiment(result, f"wall time {timing['total']:.1f} s (runs "
                                     f"{timing['runs']:.1f} s, figures {timing['figures']:.1f} s)")


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
    start (bad options, a DEM or start refused, an unreachable scheduler), is refused and
    leaves no folder it made; Ctrl-C ends the command, naming where the finished runs are
    kept (and removing the folders it made if none is)."""
    folder = NewFolder(out)
    with folder.undone_if_refused():
        with ends_with(REFUSED, ValueError):
            check_out_dir(out)
        try:
            with ends_with(REFUSED, ValueError, RuntimeError):
                return run()
        except KeyboardInterrupt:
            folder.discard()  # its empty folders only
            kept = Path(out) / "runs"
            print(f"interrupted: finished runs are in {kept}" if kept.exists() else
                  "interrupted before any run finished: nothing kept", file=sys.stderr)
            raise


def _print_failed(failed) -> int:
    """One ``FAILED`` line per failed run; the command's status (1 if any failed)."""
    for outcome in failed:
        print(f"FAILED {outcome.run.folder}: {outcome.error}", file=sys.stderr)
    return FAILED if failed else 0


def _run_sweep_and_print(name, base, axes, out, follower, workers, scheduler=None,
                         caption: str | None = None) -> int:
    from swarm.sweep import format_means, run_sweep

    result = _run_grid(lambda: run_sweep(name, base, axes, out, follower=follower,
                                         workers=workers, scheduler=scheduler), out)
    if caption:
        print(caption)
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
                                args.scheduler, compare_caption(runs[0].config, args.follower,
                                                                seeds))


def compare_caption(config: RunConfig, follower: int, seeds: list[int]) -> str:
    """What ``compare``'s table shows: whose metrics, over which seeds, on which setup and
    noise (every noise channel set, or noise-free)."""
    noises = [f"{name.removeprefix('noise_')} σ {getattr(config, name):g} {OPTIONS[name].unit}"
              for name in OPTIONS if name.startswith("noise_") and getattr(config, name)]
    return (f"follower {follower} of {config.followers}, mean over "
            f"{quantity(len(seeds), 'seeds')} ({', '.join(map(str, seeds))}); surface "
            f"{config.surface}, comm period {config.comm_period:g} s, {config.ticks} ticks; "
            + ("noise: " + ", ".join(noises) if noises else "noise-free"))


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
    result = _run_grid(lambda: run_terrain_experiment(args.dem, out, spec, workers=args.workers),
                       out)  # the DEM or a leader start refused there
    return _print_experiment(result, f"wall time {result['wall_time']:.1f} s (runs)")


def cmd_drive_study(args: argparse.Namespace) -> int:
    """``experiment drive [--quick] [--dem PATH --leader-start X,Y,VX,VY]``: the study of
    driving followers (:mod:`swarm.drive_study`)."""
    from tqdm import tqdm

    from swarm.drive_study import DriveStudySpec, quick, run_drive_study

    spec = DriveStudySpec()
    if (args.dem is None) != (args.leader_start is None):
        refuse("experiment drive --dem needs one --leader-start X,Y,VX,VY, and the other way "
               "round")
    if args.dem is not None:
        with ends_with(REFUSED, ValueError):
            spec = DriveStudySpec(dem=args.dem, dem_start=parse_leader_start(args.leader_start))
    spec = quick(spec) if args.quick else spec
    out = args.out or "runs/experiment-drive"
    bar = tqdm(desc="drive study", unit="run", disable=None)  # a bar on a terminal only

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    try:  # the options or the DEM refused: _run_grid's
        result = _run_grid(lambda: run_drive_study(out, spec, workers=args.workers,
                                                   on_run=progress), out)
    finally:
        bar.close()
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


def cmd_agent_config(args: argparse.Namespace) -> int:
    """``agent-config RUN.toml (--id K | --all) [--out PATH]``: the brief of an agent of the
    run (:class:`protocol.config.AgentBrief`), what its process is given instead of the run's
    configuration: to ``--out`` or stdout, or with ``--all`` every agent's into the folder
    ``--out`` as ``<user>.toml``."""
    from swarm.deploy import agent_user
    from swarm.launch import write_briefs

    with ends_with(REFUSED, ValueError):
        config = config_from_file(file_options(args.config), args.config)
        if args.all:
            if args.out is None:
                raise ValueError("--all needs --out DIR (one brief per agent goes there)")
        elif args.id is None:
            raise ValueError("give --id K (0 = the leader) or --all")
        else:
            brief = AgentBrief.of(config, args.id)
    with ends_with(FAILED, OSError):
        if args.all:
            folder = write_briefs(config, Path(args.out))
            print(f"briefs of the leader and {quantity(config.followers, 'followers')}: "
                  f"{folder}/{agent_user(0)}.toml … {agent_user(config.followers)}.toml")
        elif args.out is None:
            sys.stdout.write(brief.text())
        else:
            print(f"brief of the {brief.role}: {brief.write(args.out)}")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    """``export RUN_DIR [--out BAG_DIR] [--force]``: a finished run as a rosbag2/MCAP bag."""
    from swarm.ros2_export import export_run

    with ends_with(REFUSED, ValueError), ends_with(FAILED, OSError):
        bag = export_run(args.run_dir, args.out, force=args.force)
    print(f"bag: {bag}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog=program("swarm", "swarm"),
                                description="Column formation on an unknown surface over Zenoh.")
    p.add_argument("--version", action="version", version=f"{DISTRIBUTION} {version()}")
    sub = p.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run one case [default the paper's type I case]")
    add_run_flags(run)
    layout = run.add_mutually_exclusive_group()
    layout.add_argument("--processes", dest="in_process", action="store_false",
                        help="agents as separate processes [default]")
    layout.add_argument("--in-process", dest="in_process", action="store_true",
                        help="agents as sessions in this process")
    add_results_flags(run)
    run.add_argument("--plot", action="store_true", help="draw the run's figures at the end")
    run.add_argument("--live", action="store_true",
                     help="serve a live view of the run on localhost (kept up until Ctrl-C)")
    add_live_port(run)
    add_ros2_listen_flag(run)
    add_log_level_flag(run)
    run.set_defaults(func=cmd_run, in_process=False)
    add_experiment_parsers(sub)
    compare = sub.add_parser("compare", help="one setup, several estimators and seeds, one table")
    add_run_flags(compare)
    compare.add_argument("--estimators", default="persist,edmd-b,cv,kalman,arx,gp,auto",
                         help="comma-separated: edmd-<letter>, a built-in name, or "
                              "package.module:Name [default %(default)s]")
    compare.add_argument("--seeds", help="comma-separated seeds [default --seed's]")
    compare.add_argument("--follower", type=int, default=1, help="whose metrics [default 1]")
    compare.add_argument("--out", help="output folder [default runs/compare-<run id>]")
    add_grid_flags(compare)
    compare.set_defaults(func=cmd_compare)
    sweep = sub.add_parser("sweep", help="run a grid file (surfaces × estimators × ...)")
    sweep.add_argument("grid", metavar="GRID.toml", help="the grid: [base] options and [axes]")
    sweep.add_argument("--out", help="output folder [default runs/sweep-<name>]")
    add_grid_flags(sweep)
    sweep.set_defaults(func=cmd_sweep)
    dem = sub.add_parser("dem-from-npz", help="write matplotlib's sample DEM (Jacksboro fault, "
                                              "USGS, public domain) as a GeoTIFF")
    dem.add_argument("out", metavar="OUT.tif")
    dem.add_argument("--npz", help="another .npz in the same layout [default the sample]")
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
                      help="refuse a raster of more cells than N (docs/reliability.md) "
                           "[default twice what a run loads]")
    crop.set_defaults(func=cmd_dem_crop)
    plot = sub.add_parser("plot", help="draw one run's figures into RUN_DIR/figures")
    plot.add_argument("run_dir", metavar="RUN_DIR", help="a results folder of `swarm run`")
    plot.add_argument("--force", action="store_true", help="draw the figures anew if they exist")
    plot.set_defaults(func=cmd_plot)
    deploy = sub.add_parser("deploy", help="write a locked-down docker-compose deployment "
                                           "(router rules, credentials, TLS, compose, run.toml)")
    deploy.add_argument("--followers", type=int, required=True, help="number of followers N")
    deploy.add_argument("--out", required=True, help="folder to write (deploy/README.md)")
    deploy.add_argument("--run-id", help="the run id the router's rules admit [default a new "
                                         "one]")
    deploy.add_argument("--start-timeout", type=float, default=60.0,
                        help="how long the world waits for the agents, containers starting "
                             "slowly [default %(default)g s]")
    deploy.add_argument("--agent-timeout", type=float, default=30.0,
                        help="how long an agent may take to settle [default %(default)g s]")
    deploy.add_argument("--ros-domain", type=int, help="the world publishes the run's ROS 2 "
                                                       "topics on this domain, 0-232 [default "
                                                       "no ROS 2; the rules admit domain 0]")
    deploy.add_argument("--force", action="store_true",
                        help="replace the passwords and keys already in OUT/secrets")
    deploy.set_defaults(func=cmd_deploy)
    brief = sub.add_parser("agent-config", help="an agent's brief (what its process is "
                                                 "given) from a run's configuration")
    brief.add_argument("config", metavar="RUN.toml", help="the run's configuration (e.g. the "
                                                          "config.toml of a run)")
    which = brief.add_mutually_exclusive_group()
    which.add_argument("--id", type=int, metavar="K", help="the agent (0 = the leader)")
    which.add_argument("--all", action="store_true", help="every agent's brief, into --out DIR")
    brief.add_argument("--out", metavar="PATH",
                       help="the file to write, or the folder with --all [default stdout]")
    brief.set_defaults(func=cmd_agent_config)
    export = sub.add_parser("export", help="a finished run as a rosbag2 bag (MCAP) for ROS 2 "
                                           "tools (needs the [ros] extra)")
    export.add_argument("run_dir", metavar="RUN_DIR", help="a complete results folder")
    export.add_argument("--out", metavar="BAG_DIR", help="the bag folder [default RUN_DIR/bag]")
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


def add_experiment_parsers(sub) -> None:
    """``experiment paper``, ``experiment terrain`` and ``experiment drive``, each with its own
    page and flags; the terrain study's defaults are :class:`swarm.terrain.TerrainSpec`'s."""
    from swarm.terrain import TerrainSpec

    experiment = sub.add_parser("experiment", help="the paper's experiments, the terrain study, "
                                                   "the study of driving followers")
    studies = experiment.add_subparsers(dest="name", required=True, metavar="NAME")
    pages = {"paper": ("the paper's Section 4: 315 runs, tables, figures and report.md "
                       "(docs/experiments.md)"),
             "terrain": "the study on a real DEM (docs/experiments.md#the-terrain-study)",
             "drive": ("driving followers: control steps × top speed × comm period "
                       "(docs/drive.md)")}
    parsers = {}
    for name, what in pages.items():
        parsers[name] = p = studies.add_parser(name, help=what, description=what)
        p.add_argument("--out", default=None,
                       help=f"output folder D: D/runs, D/tables, D/figures, D/report.md "
                            f"[default runs/experiment-{name}]")
        p.add_argument("--quick", action="store_true", help="a reduced grid to check the pipeline")
        add_grid_flags(p, scheduler=name == "paper")
        p.set_defaults(func=cmd_experiment)
    terrain, spec = parsers["terrain"], TerrainSpec
    terrain.add_argument("--dem", help="the DEM raster (GeoTIFF or ESRI ASCII grid); required")
    terrain.add_argument("--leader-start", metavar="X,Y,VX,VY", action="append",
                         help="a leader start on the DEM (m, m/s); required; repeat it to "
                              "average over several starts")
    for flag, kind, unit, name in (("--spacing", float, " m", "spacing"),
                                   ("--followers", int, "", "followers"),
                                   ("--ticks", int, "", "ticks"),
                                   ("--smoothing", float, " m²", "smoothing")):
        what = {"spacing": "rod length d", "followers": "column length",
                "ticks": "ticks per run", "smoothing": "the DEM spline's smoothing s"}[name]
        terrain.add_argument(flag, type=kind,
                             help=f"{what} [default {getattr(spec, name):g}{unit}]")
    terrain.add_argument("--estimators", metavar="NAMES",
                         help=f"comma-separated [default {','.join(spec.estimators)}]")
    terrain.add_argument("--comm-periods", metavar="TCS", help="comma-separated, in s [default "
                         f"{','.join(f'{t:g}' for t in spec.comm_periods)}]")
    drive = parsers["drive"]
    drive.add_argument("--dem", help="the DEM raster of the study's terrain case, with "
                                     "--leader-start [default the test DEM]")
    drive.add_argument("--leader-start", metavar="X,Y,VX,VY",
                       help="the leader start on --dem (m, m/s)")


def add_grid_flags(parser: argparse.ArgumentParser, scheduler: bool = True) -> None:
    """``--workers`` and (where the command can use one) ``--scheduler``: where a grid of runs
    executes (swarm.grid.run_grid)."""
    parser.add_argument("--workers", type=int, default=None,
                        help="runs in parallel [default min(2, CPU count)]")
    if scheduler:
        parser.add_argument("--scheduler", metavar="ADDRESS", default=None,
                            help="address of a dask scheduler (tcp://host:8786): each run is "
                                 "one task on its workers; finished runs in --out are not run "
                                 "again [default a local process pool]")


def add_live_port(parser: argparse.ArgumentParser) -> None:
    from swarm.live import DEFAULT_PORT

    parser.add_argument("--live-port", type=int, default=DEFAULT_PORT,
                        help=f"port of the page on 127.0.0.1, 0 = any free [default "
                             f"{DEFAULT_PORT}]")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_command(lambda: args.func(args))


def console() -> None:
    """The installed script's entry: :func:`main`, then :func:`protocol.cli.exit_process`."""
    exit_process(main())
