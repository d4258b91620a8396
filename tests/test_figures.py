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
    fig.canvas.draw()
    found = "\n".join(problems(fig))
    assert "bars on the log axis" in found
    assert "covers data" in found
    assert "leaves the figure" in found


def test_every_table_figure_reads_at_a_glance(drawn, tmp_path):
    """The paper experiment's figures from the committed tables (and the terrain study's
    position figure from the same numbers)."""
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
    assert len(drawn) == 7
    assert {p for fig in drawn for p in problems(fig)} == set()


@pytest.mark.timeout(120)
def test_a_drive_runs_figures_read_at_a_glance(drawn, tmp_path):
    """``swarm plot``'s figures of the driving run of docs/drive.md: effectiveness, required
    range and the driven paths (whose x label the figure once cut off)."""
    from swarm.cli import main
    from swarm.plots import plot_run

    assert main(["run", "--surface", "wavy", "--followers", "3", "--estimator", "auto",
                 "--motion", "drive", "--max-speed", "1.3", "--in-process",
                 "--out", str(tmp_path / "run")]) == 0
    plot_run(tmp_path / "run")
    assert len(drawn) == 3
    assert {p for fig in drawn for p in problems(fig)} == set()
