"""The page: one Bokeh document per browser tab, redrawn from a :class:`RunStore`.

Live, the map follows the newest complete tick; in a replay a slider (and play/pause) picks the
tick. A periodic callback (every :data:`REFRESH_MS`) compares the store's version with the
one drawn and refreshes the sources when it changed.
"""
from __future__ import annotations

import numpy as np

from protocol.distribution import needs
from swarm.live.draw import (
    agent_color,
    choice_points,
    contour_levels,
    empty_map_columns,
    follower_series,
    height_grid,
    hillshade,
    map_columns,
)
from swarm.live.store import COMPLETE, INCOMPLETE, REPLAY_HINT, WAITING, RunStore, Snapshot

with needs("live"):
    from bokeh.document import Document
    from bokeh.layouts import column, row
    from bokeh.models import (
        ColumnDataSource,
        DataRange1d,
        Div,
        FactorRange,
        Range1d,
        Slider,
        Span,
        Toggle,
    )
    from bokeh.plotting import figure

REFRESH_MS = 200
PLAY_EVERY = 1  # replay: ticks advanced per refresh while playing
MAX_RANGE_PLOTS = 8  # per-follower range plots drawn (the map shows every agent)

MAP_FRAME = (680, 470)  # map's plot area in pixels (width, height): the box is fitted to it
NOSE = 0.6  # heading segment length, in rods
WAITING_HINT = (f"{WAITING}: none of this run is alive on the router (not started yet, or "
                f"over: {REPLAY_HINT})")


