"""Figures that read at a glance, checked on the drawn matplotlib figures: no bar on a log axis
(its length would be the axis floor's choice), no legend over data, every label, title and
legend inside the figure, every panel's axes labelled.

The table figures are drawn from the committed tables (``docs/tables``), the run figures from a
short in-memory run.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from swarm.grid import read_table

ROOT = Path(__file__).resolve().parents[1]
TABLES = ROOT / "docs" / "tables"


@pytest.fixture
def drawn(monkeypatch):
    """Every figure :mod:`swarm.plots` saves while the test runs, in order."""
    from swarm import plots

    figures = []
    save = plots._save
    monkeypatch.setattr(plots, "_save",
                        lambda fig, path: figures.append(fig) or save(fig, path))
    return figures


def _data_points(ax, samples: int = 20) -> np.ndarray:
    """Display coordinates (m, 2) of every line of ``ax``: its vertices and ``samples``
    points on each segment between them (a line crossing a legend between two vertices
    counts)."""
    out = [np.empty((0, 2))]
    for line in ax.get_lines():
        xy = np.asarray(line.get_transform().transform(line.get_xydata()), dtype=float)
        xy = xy[np.isfinite(xy).all(axis=1)]
        if len(xy) == 1:
            out.append(xy)
        for a, b in zip(xy[:-1], xy[1:]):
            out.append(a + np.linspace(0, 1, samples)[:, None] * (b - a))
    for collection in ax.collections:  # scatter points
        offsets = collection.get_offsets()
        if len(offsets):
            xy = collection.get_offset_transform().transform(offsets)
            out.append(xy[np.isfinite(xy).all(axis=1)])
    return np.concatenate(out)


def problems(fig) -> list[str]:
    """What makes ``fig`` hard to read (empty if nothing), as last drawn: as saved, for a
    figure :mod:`swarm.plots` saved (a second draw may lay it out anew)."""
    from matplotlib.container import BarContainer

    renderer = fig.canvas.get_renderer()
    inner = fig.bbox.padded(1.0)  # a pixel of rounding
    out = []

    def outside(artist) -> bool:
        box = artist if hasattr(artist, "x0") else artist.get_window_extent(renderer)
        return not (inner.x0 <= box.x0 and box.x1 <= inner.x1 and inner.y0 <= box.y0
                    and box.y1 <= inner.y1)

    legends = [*fig.legends, *[ax.get_legend() for ax in fig.axes if ax.get_legend()]]
    for legend in legends:
        if outside(legend):
            out.append(f"legend {[t.get_text() for t in legend.get_texts()]} leaves the figure")
        box = legend.get_window_extent(renderer).shrunk(0.98, 0.98)
        for ax in fig.axes:
            points = _data_points(ax)
            inside = ((points[:, 0] > box.x0) & (points[:, 0] < box.x1) & (points[:, 1] > box.y0)
                      & (points[:, 1] < box.y1))
            if inside.any():
                out.append(f"legend {[t.get_text() for t in legend.get_texts()]} covers data "
                           f"of panel {ax.get_title()!r}")
    for ax in fig.axes:
        name = repr(ax.get_title() or ax.get_xlabel() or ax.get_ylabel())
        if ax.get_yscale() == "log" and any(isinstance(c, BarContainer) for c in ax.containers):
            out.append(f"bars on the log axis of panel {name}")
        if outside(ax.get_tightbbox(renderer)):  # its labels, tick labels, title, legend
            out.append(f"panel {name} (labels and title) leaves the figure")
        powers = [t.get_text() for t in ax.get_xticklabels() if "^" in t.get_text()]
        if powers:  # 2^0, 2^1 for a comm period of 1 and 2 s
            out.append(f"x ticks {powers} of panel {name} are powers, not plain numbers")
    if fig._suptitle is not None and outside(fig._suptitle):
        out.append(f"title {fig.get_suptitle()!r} leaves the figure")
    return out


def test_the_check_sees_a_bar_on_a_log_axis_a_covered_curve_and_a_cut_label():
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(4, 3))
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    ax.bar([0, 1], [1e-3, 1.0])
    ax.set_yscale("log")
    ax.plot([0, 1], [0.5, 0.5], transform=ax.transAxes, label="a curve under its legend")
    ax.legend(loc="center")
    ax.set_xlabel("a label below the figure's edge", labelpad=200)
    ax.set_xscale("log", base=2)
    ax.set_xlim(1, 4)
    fig.canvas.draw()
    found = "\n".join(problems(fig))
    assert "bars on the log axis" in found
    assert "covers data" in found
    assert "leaves the figure" in found
    assert "are powers, not plain numbers" in found


def test_every_table_figure_reads_at_a_glance(drawn, tmp_path):
    """The paper experiment's figures from the committed tables (and the terrain study's
    position figure from the same numbers), and bench_column_noise's."""
    from swarm import plots

    tables = {name: read_table(TABLES / f"{name}.csv")
              for name in ("sensing_range", "dictionaries", "practical", "comm_period")}
    plots.plot_sensing_range(tables["sensing_range"], tmp_path / "s.png")
    for surface in ("elliptic", "hyperbolic", "wavy"):
        plots.plot_dictionaries(tables["dictionaries"], surface, tmp_path / f"d-{surface}.png")
    plots.plot_practical(tables["practical"], tmp_path / "p.png")
    plots.plot_comm_period(tables["comm_period"], tmp_path / "c.png")
    position = [{**r, "comm_period": 1.28} for r in tables["sensing_range"]
                if r["surface"] == "elliptic"]
    plots.plot_position(position, tmp_path / "pos.png")
    plots.plot_column_noise(read_table(TABLES / "column_noise.csv"), tmp_path / "n.png")
    assert len(drawn) == 8
    assert {p for fig in drawn for p in problems(fig)} == set()


