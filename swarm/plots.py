"""Figures (PNG) of one run (:func:`plot_run`) and of the paper experiment's tables.

Figures use matplotlib's object API on an Agg canvas: no pyplot, no display, no global
backend switch. Every PNG is written atomically (temporary file, then rename), like the rest
of a results folder. Lengths are in metres and times in seconds, on every surface
(:data:`protocol.config.LENGTH`, :data:`protocol.config.TIME`).

Table figures take the rows of a table as read back by :func:`swarm.grid.read_table`
(dicts; missing numbers are NaN), so they draw exactly what the tables hold.
"""
from __future__ import annotations

import io
import json
import math
import textwrap
from collections.abc import Callable, Sequence
from functools import wraps
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import LightSource
from matplotlib.figure import Figure
from matplotlib.ticker import NullLocator

from protocol.config import LENGTH as LENGTH_UNIT
from protocol.config import SPEED as SPEED_UNIT
from protocol.config import TIME as TIME_UNIT
from protocol.config import RunConfig, load_config
from protocol.folder import write_atomic
from protocol.record import CONTROLS_FILE, SUMMARY_FILE, TICKS_FILE, read_controls, read_ticks
from protocol.view import widen_to_aspect
from world import geometry, motion
from world.dem import DemSurface
from world.surfaces import Surface, make_surface
from world.view import height_grid

DPI = 110
STYLE = {"font.size": 12, "axes.titlesize": 13, "axes.labelsize": 12, "legend.fontsize": 11,
         "xtick.labelsize": 11, "ytick.labelsize": 11, "axes.grid": True, "grid.alpha": 0.3}
PANEL_WIDTH = 4.3  # inches per surface panel; three panels stay readable at README width
IDEAL_COLOR, ESTIMATE_COLOR = "tab:red", "tab:blue"
SURFACE_TITLES = {"elliptic": "elliptic, type I", "hyperbolic": "hyperbolic, type II",
                  "wavy": "wavy, type III"}
# estimator -> (colour, marker); the paper draws "without estimation" red and EDMD blue.
ESTIMATOR_STYLE = {"stay": ("tab:red", "o"), "persist": ("tab:gray", "s"),
                   "edmd-b": ("tab:blue", "^"), "auto": ("tab:green", "D"),
                   "auto-mix": ("darkgreen", "d"), "cv": ("tab:olive", "v"),
                   "kalman": ("tab:purple", "P"), "arx": ("tab:brown", "X"),
                   "gp": ("tab:orange", "*"), "gp-motion": ("tab:pink", "<"),
                   "gp-ratio": ("tab:cyan", ">")}
# any other estimator (an edmd variant, your own): these, in the order they first appear
OTHER_STYLES = [("black", "."), ("tab:blue", "1"), ("tab:red", "2"), ("tab:green", "3"),
                ("tab:purple", "4"), ("tab:brown", "+"), ("tab:olive", "x")]


def estimator_styles(estimators: list[str]) -> dict[str, tuple[str, str]]:
    """(colour, marker) per estimator: the fixed ones above, then a distinct one for each
    other estimator (cycling only past 7 of them)."""
    others = [e for e in estimators if e not in ESTIMATOR_STYLE]
    return {e: ESTIMATOR_STYLE.get(e) or OTHER_STYLES[others.index(e) % len(OTHER_STYLES)]
            for e in estimators}
DICTIONARY_LABELS = {"a": "a\nv", "b": "b\n(r, θ)", "c": "c\n(r, θ, v)", "d": "d\nxy",
                     "e": "e\nxyz", "f": "f\nxy, leader xy", "g": "g\nxyz, leader xyz"}
# variant -> (face colour, hatch); the paper: no hatch, white lines, white crosses.
VARIANT_STYLE = {"b": ("tab:blue", ""), "c-lagged": ("tab:blue", "//"),
                 "c-estimated": ("tab:blue", "xx"), "persist": ("tab:gray", ""),
                 "stay": ("tab:red", "")}
PAPER_COMM_PERIOD = RunConfig().comm_period  # the paper's T_c, the run default
RANGE_LABEL = "mean required sensing range"
LENGTH = f"({LENGTH_UNIT})"  # an axis label's unit


def _styled(func: Callable) -> Callable:
    """Draw under the module's rcParams (font sizes, grid) without changing the caller's."""

    @wraps(func)
    def wrapper(*args, **kwargs):
        with matplotlib.rc_context(STYLE):
            return func(*args, **kwargs)

    return wrapper


def _log_y(ax) -> bool:
    """Log-scale the y axis if it holds positive data; return whether it did (panels of
    failed runs hold only NaN and stay linear instead of failing to draw)."""
    high = ax.dataLim.intervaly[1]
    if np.isfinite(high) and high > 0:
        ax.set_yscale("log")
        return True
    return False


MAX_LEGEND_COLUMNS = 6


def _figure_legend(fig: Figure) -> None:
    """Every panel's labelled artists in one legend below the panels ("outside lower
    center": the constrained layout reserves its height, and the legend covers no data), in
    as many columns (at most :data:`MAX_LEGEND_COLUMNS`) as fit in the figure's width; none
    if nothing is labelled."""
    if not any(ax.get_legend_handles_labels()[0] for ax in fig.axes):
        return
    renderer = fig.canvas.get_renderer()
    for ncol in range(MAX_LEGEND_COLUMNS, 0, -1):
        legend = fig.legend(loc="outside lower center", ncol=ncol)
        if ncol == 1 or legend.get_window_extent(renderer).width <= fig.bbox.width:
            return
        legend.remove()


