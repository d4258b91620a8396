"""The page: one Bokeh document per browser tab, redrawn from a :class:`RunStore`.

Live, the map follows the newest complete tick; in a replay a slider (and play/pause) picks the
tick. A periodic callback (every :data:`REFRESH_MS`) compares the store's version with the
one drawn and refreshes the sources when it changed.

The map is drawn at true aspect (one metre the same number of pixels both ways): its
frame takes the shape of the world's map box, whose contour lines (and relief, on a DEM)
therefore fill the view; the view grows only to hold an agent that leaves the box. Labels
closer than :data:`LABEL_GAP` pixels to another are left out. Every range is set here, never
computed by the browser from data (BokehJS warns while a plot has none).
"""
from __future__ import annotations

import math

import numpy as np

from protocol.config import LENGTH, TIME
from protocol.distribution import needs
from swarm.live.draw import (
    agent_color,
    choice_points,
    contour_levels,
    empty_map_columns,
    estimated_choices,
    fit_view,
    follower_series,
    height_grid,
    hillshade,
    log_span,
    map_columns,
    sparse_labels,
)
from swarm.live.store import COMPLETE, INCOMPLETE, REPLAY_HINT, WAITING, RunStore, Snapshot

with needs("live"):
    from bokeh.document import Document
    from bokeh.layouts import column, row
    from bokeh.models import (
        BoxZoomTool,
        ColumnDataSource,
        Div,
        FactorRange,
        Legend,
        LegendItem,
        Range1d,
        Slider,
        Span,
        Toggle,
    )
    from bokeh.plotting import figure

REFRESH_MS = 200
PLAY_EVERY = 1  # replay: ticks advanced per refresh while playing
MAX_RANGE_PLOTS = 8  # per-follower range plots drawn (the map shows every agent)

MAP_SIDE = 700  # px: the map's plot area along the longer side of the world's map box
MIN_SIDE = 260  # px: and at least this along the other side (true aspect either way)
LABEL_GAP = 16  # px: an agent label closer than this to another label is left out
NOSE = 0.6  # heading segment length, in rods
FOLLOWERS_PER_COLUMN = 6  # of the estimator strip's legend
NEUTRAL = "#555555"  # legend glyphs of the map, whose colours stand for agents
WAITING_HINT = (f"{WAITING}: none of this run is alive on the router (not started yet, or "
                f"over: {REPLAY_HINT})")
RS_LABEL = "sensing range R_s"


def frame_size(box: list[float]) -> tuple[int, int]:
    """Plot-area pixels ``(width, height)`` for the map's ``box`` ``[x0, x1, y0, y1]`` at true
    aspect: :data:`MAP_SIDE` along its longer side, the other side in proportion but at least
    :data:`MIN_SIDE` (the view then reaches past the box that way)."""
    aspect = (box[1] - box[0]) / (box[3] - box[2])
    if aspect >= 1:
        return MAP_SIDE, max(MIN_SIDE, round(MAP_SIDE / aspect))
    return max(MIN_SIDE, round(MAP_SIDE * aspect)), MAP_SIDE


def strip_title(view_map: dict | None) -> str:
    """The estimator strip's title: the run's estimator, and what its points are."""
    if view_map is None:
        return "estimator per tick"
    name = view_map["estimator"]
    if name == "edmd":
        name += f", dictionary {view_map['dictionary']}"
    return f"followed per estimated tick (estimator {name})"