class Page:
    """The widgets and sources of one tab; :meth:`refresh` redraws from the store."""

    def __init__(self, doc: Document, store: RunStore, replay: bool) -> None:
        self.doc, self.store, self.replay = doc, store, replay
        self.drawn_version = -1
        self.drawn_tick: int | None = None
        self.map_drawn = False
        self.status = Div(text=WAITING_HINT, name="status",
                          css_classes=["swarm-status"], styles={"font-size": "16px"})
        self.sources = {name: ColumnDataSource(name=f"{name}-source", data=data)
                        for name, data in empty_map_columns().items()}
        self.map = self._map_figure()
        self.range_column = column(name="ranges")
        self.range_plots: dict[int, tuple[dict, Span]] = {}
        self.choices = ColumnDataSource(name="choices", data=choice_points({}, 1))
        self.ticks_range = DataRange1d()  # shared by every per-tick plot
        self.choice_plot = figure(height=170, width=480, y_range=FactorRange(),
                                  x_range=self.ticks_range, x_axis_label="tick",
                                  title="estimator per tick (auto: followed candidate)",
                                  toolbar_location=None)
        self.choice_plot.scatter("tick", "y", color="color", legend_field="follower",
                                 source=self.choices, size=5)
        self.choice_plot.add_layout(self.choice_plot.legend[0], "right")
        self.choice_plot.legend.title = "follower"
        self.slider = Slider(start=0, end=1, value=0, step=1, title="tick", name="tick_slider",
                             width=700, visible=replay)
        self.play = Toggle(label="play", name="play", width=90, visible=replay)
        self.play.on_change("active", lambda attr, old, new: self._on_play(new))
        self.slider.on_change("value", lambda attr, old, new: self.refresh(force=True))
        doc.add_root(column(self.status, row(self.slider, self.play),
                            row(self.map, column(self.range_column, self.choice_plot))))
        doc.title = "swarm replay" if replay else "swarm live"
        doc.add_periodic_callback(self.on_timer, REFRESH_MS)
        self.refresh()

    def _map_figure(self):
        fig = figure(frame_width=MAP_FRAME[0], frame_height=MAP_FRAME[1], x_range=Range1d(0, 1),
                     y_range=Range1d(0, 1), title="column on the surface", x_axis_label="x",
                     y_axis_label="y", name="map")
        src = self.sources
        fig.multi_line("xs", "ys", line_color="color", line_width="width", line_alpha=0.6,
                       source=src["paths"])
        fig.circle("x", "y", radius="radius", line_color="color", fill_color="color",
                   fill_alpha=0.05, line_dash="dotted", source=src["ranges"],
                   legend_label="sensing range R_s")
        fig.segment("x0", "y0", "x1", "y1", line_color="color", line_width=2, source=src["rods"],
                    name="rods", legend_label="rod")
        fig.scatter("x", "y", marker="circle", size=11, line_color="color", fill_color=None,
                    line_width=2, source=src["targets"], legend_label="true rod end")
        fig.scatter("x", "y", marker="x", size=11, line_color="color", line_width=2,
                    source=src["estimates"], legend_label="estimate")
        fig.segment("x0", "y0", "x1", "y1", line_color="color", line_width=3,
                    source=src["headings"], name="headings")
        fig.scatter("x", "y", marker="circle", size=11, fill_color="color", line_color="white",
                    source=src["agents"], name="agents", legend_label="agent and heading")
        fig.text("x", "y", text="label", x_offset=8, y_offset=-8, text_font_size="11px",
                 source=src["agents"])
        fig.legend.orientation = "horizontal"
        fig.legend.click_policy = "hide"
        fig.add_layout(fig.legend[0], "below")
        return fig

    def _draw_surface(self, view_map: dict) -> None:
        """Relief (DEM surfaces) and contour lines, once the map has arrived."""
        xs, ys, z = height_grid(view_map)
        x0, x1, y0, y1 = view_map["box"]
        if view_map["relief"] == "dem":
            image = hillshade(view_map).view(dtype=np.uint32).reshape(z.shape)
            self.map.image_rgba(image=[image], x=x0, y=y0, dw=x1 - x0, dh=y1 - y0, level="image")
        levels = contour_levels(z)
        if levels.size >= 2:
            from bokeh.palettes import Viridis256

            renderer = self.map.contour(xs, ys, np.ma.masked_invalid(z), levels,
                                        line_color=_pick(Viridis256, levels.size),
                                        line_alpha=0.7, fill_color=None)
            renderer.level = "underlay"
        (x0, x1), (y0, y1) = _fit((x0, x1), (y0, y1), MAP_FRAME[0] / MAP_FRAME[1])
        self.map.x_range.start, self.map.x_range.end = x0, x1
        self.map.y_range.start, self.map.y_range.end = y0, y1
        self.map.title.text = (f"{view_map['surface']} surface, {view_map['followers']} "
                               f"follower(s), {view_map['estimator']}, "
                               f"T_c {view_map['comm_period']:g}")
        for k in range(1, min(view_map["followers"], MAX_RANGE_PLOTS) + 1):
            self._add_range_plot(k)

    def _add_range_plot(self, k: int) -> None:
        fig = figure(height=200, width=480, y_axis_type="log", toolbar_location=None,
                     x_range=self.ticks_range,
                     title=f"follower {k}: sensing range needed per tick", name=f"ranges-{k}")
        sources = {name: ColumnDataSource(data=data) for name, data in
                   follower_series((), k).items()}
        fig.line("tick", "required", source=sources["ranges"], color=agent_color(k),
                 line_width=2, legend_label="required")
        fig.line("tick", "persist", source=sources["ranges"], color="#555555", line_dash="dotted",
                 legend_label="persist")
        fig.line("tick", "stay", source=sources["ranges"], color="#aaaaaa", line_dash="dashed",
                 legend_label="stay")
        fig.scatter("tick", "y", source=sources["lost"], marker="x", size=9, color="red",
                    legend_label="lost")
        fig.scatter("tick", "y", source=sources["missed"], marker="square_x", size=9,
                    color="purple", fill_color=None, legend_label="missed")
        fig.legend.label_text_font_size = "9px"
        fig.legend.orientation = "horizontal"
        fig.legend.padding = fig.legend.spacing = 2
        fig.add_layout(fig.legend[0], "above")
        cursor = Span(dimension="height", location=0, line_color="#999999", line_dash="dashed")
        fig.add_layout(cursor)
        self.range_plots[k] = (sources, cursor)
        self.range_column.children = [*self.range_column.children, fig]

    def _on_play(self, active: bool) -> None:
        self.play.label = "pause" if active else "play"
        if active and self.slider.value >= self.slider.end:
            self.slider.value = self.slider.start

    def on_timer(self) -> None:
        """Every :data:`REFRESH_MS`: a playing replay advances its slider (whose change
        handler redraws), anything else redraws what changed."""
        if self.replay and self.play.active:
            if self.slider.value < self.slider.end:
                self.slider.value = min(self.slider.value + PLAY_EVERY, self.slider.end)
                return
            self.play.active = False
        self.refresh()

    def refresh(self, force: bool = False) -> None:
        """Redraw what changed since the last call (``force``: the tick to show changed)."""
        if self.store.version == self.drawn_version and not force:
            return  # nothing new: no snapshot to copy, five times a second per page
        snap = self.store.snapshot()
        if snap.map is not None and not self.map_drawn:
            self._draw_surface(snap.map)
            self.map_drawn = True
        if snap.version != self.drawn_version:
            self._draw_series(snap)
        self._draw_tick(snap)
        self.drawn_version = snap.version

    def _draw_series(self, snap: Snapshot) -> None:
        for k, (sources, _) in self.range_plots.items():
            for name, data in follower_series(snap.frames, k).items():
                sources[name].data = data
        points = choice_points(snap.choices, snap.map["followers"] if snap.map else 1)
        labels = sorted(set(points["label"]))
        if list(self.choice_plot.y_range.factors) != labels:
            self.choice_plot.y_range.factors = labels
        self.choices.data = points
        if self.replay and snap.frames:
            self.slider.start = snap.frames[0].tick
            self.slider.end = max(snap.frames[-1].tick, self.slider.start + 1)

    def _draw_tick(self, snap: Snapshot) -> None:
        if not snap.frames:
            self.status.text = status_text(snap, None)
            return
        frames = {f.tick: f for f in snap.frames}
        want = int(self.slider.value) if self.replay else snap.frames[-1].tick
        tick = max((j for j in frames if j <= want), default=snap.frames[0].tick)
        sensing = snap.map["sensing_range"] if snap.map else None
        nose = NOSE * snap.map["spacing"] if snap.map else 1.0
        if tick != self.drawn_tick or snap.version != self.drawn_version:
            for name, data in map_columns(frames, tick, sensing, nose).items():
                self.sources[name].data = data
            for _, cursor in self.range_plots.values():
                cursor.location = tick
            self.drawn_tick = tick
        self.status.text = status_text(snap, frames[tick])