@pytest.mark.timeout(120)
def test_a_drive_runs_figures_read_at_a_glance(drawn, tmp_path):
    """``swarm plot``'s figures of the driving run of docs/drive.md: effectiveness, required
    range and the driven paths (whose x label the figure once cut off)."""
    from swarm.cli import main
    from swarm.plots import plot_run

    assert main(["run", "--surface", "wavy", "--followers", "3", "--estimator", "auto",
                 "--motion", "drive", "--in-process",
                 "--out", str(tmp_path / "run")]) == 0
    plot_run(tmp_path / "run")
    assert len(drawn) == 3
    assert {p for fig in drawn for p in problems(fig)} == set()


def test_the_drive_studys_figure_reads_at_a_glance(drawn, tmp_path):
    """From the committed ``docs/drive/tables/drive.csv``: no legend over the curves, plain
    tick labels, and the unbounded robot in a panel of its own, not at a made-up top speed
    on the numeric axis (it was drawn at 8×)."""
    from swarm.drive_study import DriveStudySpec, draw_study

    rows = read_table(ROOT / "docs" / "drive" / "tables" / "drive.csv")
    draw_study(rows, DriveStudySpec(), tmp_path / "drive.png")
    [fig] = drawn
    assert problems(fig) == []
    finite = max(r["speed_factor"] for r in rows if np.isfinite(r["speed_factor"]))
    speed = [ax for ax in fig.axes if ax.get_xlabel().startswith("top speed")]
    unbounded = [ax for ax in fig.axes if "bounded" in " ".join(
        t.get_text() for t in ax.get_xticklabels())]
    assert len(speed) == len(unbounded) == 2
    for ax in speed:
        xs = np.concatenate([line.get_xdata() for line in ax.get_lines()])
        assert np.isfinite(xs).all() and xs.max() <= finite - 1 + 1e-12  # the margin over 1
    for ax in unbounded:  # one point per surface and estimator at the base comm period
        points = sum(len(line.get_xdata()) for line in ax.get_lines())
        assert points == sum(1 for r in rows if r["block"] == "speed"
                             and np.isinf(r["speed_factor"]) and r["comm_period"] == 1.28)


def test_the_column_noise_figure_tells_its_estimators_apart_without_its_legend(drawn, tmp_path):
    """Its persist and auto curves once differed only in the legend: every curve's look
    (line style and marker) names its estimator, and the figure has a title."""
    from swarm.plots import plot_column_noise

    rows = read_table(TABLES / "column_noise.csv")
    plot_column_noise(rows, tmp_path / "n.png")
    [fig] = drawn
    looks = {(line.get_linestyle(), line.get_marker()) for ax in fig.axes
             for line in ax.get_lines()}
    assert len(looks) == len({r["estimator"] for r in rows})
    assert fig.get_suptitle()