def _legend_below(ax, **kwargs) -> None:
    """``ax``'s legend under its x axis (the constrained layout makes room for it), where it
    covers no data."""
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), **kwargs)


def _suptitle(fig: Figure, text: str) -> None:
    """``fig``'s title, wrapped onto more lines where one would be wider than the figure."""
    title = fig.suptitle(text)
    width = title.get_window_extent(fig.canvas.get_renderer()).width
    if width > 0.95 * fig.bbox.width:
        title.set_text(textwrap.fill(text, max(20, int(len(text) * 0.9 * fig.bbox.width
                                                       / width))))


def _figure(width: float, height: float, layout: str = "constrained") -> Figure:
    """A figure on an Agg canvas; ``layout="compressed"`` for one whose panels have a fixed
    aspect (equal axes), which the constrained layout places with labels cut off."""
    fig = Figure(figsize=(width, height), dpi=DPI, layout=layout)
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: str | Path) -> Path:
    """Write ``fig`` as PNG atomically, never through a symbolic link
    (:func:`protocol.folder.write_atomic`)."""
    path = Path(path)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    write_atomic(path, buf.getvalue(), mode=0o644)
    return path


# --- one run -----------------------------------------------------------------------------------

def leader_relative(rows: list[dict], follower: int) -> dict[str, np.ndarray]:
    """Relative position of follower ``follower``'s leader (agent ``follower - 1``) per tick.

    Seen from the ideal position (what the follower measures once it has snapped) and from the
    estimated position (what its estimate predicted it would measure), in the local frame of
    design §5.

    Parameters
    ----------
    rows : list of dict
        ``ticks.csv`` rows (:func:`protocol.record.read_ticks`).
    follower : int
        Follower id k >= 1.

    Returns
    -------
    dict of str to ndarray, each of shape (n,)
        ``tick``; ``r_ideal``, ``theta_ideal`` (leader minus ideal position: length, bearing in
        radians, unwrapped); ``r_est``, ``theta_est`` (leader minus estimate, bearing on the
        ideal's branch; NaN before estimation starts).
    """
    if follower < 1:
        raise ValueError(f"follower must be >= 1, got {follower}")
    leader = {r["tick"]: (r["pos_x"], r["pos_y"]) for r in rows if r["agent"] == follower - 1}
    mine = sorted((r for r in rows if r["agent"] == follower and r["tick"] in leader),
                  key=lambda r: r["tick"])
    if not mine:
        raise ValueError(f"ticks hold no row of follower {follower} with its leader")
    nan = math.nan
    ticks = np.array([r["tick"] for r in mine])
    lead = np.array([leader[r["tick"]] for r in mine])
    ideal = np.array([(r["ideal_x"], r["ideal_y"]) for r in mine])
    est = np.array([(r["est_x"] if r["est_x"] is not None else nan,
                     r["est_y"] if r["est_y"] is not None else nan) for r in mine])
    to_ideal, to_est = lead - ideal, lead - est
    theta_ideal = np.unwrap(np.arctan2(to_ideal[:, 1], to_ideal[:, 0]))
    theta_est = np.arctan2(to_est[:, 1], to_est[:, 0])
    theta_est = theta_ideal + np.remainder(theta_est - theta_ideal + np.pi, 2 * np.pi) - np.pi
    return {"tick": ticks, "r_ideal": np.hypot(*to_ideal.T), "theta_ideal": theta_ideal,
            "r_est": np.hypot(*to_est.T), "theta_est": theta_est}


def _surface_contours(ax, surface, low: np.ndarray, high: np.ndarray):
    """Contour lines of ``surface`` over the box ``low``..``high`` (NaN outside its domain);
    over a DEM, on its hillshaded relief (:func:`terrain_relief`)."""
    if isinstance(surface, DemSurface):
        return terrain_relief(ax, surface, low, high)[1]
    xs, ys = np.linspace(low[0], high[0], 160), np.linspace(low[1], high[1], 100)
    z = height_grid(surface, low, high, (ys.size, xs.size))
    return ax.contour(xs, ys, z, levels=14, cmap="viridis", linewidths=0.8, alpha=0.8)


def terrain_relief(ax, dem: DemSurface, low: np.ndarray, high: np.ndarray,
                   samples: int = 400):
    """Hillshade (matplotlib ``LightSource``, sun from the north-west at 45°) and contour
    lines of a DEM's spline over the part of the box ``low``..``high`` inside the grid.

    Returns the hillshade image and the contour set.
    """
    x0, x1, y0, y1 = dem.bounds
    left, right = max(low[0], x0), min(high[0], x1)
    bottom, top = max(low[1], y0), min(high[1], y1)
    if not (left < right and bottom < top):
        raise ValueError(f"the box {tuple(low)}–{tuple(high)} does not meet the DEM grid")
    scale = samples / max(right - left, top - bottom)
    xs = np.linspace(left, right, max(8, round((right - left) * scale)))
    ys = np.linspace(bottom, top, max(8, round((top - bottom) * scale)))
    z = dem.spline(ys, xs)  # (len(ys), len(xs)), row j at ys[j]
    relief = np.ptp(z) or 1.0
    # Exaggerate gentle relief so it reads at this scale (an exaggeration, not data).
    exaggeration = max(1.0, 0.05 * max(right - left, top - bottom) / relief)
    shade = LightSource(azdeg=315, altdeg=45).hillshade(
        z, vert_exag=exaggeration, dx=xs[1] - xs[0], dy=ys[1] - ys[0])
    image = ax.imshow(shade, cmap="gray", origin="lower", extent=(left, right, bottom, top),
                      vmin=0, vmax=1, alpha=0.75, interpolation="bilinear")
    contours = ax.contour(xs, ys, z, levels=14, cmap="viridis", linewidths=0.8, alpha=0.9)
    return image, contours


