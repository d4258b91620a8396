"""``python -m swarm``: run one case (``run``), and more subcommands as they come (SPEC §9)."""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from protocol.cli import (
    EXPECTED_FAILURES, add_log_level_flag, bounded_interrupt, check_out_dir, describe,
    setup_logging,
)
from protocol.config import (DICTIONARIES, ESTIMATORS, MODES, MOTIONS, SIDES, VELOCITY_VARIANTS,
                             RunConfig, config_from_dict, config_from_file, read_toml)
from protocol.session import add_credential_flags

EXIT_NOTHING_ESTIMATED = 3
"""``swarm run``'s status for a run that completed but in which a follower missed every tick
or estimated none."""

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
    "--estimator": ("estimator", {"help": ", ".join(ESTIMATORS) + ", or your own "
                                          "package.module:Name (SPEC §6)"}),
    "--dictionary": ("dictionary", {"choices": DICTIONARIES}),
    "--velocity": ("velocity", {"choices": VELOCITY_VARIANTS}),
    "--online": ("online", {"action": "store_const", "const": True}),
    "--delays": ("delays", {"type": int}),
    "--affine": ("affine", {"action": "store_const", "const": True}),
    "--forget": ("forget", {"type": float}),
    "--window": ("window", {"type": int, "help": "sliding window of pairs (0 = all)"}),
    "--ridge": ("ridge", {"type": float}),
    "--arx-order": ("arx_order", {"type": int, "help": "arx: past (x, u) pairs per regressor"}),
    "--arx-window": ("arx_window", {"type": int, "help": "arx: pairs fitted (0 = all)"}),
    "--gp-samples": ("gp_samples", {"type": int, "help": "gp: relative positions fitted"}),
    "--kalman-accel": ("kalman_accel", {"type": float,
                                        "help": "kalman: process noise (length²/tick⁴)"}),
    "--gps": ("gps", {"action": "store_const", "const": True}),
    "--noise-range": ("noise_range", {"type": float}),
    "--noise-bearing": ("noise_bearing", {"type": float}),
    "--noise-velocity": ("noise_velocity", {"type": float}),
    "--noise-move": ("noise_move", {"type": float}),
    "--noise-gps": ("noise_gps", {"type": float, "help": "GPS noise σ per coordinate (m)"}),
    "--side": ("side", {"choices": tuple(SIDES)}),
    "--leader-start": ("leader_start", {"metavar": "X,Y,VX,VY"}),
    "--seed": ("seed", {"type": int}),
    "--sensing-range": ("sensing_range", {"type": float, "help": "R_s (inf = unlimited)"}),
    "--mode": ("mode", {"choices": MODES}),
    "--unpipelined": ("pipelined", {"action": "store_const", "const": False,
                                    "help": "lockstep one agent at a time (for comparison; "
                                            "default: pipelined, SPEC §4)"}),
    "--time-scale": ("time_scale", {"type": float}),
    "--agent-timeout": ("agent_timeout", {"type": float}),
    "--run-id": ("run_id", {}),
    # --motion drive (SPEC §4, docs/drive.md)
    "--motion": ("motion", {"choices": MOTIONS,
                            "help": "teleport (default: a move relocates) or drive (bounded "
                                    "unicycle robots on the surface)"}),
    "--max-speed": ("max_speed", {"type": float, "help": "drive: top speed, m of arc per time "
                                                         "unit (default 2× the leader's; inf)"}),
    "--max-turn": ("max_turn", {"type": float, "help": "drive: top turn rate, rad per time unit "
                                                       "(default 2; inf)"}),
    "--control-steps": ("control_steps", {"type": int, "help": "drive: control steps per comm "
                                                               "interval (default 8)"}),
    "--snap-steps": ("snap_steps", {"type": int, "help": "drive: control steps of the "
                                                         "correction window (default 4)"}),
    "--noise-speed": ("noise_speed", {"type": float, "help": "drive: σ of the speed per step"}),
    "--noise-turn": ("noise_turn", {"type": float, "help": "drive: σ of the turn rate per step"}),
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

    # the file is read once, under the input limits; a run id is made unless it names one
    file_data = read_toml(Path(args.config), "config file") if args.config else {}
    base = (config_from_file(file_data, args.config) if args.config
            else RunConfig(run_id=new_run_id()))
    data = base.to_dict()
    for dest, _ in RUN_FLAGS.values():
        value = getattr(args, dest)
        if value is not None:
            data[dest] = value
    if isinstance(data.get("leader_start"), str):
        data["leader_start"] = parse_leader_start(data["leader_start"])
    if args.smoothing is not None:
        data["surface_params"] = {**data.get("surface_params", {}), "smoothing": args.smoothing}
    if args.config and args.run_id is None and "run_id" not in file_data:
        data["run_id"] = new_run_id()
    return config_from_dict(data)


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
    counterfactual) and what ``auto`` followed."""
    from swarm.grid import table_number  # not at start-up: grid brings the process pool

    label = "required (" + summary["estimator"] + ")"
    width = max(20, len(label))
    head = (f"{'follower':>8}  {label:>{width}}  {'rmse':>8}  {'stay':>8}  {'persist':>8}  "
            f"{'/persist':>8}  {'persist*':>8}  {'lost':>4}  {'missed':>6}  {'fallback':>8}")
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
                     f"{s.get('fallback_ticks', 0):>8}")
        followed = s.get("followed") or {}
        if len(followed) > 1:
            shares.append(f"follower {k} followed " + ", ".join(
                f"{name} {share:.0%}" for name, share in followed.items()))
    lines.append("persist: from the same (noisy) readings; persist*: its noise-free "
                 "counterfactual; /persist: required over persist")
    if summary.get("motion") == "drive":
        lines += [f"follower {k} drove {s['path_length']:.4g} m: reach error "
                  f"{table_number(s['mean_reach_error'])}, snap error "
                  f"{table_number(s['mean_snap_error'])}, formation error "
                  f"{table_number(s['mean_formation_error'])}, {s['saturated_steps']} steps "
                  "at a limit" for k, s in summary["followers"].items()]
    lines += shares
    state = "complete" if summary["complete"] else f"INCOMPLETE: {summary['reason']}"
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
    try:
        config = config_from_args(args)
    except ValueError as exc:
        print(f"error: {describe(exc)}", file=sys.stderr)
        return 2
    live = endpoint = None
    if args.live:  # its arguments are checked before anything is written
        from protocol.session import free_tcp_endpoint
        from swarm.live.observer import LiveView

        try:
            live = LiveView(port=args.live_port, run_id=config.run_id)
        except (ValueError, RuntimeError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
        endpoint = free_tcp_endpoint()
    try:
        out = Path(args.out) if args.out else Path("runs") / config.run_id
        if (out / "summary.json").exists():
            raise ValueError(f"{out} already holds a run's results; choose another --out "
                             "(nothing was overwritten)")
        check_out_dir(out)
    except ValueError as exc:
        print(f"error: {describe(exc)}", file=sys.stderr)
        return 2
    try:
        if live is not None:
            try:
                print(f"live view: {live.start()}", flush=True)
            except RuntimeError as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 1
        return _run_and_report(args, config, out, live, endpoint)
    finally:
        if live is not None:
            live.close()


def _run_and_report(args: argparse.Namespace, config: RunConfig, out: Path, live, endpoint) -> int:
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
        summary = launch(config, out, in_process=args.in_process, on_tick=lambda j: bar.update(1),
                         endpoint=endpoint,
                         before_agents=None if live is None else observe)
    except OSError as exc:  # the results disk failed during the run (read-only, full)
        bar.close()
        print(f"error: cannot write the results in {out}: {describe(exc)}", file=sys.stderr)
        return 1
    except EXPECTED_FAILURES as exc:
        bar.close()
        print(f"error: {describe(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        bar.close()
        print(f"interrupted: partial result in {out}", file=sys.stderr)
        return 130
    bar.close()
    print(format_summary(summary))
    print(f"results: {out}", flush=True)
    if args.plot:
        from swarm.plots import plot_run

        for path in plot_run(out):
            print(f"figure: {path}")
    empty = empty_followers(summary, config.init_ticks)
    for line in empty:
        print(f"warning: {line}", file=sys.stderr)
    if live is not None:
        print(f"live view still at {live.server.url} (Ctrl-C to quit)", flush=True)
        live.serve_until_interrupted()
    if not summary["complete"]:
        return 1
    return EXIT_NOTHING_ESTIMATED if empty else 0


def cmd_watch(args: argparse.Namespace) -> int:
    """``watch``: the live view of a run assembled elsewhere, as a read-only observer."""
    from protocol.session import credentials, zenoh_config
    from swarm.live.observer import LiveView

    try:
        user, password = credentials(args)
        conf = zenoh_config(args.mode, connect=args.connect, user=user, password=password,
                            extra=args.cfg)
        live = LiveView(port=args.live_port, run_id=args.run_id)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return _serve(live, conf)


def cmd_replay(args: argparse.Namespace) -> int:
    """``replay RUN_DIR``: the same page for a finished run, with a tick slider."""
    from swarm.live.observer import LiveView
    from swarm.live.store import load_run

    try:
        live = LiveView(port=args.live_port, store=load_run(args.run_dir), replay=True)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return _serve(live, None)


def _serve(live, conf) -> int:
    """Serve ``live`` (connected with ``conf`` unless None) until Ctrl-C."""
    try:
        print(f"live view: {live.start()} (Ctrl-C to quit)", flush=True)
        if conf is not None:  # the page waits for the world meanwhile
            live.connect(conf)
        live.serve_until_interrupted()
    except RuntimeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    finally:
        live.close()
    return 0


def cmd_experiment(args: argparse.Namespace) -> int:
    """``experiment paper``: the paper's Section 4 grid, tables, figures and report;
    ``experiment terrain --dem PATH``: the terrain study (:mod:`swarm.terrain`)."""
    from swarm.experiment import FULL, QUICK, run_paper_experiment

    try:
        _check_workers(args.workers)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.name == "terrain":
        return cmd_terrain(args)
    if args.name == "drive":
        return cmd_drive_study(args)
    if args.dem is not None:
        print("error: --dem applies only to `experiment terrain`", file=sys.stderr)
        return 2
    args.out = args.out or "runs/experiment-paper"
    result, status = _run_grid(lambda: run_paper_experiment(
        args.out, QUICK if args.quick else FULL, workers=args.workers, scheduler=args.scheduler),
        args.out)
    if result is None:
        return status
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


def _run_grid(run, out) -> tuple[dict | None, int]:
    """``run()``'s result and 0; or None and the status that ends the command: 2 after a
    one-line error (an output folder that cannot hold results is one, found before any run),
    130 on Ctrl-C (naming where the finished runs are kept)."""
    try:
        check_out_dir(out)
    except ValueError as exc:
        print(f"error: {describe(exc)}", file=sys.stderr)
        return None, 2
    try:
        return run(), 0
    except RuntimeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None, 2
    except KeyboardInterrupt:
        print(f"interrupted: finished runs are in {Path(out) / 'runs'}", file=sys.stderr)
        return None, 130


def _print_failed(failed) -> int:
    """One ``FAILED`` line per failed run; the command's status (1 if any failed)."""
    for outcome in failed:
        print(f"FAILED {outcome.run.folder}: {outcome.error}", file=sys.stderr)
    return 1 if failed else 0