class Page:
    """The widgets and sources of one tab; :meth:`refresh` redraws from the store."""

    def __init__(self, doc: Document, store: RunStore, replay: bool) -> None:
        self.doc, self.store, self.replay = doc, store, replay
        self.drawn_version = -1
        self.drawn_tick: int | None = None
        self.map_drawn = False
        self.view: tuple[float, float, float, float] | None = None
        self.status = Div(text=WAITING_HINT, name="status",
                          css_classes=["swarm-status"], styles={"font-size": "16px"})
        self.health = Div(text="", name="health", css_classes=["swarm-health"])
        self.sources = {name: ColumnDataSource(name=f"{name}-source", data=data)
                        for name, data in empty_map_columns().items()}
        self.map = self._map_figure()
        self.range_column = column(Div(text="(the range plots follow the world's map)"),
                                   name="ranges")
        self.range_plots: dict[int, tuple[dict, Span, Range1d]] = {}
        self.choices = ColumnDataSource(name="choices", data=choice_points({}, 1))
        # shared by every per-tick plot; every range is set from the server, never computed
        # by the browser from data (which warns while there is none)
        self.ticks_range = Range1d(-0.5, 0.5)
        self.choice_plot = figure(height=190, width=480, y_range=FactorRange(),
                                  x_range=self.ticks_range, x_axis_label="tick j",
                                  y_axis_label="followed", title=strip_title(None),
                                  name="choices-plot",
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
        doc.add_root(column(self.status, self.health, row(self.slider, self.play),
                            row(self.map, column(self.range_column, self.choice_plot))))
        doc.title = "swarm replay" if replay else "swarm live"
        doc.add_periodic_callback(self.on_timer, REFRESH_MS)
        self.refresh()

    def _map_figure(self):
        fig = figure(frame_width=MAP_SIDE, frame_height=MAP_SIDE * 2 // 3, x_range=Range1d(0, 1),
                     y_range=Range1d(0, 1), title="column on the surface",
                     x_axis_label=f"x ({LENGTH})", y_axis_label=f"y ({LENGTH})", name="map",
                     tools="pan,wheel_zoom,reset,save")
        fig.add_tools(BoxZoomTool(match_aspect=True))
        src = self.sources
        drawn = {
            "trail": fig.multi_line("xs", "ys", line_color="color", line_width="width",
                                    line_alpha=0.6, source=src["paths"]),
            RS_LABEL: fig.circle("x", "y", radius="radius", line_color="color",
                                 fill_color="color", fill_alpha=0.05, line_dash="dotted",
                                 source=src["ranges"]),
            "rod": fig.segment("x0", "y0", "x1", "y1", line_color="color", line_width=2,
                               source=src["rods"], name="rods"),
            "true rod end": fig.scatter("x", "y", marker="circle", size=11, line_color="color",
                                        fill_color=None, line_width=2, source=src["targets"]),
            "estimate": fig.scatter("x", "y", marker="x", size=11, line_color="color",
                                    line_width=2, source=src["estimates"]),
        }
        heading = fig.segment("x0", "y0", "x1", "y1", line_color="color", line_width=3,
                              source=src["headings"], name="headings")
        agents = fig.scatter("x", "y", marker="circle", size=11, fill_color="color",
                             line_color="white", source=src["agents"], name="agents")
        fig.text("x", "y", text="label", x_offset=8, y_offset=-8, text_font_size="12px",
                 text_font_style="bold", background_fill_color="white",
                 background_fill_alpha=0.8, source=src["agents"], name="labels")
        styles = {"trail": ("line", {"line_color": NEUTRAL, "line_width": 2}),
                  RS_LABEL: ("scatter", {"marker": "circle", "size": 13, "line_color": NEUTRAL,
                                         "line_dash": "dotted", "fill_alpha": 0.05,
                                         "fill_color": NEUTRAL}),
                  "rod": ("segment", {"line_color": NEUTRAL, "line_width": 2}),
                  "true rod end": ("scatter", {"marker": "circle", "size": 11, "line_width": 2,
                                               "line_color": NEUTRAL, "fill_color": None}),
                  "estimate": ("scatter", {"marker": "x", "size": 11, "line_width": 2,
                                           "line_color": NEUTRAL})}
        items = [legend_item(fig, label, [drawn[label]], *styles[label]) for label in styles]
        items.append(legend_item(fig, "agent (L: leader), heading", [agents, heading], "scatter",
                                 {"marker": "circle", "size": 11, "fill_color": NEUTRAL,
                                  "line_color": "white"}))
        legend = Legend(items=items, orientation="horizontal", click_policy="hide",
                        name="map-legend")
        fig.add_layout(legend, "below")
        return fig

    def _draw_surface(self, view_map: dict) -> None:
        """Relief (DEM surfaces) and contour lines over the whole box of the map, the map's
        frame at the box's true aspect, the range plots, once the map has arrived."""
        xs, ys, z = height_grid(view_map)
        x0, x1, y0, y1 = view_map["box"]
        if view_map["relief"] == "dem":  # pixel centres on the grid's nodes
            image = hillshade(view_map).view(dtype=np.uint32).reshape(z.shape)
            dx, dy = xs[1] - xs[0], ys[1] - ys[0]
            self.map.image_rgba(image=[image], x=x0 - dx / 2, y=y0 - dy / 2, dw=x1 - x0 + dx,
                                dh=y1 - y0 + dy, level="image", name="relief")
        levels = contour_levels(z)
        if levels.size >= 2:
            from bokeh.palettes import Viridis256

            renderer = self.map.contour(xs, ys, np.ma.masked_invalid(z), levels,
                                        line_color=_pick(Viridis256, levels.size),
                                        line_alpha=0.7, fill_color=None)
            renderer.level = "underlay"
            renderer.name = "contours"
        self.map.frame_width, self.map.frame_height = frame_size(view_map["box"])
        if view_map["sensing_range"] is None:  # nothing of it to draw
            legend = self.map.select_one({"name": "map-legend"})
            legend.items = [i for i in legend.items if i.label.value != RS_LABEL]
        self.map.title.text = (f"{view_map['surface']} surface, {view_map['followers']} "
                               f"follower(s), {view_map['estimator']}, "
                               f"T_c {view_map['comm_period']:g} {TIME}")
        self.ticks_range.start, self.ticks_range.end = -0.5, view_map["ticks"] - 0.5
        self.choice_plot.title.text = strip_title(view_map)
        self.choice_plot.legend.ncols = math.ceil(view_map["followers"] / FOLLOWERS_PER_COLUMN)
        self.range_column.children = []
        for k in range(1, min(view_map["followers"], MAX_RANGE_PLOTS) + 1):
            self._add_range_plot(k)

    def _fit_view(self, snap: Snapshot) -> None:
        """Fit the map's ranges to the box and every agent seen so far, when that view changed
        (it only grows, as ticks come in; a pan or zoom of the user's is kept till then)."""
        points = np.array([(row["pos_x"], row["pos_y"]) for frame in snap.frames
                           for row in frame.rows.values()])
        width, height = self.map.frame_width, self.map.frame_height
        view = fit_view(snap.map["box"], points, snap.map["spacing"], width / height)
        if view == self.view:
            return
        self.view = view
        self.map.x_range.start, self.map.x_range.end, self.map.y_range.start, \
            self.map.y_range.end = view

    def _add_range_plot(self, k: int) -> None:
        y_range = Range1d(*log_span({}))
        fig = figure(height=230, width=480, y_axis_type="log", toolbar_location=None,
                     x_range=self.ticks_range, y_range=y_range, x_axis_label="tick j",
                     y_axis_label=f"range ({LENGTH})",
                     title=f"follower {k}: sensing range needed per tick", name=f"ranges-{k}")
        sources = {name: ColumnDataSource(data=data) for name, data in
                   follower_series((), k).items()}
        lines = {"required": {"line_color": agent_color(k), "line_width": 2},
                 "persist": {"line_color": "#555555", "line_dash": "dotted"},
                 "stay": {"line_color": "#aaaaaa", "line_dash": "dashed"}}
        marks = {"lost": {"marker": "x", "size": 9, "line_color": "red"},
                 "missed": {"marker": "square_x", "size": 9, "line_color": "purple",
                            "fill_color": None}}
        items = [legend_item(fig, name, [fig.line("tick", name, source=sources["ranges"],
                                                  **style)], "line", style)
                 for name, style in lines.items()]
        items += [legend_item(fig, name, [fig.scatter("tick", "y", source=sources[name],
                                                      **style)], "scatter", style)
                  for name, style in marks.items()]
        fig.add_layout(Legend(items=items, orientation="horizontal", label_text_font_size="9px",
                              padding=2, spacing=2, name=f"ranges-{k}-legend"), "above")
        cursor = Span(dimension="height", location=0, line_color="#999999", line_dash="dashed")
        fig.add_layout(cursor)
        self.range_plots[k] = (sources, cursor, y_range)
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
        if snap.map is not None:
            self._fit_view(snap)
        for k, (sources, _, y_range) in self.range_plots.items():
            series = follower_series(snap.frames, k)
            for name, data in series.items():
                sources[name].data = data
            y_range.start, y_range.end = log_span(series["ranges"])
        points = choice_points(estimated_choices(snap.choices, snap.frames),
                               snap.map["followers"] if snap.map else 1)
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
            self.health.text = health_html(snap, None)
            return
        frames = {f.tick: f for f in snap.frames}
        want = int(self.slider.value) if self.replay else snap.frames[-1].tick
        tick = max((j for j in frames if j <= want), default=snap.frames[0].tick)
        sensing = snap.map["sensing_range"] if snap.map else None
        nose = NOSE * snap.map["spacing"] if snap.map else 1.0
        if tick != self.drawn_tick or snap.version != self.drawn_version:
            columns = map_columns(frames, tick, sensing, nose)
            agents = columns["agents"]
            if self.view is not None:
                gap = LABEL_GAP * (self.view[1] - self.view[0]) / self.map.frame_width
                agents["label"] = sparse_labels(agents["x"], agents["y"], agents["label"], gap)
            for name, data in columns.items():
                self.sources[name].data = data
            for _, cursor, _ in self.range_plots.values():
                cursor.location = tick
            self.drawn_tick = tick
        self.status.text = status_text(snap, frames[tick])
        self.health.text = health_html(snap, frames[tick])


def health_html(snap: Snapshot, frame) -> str:
    """Each follower's formation health at ``frame``'s tick (the world's running values,
    :mod:`protocol.health`) as an HTML table: the tick's formation error, the mean and worst
    so far and the broken ticks (beyond the map's ``formation_tolerance``), a follower with
    broken ticks in red. The first :data:`MAX_RANGE_PLOTS` followers get a row, the others
    one line together. Empty before the first tick."""
    if frame is None:
        return ""
    followers = sorted(k for k in frame.rows if k > 0)
    tolerance = snap.map.get("formation_tolerance") if snap.map else None
    limit = f"{tolerance:g} m" if tolerance is not None else "the tolerance"

    def metres(x: float | None) -> str:
        return "–" if x is None else f"{x:.3g}"

    lines = ["<style>table.health td, table.health th {padding: 1px 14px 1px 0; "
             "text-align: right}</style>"
             "<table class='health' style='border-collapse: collapse'><tr><th>follower</th>"
             "<th>formation error (m)</th><th>mean</th><th>worst</th>"
             f"<th>broken ticks (beyond {limit})</th></tr>"]
    for k in followers[:MAX_RANGE_PLOTS]:
        r = frame.rows[k]
        style = " style='color: #c00000; font-weight: bold'" if r["broken_ticks"] else ""
        missed = " (missed)" if r["missed"] else ""
        lines.append(f"<tr{style}><td>{k}</td><td>{metres(r['formation_error'])}{missed}</td>"
                     f"<td>{metres(r['mean_formation_error'])}</td>"
                     f"<td>{metres(r['worst_formation_error'])}</td>"
                     f"<td>{r['broken_ticks']}</td></tr>")
    lines.append("</table>")
    rest = followers[MAX_RANGE_PLOTS:]
    if rest:
        worst = [w for k in rest if (w := frame.rows[k]["worst_formation_error"]) is not None]
        lines.append(f"followers {rest[0]}–{rest[-1]}: "
                     f"{sum(frame.rows[k]['broken_ticks'] for k in rest)} broken ticks, worst "
                     f"{metres(max(worst, default=None))} m")
    return "".join(lines)


def status_text(snap: Snapshot, frame) -> str:
    """``tick j of n · t = … · status`` (the last tick is ``ticks − 1``); a complete run says
    how many follower-ticks broke the formation up to ``frame``'s tick, if any did."""
    if snap.status == COMPLETE:
        broken = 0 if frame is None else sum(
            row.get("broken_ticks") or 0 for row in frame.rows.values())
        # a broken formation is no success (design §7), whatever the run's end says
        state = (f"complete, formation broken: {broken} follower-ticks beyond the tolerance"
                 if broken else "complete")
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


def legend_item(fig, label: str, renderers: list, glyph: str, style: dict) -> LegendItem:
    """A legend entry for ``renderers`` whose glyph is drawn by a proxy of one point at NaN
    (drawn nowhere) in ``style``: Bokeh draws no legend glyph for a renderer with no data,
    and the map's colours stand for agents, not for what is drawn. Hiding the entry (click)
    hides ``renderers``."""
    nan = [math.nan]
    source = ColumnDataSource(data={"x": nan, "y": nan, "x0": nan, "y0": nan, "x1": nan,
                                    "y1": nan})
    coordinates = ("x0", "y0", "x1", "y1") if glyph == "segment" else ("x", "y")
    proxy = getattr(fig, glyph)(*coordinates, source=source, **style)
    for renderer in renderers:
        proxy.js_link("visible", renderer, "visible")
    return LegendItem(label=label, renderers=[proxy])


def _pick(palette: tuple[str, ...], n: int) -> list[str]:
    return [palette[int(i)] for i in np.linspace(0, len(palette) - 1, n)]


def build_page(doc: Document, store: RunStore, replay: bool) -> None:
    """Bokeh application handler: one :class:`Page` per browser tab."""
    Page(doc, store, replay)