def _terrain_map(fig, ax, rows: list[dict], config: RunConfig, surface: Surface,
                 aspect: float) -> tuple[str, list]:
    """Draw a run's terrain under ``ax`` (contour lines or a DEM's relief, with its colour
    bar), fitted to every settled and ideal position at ``aspect`` and equal axes, and the
    leader's path; return the leader's rows."""
    positions = np.array([(r[f"{c}_x"], r[f"{c}_y"]) for r in rows for c in ("pos", "ideal")
                          if r.get(f"{c}_x") is not None])
    low, high = widen_to_aspect(np.nanmin(positions, axis=0) - config.spacing,
                                np.nanmax(positions, axis=0) + config.spacing, aspect)
    contours = _surface_contours(ax, surface, low, high)
    fig.colorbar(contours, ax=ax, shrink=0.9, pad=0.01, label=f"height z {LENGTH}")
    lead = sorted((r for r in rows if r["agent"] == 0), key=lambda r: r["tick"])
    ax.plot([r["pos_x"] for r in lead], [r["pos_y"] for r in lead], "k.-", lw=1, ms=4,
            label="leader")
    ax.set(xlim=(low[0], high[0]), ylim=(low[1], high[1]), aspect="equal")
    return lead


def _run_record(run_dir: Path) -> tuple[list[dict], RunConfig]:
    """``run_dir``'s ``ticks.csv`` rows and configuration."""
    return read_ticks(run_dir / TICKS_FILE), load_config(run_dir / "config.toml")


def _run_surface(config: RunConfig) -> Surface:
    """The run's surface (built once per :func:`plot_run`: a DEM's means a spline fit)."""
    return make_surface(config.surface, config.surface_params)


def plot_effectiveness(run_dir: str | Path, path: str | Path,
                       followers: Sequence[int] | None = None, title: str | None = None) -> Path:
    """The paper's effectiveness figure for one run.

    Top: the leader's path and every follower's ideal (red) and estimated (blue) positions
    over the surface's contour lines. Below, one column per follower in ``followers``
    (default the first three): distance and bearing of its leader seen from the ideal position
    (red) and from the estimate (blue), per tick.
    """
    rows, config = _run_record(Path(run_dir))
    return _draw_effectiveness(rows, config, _run_surface(config), path, followers, title)


@_styled
def _draw_effectiveness(rows: list[dict], config: RunConfig, surface: Surface, path: str | Path,
                        followers: Sequence[int] | None = None,
                        title: str | None = None) -> Path:
    """:func:`plot_effectiveness`'s figure, from the run's record already read."""
    followers = list(followers or range(1, min(config.followers, 3) + 1))
    width = 13.0
    fig = _figure(width, 10.0)
    grid = fig.add_gridspec(3, len(followers), height_ratios=(1.6, 1, 1))
    ax = fig.add_subplot(grid[0, :])
    lead = _terrain_map(fig, ax, rows, config, surface, aspect=3.3)
    ax.plot(lead[0]["pos_x"], lead[0]["pos_y"], "ks", mfc="none", ms=10, label="leader at tick 0")
    for k in range(1, config.followers + 1):
        mine = sorted((r for r in rows if r["agent"] == k), key=lambda r: r["tick"])
        ax.plot([r["ideal_x"] for r in mine], [r["ideal_y"] for r in mine], "o-",
                color=IDEAL_COLOR, lw=0.6, ms=3.5, label="ideal" if k == 1 else None)
        est = [r for r in mine if r["est_x"] is not None]
        ax.plot([r["est_x"] for r in est], [r["est_y"] for r in est], "x", color=ESTIMATE_COLOR,
                ms=5, mew=1.2, label="estimated" if k == 1 else None)
    ax.set(xlabel=f"x {LENGTH}", ylabel=f"y {LENGTH}",
           title=f"leader and {config.followers} follower(s) over the "
                 f"{'hillshaded relief' if isinstance(surface, DemSurface) else 'contour lines'}, "
                 f"estimator {_estimator_label(config)}")
    for col, k in enumerate(followers):
        rel = leader_relative(rows, k)
        for row, (ideal, est, label, scale) in enumerate((
                ("r_ideal", "r_est", f"distance {LENGTH}", 1.0),
                ("theta_ideal", "theta_est", "bearing (deg)", 180 / math.pi)), start=1):
            sub = fig.add_subplot(grid[row, col])
            first = row == 1 and col == 0  # labels its curves, once, for the figure's legend
            sub.plot(rel["tick"], rel[ideal] * scale, "o-", color=IDEAL_COLOR, ms=3, lw=1,
                     label="leader seen from the ideal position (measured)" if first else None)
            sub.plot(rel["tick"], rel[est] * scale, "x--", color=ESTIMATE_COLOR, ms=4, lw=1,
                     label="from the estimate (predicted)" if first else None)
            sub.axvline(config.init_ticks - 0.5, color="0.5", ls=":", lw=1,
                        label="estimation starts" if first else None)
            sub.ticklabel_format(axis="y", useOffset=False)
            sub.set(title=f"follower {k}: leader's {label.split()[0]}")
            if col == 0:
                sub.set_ylabel(label)
            if row == 2:
                sub.set_xlabel("tick j (t = j·T_c)")
    _figure_legend(fig)
    _suptitle(fig, title or f"{config.surface}: trajectory estimation, T_c = "
                            f"{config.comm_period:g} {TIME_UNIT}")
    return _save(fig, path)