def _run_sweep_and_print(name, base, axes, out, follower, workers, scheduler=None) -> int:
    from swarm.sweep import format_means, run_sweep

    result, status = _run_grid(lambda: run_sweep(name, base, axes, out, follower=follower,
                                                 workers=workers, scheduler=scheduler), out)
    if result is None:
        return status
    print(format_means(result["means"], result["keys"]))
    for path in result["tables"].values():
        print(f"table: {path}")
    return _print_failed([o for o in result["outcomes"] if not o.ok])


def _check_workers(workers: int | None) -> None:
    if workers is not None and workers < 1:
        raise ValueError(f"--workers must be at least 1, got {workers}")


def cmd_compare(args: argparse.Namespace) -> int:
    """``compare``: one setup (``run``'s flags), several estimators and seeds, one table."""
    from swarm.sweep import compare_axes

    try:
        _check_workers(args.workers)
        base = config_from_args(args)
        try:
            seeds = [int(x) for x in args.seeds.split(",")] if args.seeds else [base.seed]
        except ValueError:
            raise ValueError(f"--seeds must be comma-separated integers, got {args.seeds!r}") from None
        axes = compare_axes([e for e in args.estimators.split(",") if e], seeds)
        if not 1 <= args.follower <= base.followers:
            raise ValueError(f"--follower must be in 1..{base.followers}, got {args.follower}")
        from swarm.grid import expand

        expand("compare", base, axes)  # every combination must be valid before anything runs
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else Path("runs") / f"compare-{base.run_id}"
    return _run_sweep_and_print("compare", base, axes, out, args.follower, args.workers,
                                args.scheduler)