def status_text(snap: Snapshot, frame) -> str:
    """``tick j of n · t = … · status`` (the last tick is ``ticks − 1``)."""
    if snap.status == COMPLETE:
        state = "complete"
    elif snap.status == INCOMPLETE:
        state = f"incomplete: {snap.reason}" if snap.reason else "incomplete"
    elif snap.status == WAITING:
        state = WAITING_HINT
    else:
        state = snap.status
    last = snap.map["ticks"] - 1 if snap.map else "?"
    if frame is None:
        return f"tick - of {last} · {state}"
    return f"tick {frame.tick} of {last} · t = {frame.t:.2f} · {state}"


def _pick(palette: tuple[str, ...], n: int) -> list[str]:
    return [palette[int(i)] for i in np.linspace(0, len(palette) - 1, n)]


def _fit(xs: tuple[float, float], ys: tuple[float, float],
         aspect: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """The ranges ``xs``, ``ys`` widened about their centres to the width/height ``aspect``
    (one length unit the same number of pixels on both axes)."""
    width, height = xs[1] - xs[0], ys[1] - ys[0]
    width, height = max(width, height * aspect), max(height, width / aspect)
    cx, cy = sum(xs) / 2, sum(ys) / 2
    return (cx - width / 2, cx + width / 2), (cy - height / 2, cy + height / 2)


def build_page(doc: Document, store: RunStore, replay: bool) -> None:
    """Bokeh application handler: one :class:`Page` per browser tab."""
    Page(doc, store, replay)