@_styled
def _draw_required_range(rows: list[dict], config: RunConfig, summary: dict,
                         path: str | Path) -> Path:
    """Required sensing range of one run: per-follower means against the two baselines
    (markers, from ``summary.json``) and per tick (lines, from ``ticks.csv``); each panel's
    legend below it, off the data."""
    fig = _figure(12.0, 5.6)
    means, lines = fig.subplots(1, 2, width_ratios=(1, 1.4))
    followers = sorted(summary["followers"], key=int)
    x = np.arange(len(followers))
    series = ((f"{_estimator_label(config)} (this run)", "mean_required_range", ESTIMATE_COLOR,
               ESTIMATOR_STYLE["edmd-b"][1]),
              ("stay (counterfactual)", "mean_stay_range", *ESTIMATOR_STYLE["stay"]),
              ("persist (counterfactual)", "mean_persist_range", *ESTIMATOR_STYLE["persist"]))
    for i, (label, key, color, marker) in enumerate(series):
        values = [_nan(summary["followers"][k][key]) for k in followers]
        _dots(means, x + (i - 1) * 0.15, values, color, marker, label=label)
    means.set_xticks(x, [f"F{k}" for k in followers])
    means.set_xlim(-0.5, len(followers) - 0.5)
    _log_y(means)
    means.set(xlabel="follower", ylabel=f"{RANGE_LABEL} {LENGTH}",
              title="mean over estimated ticks")
    _legend_below(means, ncol=1, fontsize=9.5)
    for k in followers:
        mine = sorted((r for r in rows if r["agent"] == int(k) and r["required_range"] is not None),
                      key=lambda r: r["tick"])
        line, = lines.plot([r["tick"] for r in mine], [r["required_range"] for r in mine], ".-",
                           label=f"follower {k}")
        lines.plot([r["tick"] for r in mine], [r["persist_range"] for r in mine], ":",
                   color=line.get_color())
    _log_y(lines)
    lines.set(xlabel="tick j", ylabel=f"required sensing range {LENGTH}",
              title="per tick (dotted: persist counterfactual)")
    _legend_below(lines, ncol=min(len(followers), 5), fontsize=9.5)
    _suptitle(fig, f"{config.surface}, T_c = {config.comm_period:g} {TIME_UNIT}: "
                   "distance from the estimate to the ideal position")
    return _save(fig, path)


def driven_paths(config: RunConfig, surface: Surface, rows: list[dict],
                 controls: list[dict]) -> dict[int, list[np.ndarray]]:
    """Every driving follower's path, control step by control step, rebuilt from the record.

    Tick ``j`` starts from the pose the follower settled at in tick ``j - 1`` (``ticks.csv``'s
    position and heading; tick 0 from its place in the starting column,
    :func:`world.geometry.column`) and drives each of the tick's steps in ``controls.csv`` at
    its achieved speed and turn rate for the step's duration (``config.step_duration``)
    (:func:`world.motion.drive`, as the world moved it). A tick's path therefore ends where the
    follower settled, lost and
    missed ticks included (a missed tick keeps the steps it drove).

    Parameters
    ----------
    config : RunConfig
        The run's resolved configuration (``config.toml``).
    surface : Surface
        The run's surface.
    rows, controls : list of dict
        ``ticks.csv`` and ``controls.csv`` rows (:func:`protocol.record.read_ticks`,
        :func:`protocol.record.read_controls`).

    Returns
    -------
    dict of int to list of ndarray
        Per follower ``k``, per tick of ``rows`` in order, the positions (1 + steps, 2):
        where the tick began, then after each of its steps.
    """
    if config.leader_start is None:
        raise ValueError("config.leader_start must be resolved (a run's config.toml is)")
    if any(r.get("heading_x") is None for r in rows):
        raise ValueError("ticks.csv holds no settled headings (written by an earlier version)")
    start = np.asarray(config.leader_start, dtype=float)
    positions, headings = geometry.column(surface, start[:2], start[2:], config.followers,
                                          config.spacing, config.side_sign)
    steps: dict[tuple[int, int], list[dict]] = {}
    for c in controls:
        steps.setdefault((c["tick"], c["agent"]), []).append(c)
    paths: dict[int, list[np.ndarray]] = {}
    for k in range(1, config.followers + 1):
        pos, heading = positions[k], headings[k]
        paths[k] = []
        for row in sorted((r for r in rows if r["agent"] == k), key=lambda r: r["tick"]):
            points = [pos]
            for c in steps.get((row["tick"], k), ()):
                pos, heading = motion.drive(surface, pos, heading, c["achieved_speed"],
                                            c["achieved_turn"],
                                            config.step_duration(c["step"]))
                points.append(pos)
            paths[k].append(np.array(points))
            pos = np.array([row["pos_x"], row["pos_y"]])
            heading = np.array([row["heading_x"], row["heading_y"]])
    return paths