def cmd_sweep(args: argparse.Namespace) -> int:
    """``sweep GRID.toml``: any grid of options, one table (``experiment paper`` is one)."""
    from swarm.sweep import load_grid

    try:
        _check_workers(args.workers)
        name, base, axes, follower = load_grid(args.grid)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else Path("runs") / f"sweep-{name}"
    return _run_sweep_and_print(name, base, axes, out, follower, args.workers, args.scheduler)
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
        out = args.out or "runs/experiment-terrain"
        result, status = _run_grid(lambda: run_terrain_experiment(args.dem, out, spec,
                                                                  workers=args.workers), out)
    except ValueError as exc:  # the options, the DEM or a leader start
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if result is None:
        return status
    return _print_experiment(result, f"wall time {result['wall_time']:.1f} s (runs)")


def cmd_drive_study(args: argparse.Namespace) -> int:
    """``experiment drive [--quick] [--dem PATH --leader-start X,Y,VX,VY]``: the study of
    driving followers (:mod:`swarm.drive_study`)."""
    from swarm.drive_study import DriveStudySpec, quick, run_drive_study

    spec = DriveStudySpec()
    if args.dem is not None:
        if not args.leader_start or len(args.leader_start) != 1:
            print("error: experiment drive --dem needs one --leader-start X,Y,VX,VY",
                  file=sys.stderr)
            return 2
        try:
            spec = DriveStudySpec(dem=args.dem, dem_start=parse_leader_start(args.leader_start[0]))
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    spec = quick(spec) if args.quick else spec
    out = args.out or "runs/experiment-drive"
    result, status = _run_grid(lambda: run_drive_study(
        out, spec, workers=args.workers,
        on_run=lambda done, total: print(f"\rrun {done}/{total}", end="", file=sys.stderr,
                                         flush=True)), out)
    print(file=sys.stderr)
    if result is None:
        return status
    return _print_experiment({**result, "figure_problems": {}, "failed": []},
                             f"wall time {result['wall_time']:.1f} s ({result['runs']} runs in "
                             f"{result['runs_time']:.1f} s)")