@_styled
def _draw_driven_paths(rows: list[dict], config: RunConfig, surface: Surface,
                       controls: list[dict], path: str | Path) -> Path:
    """A drive run's paths: every follower's path control step by control step (blue,
    :func:`driven_paths`) from where it started, over the terrain, against its ideal
    positions (red), with the leader (black)."""
    fig = _figure(13.0, 6.5, layout="compressed")
    ax = fig.add_subplot()
    _terrain_map(fig, ax, rows, config, surface, aspect=2.0)
    paths = driven_paths(config, surface, rows, controls)
    for k in range(1, config.followers + 1):
        mine = sorted((r for r in rows if r["agent"] == k), key=lambda r: r["tick"])
        ax.plot([r["ideal_x"] for r in mine], [r["ideal_y"] for r in mine], "o",
                color=IDEAL_COLOR, ms=3.5, label="ideal positions" if k == 1 else None)
        steps = np.concatenate([paths[k][0][:1], *(tick[1:] for tick in paths[k])])
        ax.plot(steps[:, 0], steps[:, 1], "-", color=ESTIMATE_COLOR, lw=0.8,
                label="driven paths" if k == 1 else None)
        ax.plot([r["pos_x"] for r in mine], [r["pos_y"] for r in mine], "x",
                color=ESTIMATE_COLOR, ms=4, mew=1, label="settled" if k == 1 else None)
    ax.set(xlabel=f"x {LENGTH}", ylabel=f"y {LENGTH}")
    _figure_legend(fig)
    _suptitle(fig, f"{config.surface}: driving followers ({config.control_steps} control + "
                   f"{config.snap_steps} correction steps per T_c = {config.comm_period:g} "
                   f"{TIME_UNIT}, top speed {config.max_speed:.3g} {SPEED_UNIT}, "
                   f"estimator {_estimator_label(config)})")
    return _save(fig, path)


def plot_run(run_dir: str | Path, force: bool = False) -> list[Path]:
    """Draw one run's figures into ``run_dir/figures``; return their paths (a drive run's
    driven paths too).

    Raises ValueError if ``run_dir`` is not a results folder, or holds the figures already
    (unless ``force``: draw them anew).
    """
    run_dir = Path(run_dir)
    missing = [n for n in ("config.toml", TICKS_FILE, SUMMARY_FILE)
               if not (run_dir / n).is_file()]
    if missing:
        raise ValueError(f"run_dir {run_dir} is not a results folder "
                         f"(missing {', '.join(missing)})")
    out = run_dir / "figures"
    effectiveness, required = (out / f"{name}.png" for name in ("effectiveness", "required_range"))
    if not force and (effectiveness.exists() or required.exists()):
        raise ValueError(f"{out} holds the run's figures already; draw them anew with --force")
    rows, config = _run_record(run_dir)
    surface = _run_surface(config)
    figures = [_draw_effectiveness(rows, config, surface, effectiveness),
               _draw_required_range(rows, config,
                                    json.loads((run_dir / SUMMARY_FILE).read_text()), required)]
    if config.drives:
        figures.append(_draw_driven_paths(rows, config, surface,
                                          read_controls(run_dir / CONTROLS_FILE),
                                          out / "driven_paths.png"))
    return figures


def _estimator_label(config) -> str:
    if config.estimator != "edmd":
        return config.estimator
    label = f"edmd-{config.dictionary}"
    return label + (f"-{config.velocity}" if config.dictionary == "c" else "")


def _nan(value) -> float:
    return math.nan if value is None else float(value)


# --- experiment tables -------------------------------------------------------------------------

def _surfaces(rows: list[dict]) -> list[str]:
    return list(dict.fromkeys(r["surface"] for r in rows))


def _panels(fig: Figure, n: int, **kwargs) -> list:
    axes = fig.subplots(1, n, squeeze=False, **kwargs)[0]
    return list(axes)


def _dots(ax, x: Sequence[float], values: Sequence[float], color: str, marker: str,
          label: str | None = None, joined: bool = False, values_shown: bool = False) -> None:
    """``values`` at ``x`` as markers (on a log axis a bar has no honest base: its length
    would be the axis floor's choice), ``joined`` by a thin line, each ``values_shown`` to
    two digits beside it."""
    ax.plot(x, values, marker=marker, color=color, ms=8, ls="-" if joined else "none", lw=0.8,
            label=label)
    if values_shown:
        for xi, v in zip(x, values):
            if not math.isnan(v):
                ax.annotate(f"{v:.2g}", (xi, v), xytext=(7, 0), textcoords="offset points",
                            va="center", fontsize=10,
                            bbox={"fc": "white", "ec": "none", "alpha": 0.75, "pad": 0.5})


@_styled
def plot_sensing_range(rows: list[dict], path: str | Path) -> Path:
    """The mean required sensing range per follower and estimator as markers (one line per
    estimator down the column), one panel per surface (the paper's Fig. "averaged follower
    required sensing range", drawn there as bars), log scale."""
    surfaces = _surfaces(rows)
    fig = _figure(PANEL_WIDTH * len(surfaces) + 0.6, 4.8)
    estimators = list(dict.fromkeys(r["estimator"] for r in rows))
    for ax, surface in zip(_panels(fig, len(surfaces), sharey=True), surfaces):
        mine = [r for r in rows if r["surface"] == surface]
        followers = sorted({r["follower"] for r in mine})
        width = 0.5 / len(estimators)  # markers side by side, so that equal values both show
        styles = estimator_styles(estimators)
        for i, est in enumerate(estimators):
            values = [next((r["mean_required_range"] for r in mine
                            if r["follower"] == k and r["estimator"] == est), math.nan)
                      for k in followers]
            x = np.arange(len(followers)) + (i - (len(estimators) - 1) / 2) * width
            _dots(ax, x, values, *styles[est], label=est if surface == surfaces[0] else None,
                  joined=True)
        ax.set_xticks(np.arange(len(followers)), [f"F{k}" for k in followers])
        ax.set_xlabel("follower")
        ax.set_xlim(-0.5, len(followers) - 0.5)
        _log_y(ax)
        ax.set_title(SURFACE_TITLES.get(surface, surface))
    fig.axes[0].set_ylabel(f"{RANGE_LABEL} {LENGTH}")
    _figure_legend(fig)
    return _save(fig, path)


@_styled
def plot_dictionaries(rows: list[dict], surface: str, path: str | Path) -> Path:
    """RMSE per dictionary on one surface, markers on a log scale: (a) local measurements a–c,
    (b) absolute positions d–g (the paper's two panels, bars there), with the ``stay`` and
    ``persist`` baselines as lines."""
    mine = {r["dictionary"]: r for r in rows if r["surface"] == surface}
    fig = _figure(11.0, 4.8)
    panels = _panels(fig, 2, sharey=True, width_ratios=(3, 4))
    for ax, (title, names, color) in zip(panels, (
            ("(a) local measurements", "abc", "tab:blue"),
            ("(b) absolute position (GPS)", "defg", "tab:orange"))):
        names = [n for n in names if n in mine]
        _dots(ax, range(len(names)), [mine[n]["rmse"] for n in names], color, "o",
              values_shown=True)
        ax.set_xticks(range(len(names)), [DICTIONARY_LABELS[n] for n in names])
        for base, style in (("persist", "--"), ("stay", ":")):
            if base in mine and not math.isnan(mine[base]["rmse"]):
                ax.axhline(mine[base]["rmse"], color=ESTIMATOR_STYLE[base][0], ls=style, lw=1.5,
                           label=f"{base}: {mine[base]['rmse']:.2g}" if ax is panels[0] else None)
        ax.set(title=title, xlabel="dictionary (lifted measurements)")
        _log_y(ax)
        ax.set_xlim(-0.5, len(names) - 0.5)
    panels[0].set_ylabel(f"RMSE of the estimate {LENGTH}")
    _figure_legend(fig)
    _suptitle(fig, f"{SURFACE_TITLES.get(surface, surface)}: dictionaries for data-streaming "
                   "EDMD (idealised: oracle velocity for c)")
    return _save(fig, path)


@_styled
def plot_practical(rows: list[dict], path: str | Path) -> Path:
    """RMSE of the practical variants per velocity-noise level, one panel per surface
    (the paper's Fig. "comparison of RMSE … all types of manifold"), mean ± s.d. over seeds.

    ``stay`` is far above the rest and is given in the panel title instead of drawn; the
    dotted line is the floor σ_move·√2 that actuation noise alone puts on the RMSE.
    """
    surfaces = _surfaces(rows)
    variants = [v for v in dict.fromkeys(r["variant"] for r in rows) if v != "stay"]
    noises = sorted({r["noise_velocity"] for r in rows})
    fig = _figure(PANEL_WIDTH * len(surfaces) + 0.6, 5.0)
    width = 0.8 / len(variants)
    move = rows[0]["noise_move"] if rows else math.nan
    for ax, surface in zip(_panels(fig, len(surfaces)), surfaces):
        def cell(variant: str, noise: float, surface: str = surface) -> dict | None:
            return next((r for r in rows if r["surface"] == surface and r["variant"] == variant
                         and r["noise_velocity"] == noise), None)

        for i, variant in enumerate(variants):
            cells = [cell(variant, nv) for nv in noises]
            values = [c["rmse"] if c else math.nan for c in cells]
            spread = [0.0 if c is None or math.isnan(c["rmse_std"]) else c["rmse_std"]
                      for c in cells]
            color, hatch = VARIANT_STYLE.get(variant, ("k", ""))
            x = np.arange(len(noises)) + (i - (len(variants) - 1) / 2) * width
            ax.bar(x, values, width, yerr=spread, color=color, hatch=hatch, edgecolor="white",
                   lw=0.5, error_kw={"lw": 0.9, "capsize": 2},
                   label=variant if surface == surfaces[0] else None)
        if move > 0:
            ax.axhline(move * math.sqrt(2), color="k", ls=":", lw=1.2,
                       label="actuation floor σ_move·√2" if surface == surfaces[0] else None)
        stay = [c["rmse"] for nv in noises if (c := cell("stay", nv)) is not None]
        title = SURFACE_TITLES.get(surface, surface)
        ax.set_xticks(np.arange(len(noises)), [f"{nv:g}" for nv in noises])
        ax.set(title=title + (f"\n(stay, not drawn: {np.mean(stay):.2g})" if stay else ""),
               xlabel=f"velocity noise σ_v ({SPEED_UNIT})")
        ax.set_ylim(bottom=0)
    fig.axes[0].set_ylabel(f"RMSE of the estimate {LENGTH}")
    seeds = max((r["seeds"] for r in rows), default=0)
    _suptitle(fig, f"Practical case: actuation noise σ_move = {move:g} {LENGTH_UNIT} per move; "
                   f"mean ± s.d. over {seeds} seed(s)")
    _figure_legend(fig)
    return _save(fig, path)