def cmd_dem_crop(args: argparse.Namespace) -> int:
    """``dem-crop IN OUT.tif [--bounds XMIN,YMIN,XMAX,YMAX]``: a rectangle of a DEM with data
    at every node."""
    from swarm.terrain import crop_dem

    try:
        crop = crop_dem(args.source, args.out, args.bounds, force=args.force)
    except (ValueError, OSError) as exc:
        print(f"error: {describe(exc)}", file=sys.stderr)
        return 2
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


def cmd_deploy(args: argparse.Namespace) -> int:
    """``deploy``: write a locked-down docker-compose deployment of one run into ``--out``."""
    from swarm.deploy import write_deployment
    from swarm.launch import new_run_id

    try:
        config = RunConfig(run_id=args.run_id or new_run_id(), followers=args.followers,
                           start_timeout=args.start_timeout, agent_timeout=args.agent_timeout)
        written = write_deployment(args.out, config, force=args.force)
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"deployment of run {config.run_id} ({config.followers} followers): "
          f"{len(written)} files in {args.out}; secrets in {Path(args.out) / 'secrets'} "
          "(keep them out of version control)")
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
    run.add_argument("--live", action="store_true",
                     help="serve a live view of the run on localhost (kept up until Ctrl-C)")
    add_live_port(run)
    add_log_level_flag(run)
    run.set_defaults(func=cmd_run, in_process=False)
    experiment = sub.add_parser("experiment", help="regenerate the paper's tables, figures and report")
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
    dem.set_defaults(func=cmd_dem_from_npz)
    crop = sub.add_parser("dem-crop", help="keep a rectangle of a DEM without no-data nodes "
                                           "(by default the largest) as a GeoTIFF")
    crop.add_argument("source", metavar="IN", help="a DEM raster (GeoTIFF, .asc, ...)")
    crop.add_argument("out", metavar="OUT.tif")
    crop.add_argument("--bounds", type=_bounds, metavar="XMIN,YMIN,XMAX,YMAX",
                      help="keep these nodes instead (m, in IN's frame: origin at its "
                           "south-west node)")
    crop.add_argument("--force", action="store_true", help="replace OUT if it exists")
    crop.set_defaults(func=cmd_dem_crop)
    plot = sub.add_parser("plot", help="draw one run's figures into RUN_DIR/figures")
    plot.add_argument("run_dir", metavar="RUN_DIR", help="a results folder of `swarm run`")
    plot.set_defaults(func=cmd_plot)
    deploy = sub.add_parser("deploy", help="write a locked-down docker-compose deployment "
                                           "(router rules, credentials, TLS, compose, run.toml)")
    deploy.add_argument("--followers", type=int, required=True, help="number of followers N")
    deploy.add_argument("--out", required=True, help="folder to write (deploy/README.md)")
    deploy.add_argument("--run-id", help="the run id the router's rules admit (default: new)")
    deploy.add_argument("--start-timeout", type=float, default=60.0,
                        help="seconds the world waits for the agents (containers start slowly)")
    deploy.add_argument("--agent-timeout", type=float, default=30.0)
    deploy.add_argument("--force", action="store_true",
                        help="replace the passwords and keys already in OUT/secrets")
    deploy.set_defaults(func=cmd_deploy)
    watch = sub.add_parser("watch", help="live view of a running run, as a read-only observer")
    watch.add_argument("--connect", action="append", required=True, metavar="ENDPOINT",
                       help="Zenoh router (or peer) to connect to, e.g. tcp/127.0.0.1:7447")
    watch.add_argument("--run-id", required=True, help="the run to watch")
    watch.add_argument("--mode", choices=("client", "peer"), default="client")
    add_credential_flags(watch)
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
    with bounded_interrupt():
        return args.func(args)