@_styled
def plot_comm_period(rows: list[dict], path: str | Path) -> Path:
    """Mean required sensing range against the comm period T_c (log–log), one panel per
    surface, one curve per estimator."""
    surfaces = _surfaces(rows)
    estimators = list(dict.fromkeys(r["estimator"] for r in rows))
    periods = sorted({r["comm_period"] for r in rows})
    fig = _figure(PANEL_WIDTH * len(surfaces) + 0.6, 4.8)
    styles = estimator_styles(estimators)
    for ax, surface in zip(_panels(fig, len(surfaces), sharey=True), surfaces):
        for est in estimators:
            mine = sorted((r["comm_period"], r["mean_required_range"]) for r in rows
                           if r["surface"] == surface and r["estimator"] == est)
            color, marker = styles[est]
            ax.plot(*zip(*mine), marker=marker, color=color, ms=5,
                    label=est if surface == surfaces[0] else None)
        ax.set_xscale("log", base=2)
        _log_y(ax)
        ax.axvline(PAPER_COMM_PERIOD, color="0.4", ls=":", lw=1,
                   label="paper's T_c" if surface == surfaces[0] else None)
        ax.set_xticks(periods, [f"{p:g}" for p in periods], rotation=45)
        ax.xaxis.set_minor_locator(NullLocator())
        ax.set(title=SURFACE_TITLES.get(surface, surface),
               xlabel=f"comm period T_c ({TIME_UNIT})")
    fig.axes[0].set_ylabel(f"{RANGE_LABEL} {LENGTH}")
    _figure_legend(fig)
    return _save(fig, path)


@_styled
def plot_position(rows: list[dict], path: str | Path) -> Path:
    """Mean required sensing range against the position in the column (follower 1 … N), one
    panel per comm period, one curve per estimator (log y)."""
    periods = sorted({r["comm_period"] for r in rows})
    estimators = list(dict.fromkeys(r["estimator"] for r in rows))
    fig = _figure(PANEL_WIDTH * len(periods) + 0.6, 4.8)
    styles = estimator_styles(estimators)
    for ax, period in zip(_panels(fig, len(periods), sharey=True), periods):
        for est in estimators:
            mine = sorted((r["follower"], r["mean_required_range"]) for r in rows
                          if r["comm_period"] == period and r["estimator"] == est)
            color, marker = styles[est]
            ax.plot(*zip(*mine), marker=marker, color=color, ms=5,
                    label=est if period == periods[0] else None)
        _log_y(ax)
        followers = sorted({r["follower"] for r in rows})
        ax.set_xticks(followers, [str(k) for k in followers])
        ax.set(title=f"T_c = {period:g} {TIME_UNIT}", xlabel="position in the column (follower k)")
    fig.axes[0].set_ylabel(f"{RANGE_LABEL} {LENGTH}")
    _figure_legend(fig)
    return _save(fig, path)


SURFACE_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:brown", "tab:purple", "tab:olive")
"""A surface's colour in a figure of several surfaces, in the order they come."""


def _plain_ticks(ax, values: Sequence[float], labels: Sequence[str] | None = None) -> None:
    """Ticks at ``values`` labelled as plain numbers (``0.64``, not ``2^-0.64``) or
    ``labels``, no others."""
    ax.set_xticks(list(values), labels or [f"{v:g}" for v in values])
    ax.xaxis.set_minor_locator(NullLocator())


def _key_legend(fig: Figure, colours: dict[str, str], styles: dict[str, dict]) -> None:
    """One legend below the panels keying a figure's two encodings: a line of each colour of
    ``colours`` (label to colour), then a black sample of each line style of ``styles``
    (label to :class:`matplotlib.lines.Line2D` keywords)."""
    proxies = [matplotlib.lines.Line2D([], [], color=c, lw=2, label=label)
               for label, c in colours.items()]
    proxies += [matplotlib.lines.Line2D([], [], color="k", label=label, **style)
                for label, style in styles.items()]
    fig.legend(handles=proxies, loc="outside lower center", ncol=len(proxies))


@_styled
def plot_drive_study(rows: list[dict], spec, path: str | Path) -> Path:
    """The drive study's figure: mean formation error (top) and mean required sensing range
    (bottom) against the control steps, the top speed (at the base comm period) and the comm
    period (at the base top speed); colour the surface, marker the estimator.

    The top speed is drawn as its margin over the leader's speed (``speed_factor − 1``, +2 %
    … +200 %) on a log axis, where the factors 1.02, 1.05 and 1.1 stay apart. The unbounded
    robot (``speed_factor`` inf) has no place on a numeric axis: it is drawn in a narrow
    panel of its own beside it, sharing its y axis.

    Parameters
    ----------
    rows : list of dict
        ``tables/drive.csv``'s rows (:func:`swarm.grid.read_table`).
    spec : swarm.drive_study.DriveStudySpec
        The study's grid: its surfaces, estimators, base steps, factor and period, followers.
    path : str or Path
        The PNG to write.
    """
    fig = _figure(15.0, 9.0)
    grid = fig.add_gridspec(2, 4, width_ratios=(1, 0.82, 0.1, 1))
    colours = dict(zip(spec.surfaces, SURFACE_COLORS, strict=False))
    markers = {label: ESTIMATOR_STYLE.get(label, OTHER_STYLES[0])[1]
               for label in spec.estimators}
    base = f"{spec.base_factor:g}× the leader's"
    panels = (("steps", "control_steps", "control steps per comm interval", None,
               f"T_c = {spec.base_period:g} {TIME_UNIT}, top speed {base}"),
              ("speed", "speed_factor", "top speed above the leader's", spec.base_period,
               f"T_c = {spec.base_period:g} {TIME_UNIT}, {spec.base_steps} control steps"),
              ("speed", "comm_period", f"comm period T_c ({TIME_UNIT})", spec.base_factor,
               f"top speed {base}, {spec.base_steps} control steps"))
    for row, (y_key, y_label) in enumerate((("mean_formation_error", "formation error"),
                                            ("mean_required_range", "required sensing range"))):
        unbounded = fig.add_subplot(grid[row, 2])
        for (block, x_key, x_label, fixed, title), col in zip(panels, (0, 1, 3)):
            ax = fig.add_subplot(grid[row, col], sharey=unbounded if col == 1 else None)
            xs_seen: set[float] = set()
            for surface in spec.surfaces:
                for label in spec.estimators:
                    mine = [r for r in rows if r["block"] == block
                            and r["surface"] == surface and r["estimator"] == label]
                    if x_key == "speed_factor":
                        mine = [r for r in mine if r["comm_period"] == fixed]
                    if x_key == "comm_period":
                        mine = [r for r in mine if r["speed_factor"] == fixed]
                    mine.sort(key=lambda r: r[x_key])
                    finite = [r for r in mine if math.isfinite(r[x_key])]
                    xs = [r[x_key] - (x_key == "speed_factor") for r in finite]
                    style = {"marker": markers[label], "color": colours[surface], "ms": 5}
                    ax.plot(xs, [r[y_key] for r in finite], lw=1, **style)
                    xs_seen.update(xs)
                    if x_key == "speed_factor":
                        unbounded.plot([0.0] * (len(mine) - len(finite)),
                                       [r[y_key] for r in mine if not math.isfinite(r[x_key])],
                                       ls="none", **style)
            ax.set_xscale("log", base=2)
            _log_y(ax)
            _plain_ticks(ax, sorted(xs_seen), [f"+{100 * x:.0f}%" for x in sorted(xs_seen)]
                         if x_key == "speed_factor" else None)
            if x_key == "speed_factor":
                ax.tick_params(axis="x", labelrotation=40)
            ax.set(xlabel=x_label, ylabel=f"mean {y_label} {LENGTH}", title=title)
            if col == 1:
                ax.set_ylabel("")
        unbounded.set_xticks([0.0], ["un-\nbounded"])
        unbounded.set_xlim(-1, 1)
        unbounded.tick_params(axis="y", labelleft=False)
        unbounded.grid(axis="x", visible=False)
    _key_legend(fig, colours, {e: {"marker": m, "ls": "none"} for e, m in markers.items()})
    _suptitle(fig, "driving followers (--motion drive), noise-free: mean over the column's "
                   f"{spec.followers} followers (colour: surface; marker: estimator)")
    return _save(fig, path)


@_styled
def plot_column_noise(rows: list[dict], path: str | Path) -> Path:
    """Errors travelling down a noisy column (``bench/bench_column_noise.py``): mean formation
    error (top) and mean required sensing range (bottom) per follower, one panel per surface;
    colour the noise level, line and marker the estimator (log y).

    Parameters
    ----------
    rows : list of dict
        ``tables/column_noise.csv``'s rows: ``surface``, ``noise_range``, ``noise_bearing``,
        ``estimator``, ``follower``, ``mean_formation_error``, ``mean_required_range``.
    path : str or Path
        The PNG to write.
    """
    surfaces = _surfaces(rows)
    levels = list(dict.fromkeys((r["noise_range"], r["noise_bearing"]) for r in rows))
    estimators = list(dict.fromkeys(r["estimator"] for r in rows))
    colours = dict(zip(levels, ("tab:green", "tab:blue", "tab:red", *SURFACE_COLORS),
                       strict=False))
    lines = dict(zip(estimators, ("--", "-", ":", "-."), strict=False))
    markers = {e: estimator_styles(estimators)[e][1] for e in estimators}
    fig = _figure(PANEL_WIDTH * len(surfaces) + 0.6, 7.6)
    axes = fig.subplots(2, len(surfaces), sharex=True, squeeze=False)
    for col, surface in enumerate(surfaces):
        for row, (key, label) in enumerate((("mean_formation_error", "formation error"),
                                            ("mean_required_range", "required sensing range"))):
            ax = axes[row][col]
            for level in levels:
                for est in estimators:
                    mine = sorted((r["follower"], r[key]) for r in rows
                                  if r["surface"] == surface and r["estimator"] == est
                                  and (r["noise_range"], r["noise_bearing"]) == level)
                    ax.plot(*zip(*mine), lines[est], marker=markers[est], ms=4, lw=1.2,
                            color=colours[level], mfc="white" if lines[est] != "-" else None)
            _log_y(ax)
            if col == 0:
                ax.set_ylabel(f"mean {label} {LENGTH}")
            if row == 1:
                ax.set_xlabel("follower k (position in the column)")
        axes[0][col].set_title(SURFACE_TITLES.get(surface, surface))
    followers = sorted({r["follower"] for r in rows})
    axes[1][0].set_xticks(followers, [str(k) for k in followers])
    _key_legend(fig, {f"σ_range {nr:g} {LENGTH_UNIT}, σ_bearing {nb:g} rad": c
                      for (nr, nb), c in colours.items()},
                {e: {"ls": lines[e], "marker": markers[e],
                     "mfc": "white" if lines[e] != "-" else None} for e in estimators})
    _suptitle(fig, "Errors down a noisy column: mean over seeds per follower (colour: noise "
                   "on range and bearing; line and marker: estimator)")
    return _save(fig, path)
