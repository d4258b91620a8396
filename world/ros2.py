"""A run as ROS 2 messages (design §10): built from the world's tick rows, published live on the
run's Zenoh session the way rmw_zenoh does, or written to a bag (``swarm/ros2_export.py``).

:class:`RosScene` turns each completed tick's rows (``WorldSim.finish_tick``, or ``ticks.csv``
read back) into the messages of every topic of :func:`protocol.ros2.run_topics`, a drive run's
control steps (``WorldSim.control_rows``, or ``controls.csv``) into ``cmd_vel`` twists, and
draws the terrain as a triangle mesh (sent again every :data:`TERRAIN_EVERY_S`).
:class:`Ros2Publisher` publishes them, with the key expressions, attachments and liveliness
tokens of :mod:`protocol.ros2`.

Frames and poses: frame ``map`` is the world's x, y and ``z = F(x, y)``. An agent at ``p`` with
heading ``h`` (xy) has the pose whose position is ``(x, y, F(x, y))`` and whose orientation is
the rotation taking the axes of ``map`` to: x along the heading lifted into the tangent plane,
``(h_x, h_y, ∇F·h)`` normalised; z the upward unit normal ``(−F_x, −F_y, 1)/√(1 + |∇F|²)``;
y = z × x. Its yaw (about ``map``'s z) is therefore ``atan2(h_y, h_x)``, and on a flat surface
the orientation is that yaw alone. Stamps are simulation time ``t_j`` (``builtin_interfaces``
seconds and nanoseconds, nanoseconds rounded).
"""
from __future__ import annotations

import math
import time
from collections.abc import Iterable, Sequence

import numpy as np
import zenoh

from protocol import ros2
from protocol.health import HEALTH_COLUMNS
from protocol.session import undeclare_all
from world import geometry
from world.surfaces import Surface
from world.view import grid_shape, height_grid, map_box

EXPORT_ROD_PIECES, LIVE_ROD_PIECES = 8, 4
"""Straight pieces per rod line strip (the rod's geodesic sampled at pieces + 1 points)."""
EXPORT_TERRAIN_CELLS = 100 * 100
LIVE_TERRAIN_CELLS = 48 * 48
"""Terrain mesh nodes: at most 100 × 100 in a bag; 48 × 48 live (a 0.5 MB sample, well under
the 1 MiB a router accepts)."""
LIVE_PATH_POSES = 16
"""Live ``/path`` samples carry the last this many settled poses (a trail; a bag carries them
all): one sample per agent and tick stays small and cheap however long the run."""
TERRAIN_EVERY_S = 5.0
"""The terrain marker is sent again every this many seconds (live: of the wall clock, at
most this often; in a bag: of simulation time), so a viewer that starts late, or a player
that seeks, gets it (:class:`Period`)."""
_TERRAIN_COLORS = np.array([[0.16, 0.42, 0.20], [0.62, 0.52, 0.34], [0.93, 0.93, 0.90]])


class Period:
    """Whether something is due on a clock: the first call, then once ``seconds`` have gone
    by since it was last due.

    >>> due = Period(5.0)
    >>> [t for t in (0.0, 1.28, 5.0, 6.4, 10.24) if due(t)]
    [0.0, 5.0, 10.24]
    """

    def __init__(self, seconds: float) -> None:
        if not (isinstance(seconds, (int, float)) and math.isfinite(seconds) and seconds > 0):
            raise ValueError(f"seconds must be a finite number > 0, got {seconds!r}")
        self.seconds, self._last = float(seconds), -math.inf

    def __call__(self, now: float) -> bool:
        if now - self._last < self.seconds:
            return False
        self._last = now
        return True


def stamp_parts(t: float) -> tuple[int, int]:
    """``(sec, nanosec)`` of simulation time ``t`` >= 0, nanoseconds rounded.

    >>> stamp_parts(1.28)
    (1, 280000000)
    """
    if not (math.isfinite(t) and t >= 0):
        raise ValueError(f"a stamp needs a finite time >= 0, got {t!r}")
    sec = math.floor(t)
    nanosec = round((t - sec) * 1e9)
    return (sec + 1, 0) if nanosec >= 1_000_000_000 else (sec, nanosec)


def stamp_ns(t: float) -> int:
    """Simulation time ``t`` in integer nanoseconds (a bag's record time)."""
    sec, nanosec = stamp_parts(t)
    return sec * 1_000_000_000 + nanosec


def surface_quaternion(gradient: Sequence[float], heading: Sequence[float]
                       ) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` (w >= 0) of an agent's frame: x the heading lifted into the tangent
    plane, z the upward surface normal, y = z × x (see the module docstring)."""
    fx, fy = float(gradient[0]), float(gradient[1])
    hx, hy = float(heading[0]), float(heading[1])
    hz = fx * hx + fy * hy
    norm = math.sqrt(hx * hx + hy * hy + hz * hz)
    if not (norm > 0 and math.isfinite(norm)):
        raise ValueError(f"heading must be a nonzero finite vector, got {(hx, hy)}")
    x = (hx / norm, hy / norm, hz / norm)
    scale = 1.0 / math.sqrt(1.0 + fx * fx + fy * fy)
    z = (-fx * scale, -fy * scale, scale)
    y = (z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0])
    return quaternion(((x[0], y[0], z[0]), (x[1], y[1], z[1]), (x[2], y[2], z[2])))


def quaternion(m: Sequence[Sequence[float]]) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` (w >= 0) of a rotation matrix ``m`` (rows)."""
    trace = m[0][0] + m[1][1] + m[2][2]
    if trace > 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = ((m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s, s / 4)
    else:
        i = max(range(3), key=lambda k: m[k][k])
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[i][i] - m[j][j] - m[k][k])
        v = [0.0, 0.0, 0.0]
        v[i], v[j], v[k] = s / 4, (m[j][i] + m[i][j]) / s, (m[k][i] + m[i][k]) / s
        q = (*v, (m[k][j] - m[j][k]) / s)
    sign = -1.0 if q[3] < 0 else 1.0
    return tuple(sign * c for c in q)  # type: ignore[return-value]


def agent_color(agent: int, n_agents: int) -> tuple[float, float, float]:
    """The leader black, the followers from blue to orange along the column."""
    if agent == 0:
        return (0.05, 0.05, 0.05)
    f = (agent - 1) / max(1, n_agents - 2)
    blue, orange = np.array([0.12, 0.47, 0.71]), np.array([1.0, 0.5, 0.05])
    return tuple(float(c) for c in (1 - f) * blue + f * orange)  # type: ignore[return-value]


def terrain_colors(z: np.ndarray) -> np.ndarray:
    """RGB (n, 3) of heights ``z``: low green, middle brown, high near white."""
    z = np.asarray(z, dtype=float)
    low, high = float(np.nanmin(z)), float(np.nanmax(z))
    f = (z - low) / (high - low) if high > low else np.zeros_like(z)
    pos = np.clip(f, 0.0, 1.0) * (len(_TERRAIN_COLORS) - 1)
    i = np.minimum(pos.astype(int), len(_TERRAIN_COLORS) - 2)
    w = (pos - i)[:, None]
    return _TERRAIN_COLORS[i] * (1 - w) + _TERRAIN_COLORS[i + 1] * w


def terrain_triangles(surface: Surface, points: np.ndarray, spacing: float,
                      cells: int) -> tuple[np.ndarray, np.ndarray]:
    """The terrain under ``points`` (any shape ending in 2) as a triangle list.

    The box of :func:`world.view.map_box` is sampled on a grid of at most ``cells`` nodes
    (:func:`world.view.grid_shape`); every grid cell with four heights (inside the surface's
    domain) gives two triangles. Returns the vertices (3·m, 3) and their heights' colours
    (3·m, 3).
    """
    low, high = map_box(points, spacing)
    ny, nx = grid_shape(low, high, cells)
    z = height_grid(surface, low, high, (ny, nx))
    xs, ys = np.linspace(low[0], high[0], nx), np.linspace(low[1], high[1], ny)
    gx, gy = np.meshgrid(xs, ys)
    nodes = np.stack([gx, gy, z], axis=-1)
    a, b = nodes[:-1, :-1], nodes[:-1, 1:]  # each cell: a b / c d (a south-west)
    c, d = nodes[1:, :-1], nodes[1:, 1:]
    ok = np.isfinite(np.stack([a[..., 2], b[..., 2], c[..., 2], d[..., 2]])).all(axis=0)
    tri = np.concatenate([np.stack([a[ok], b[ok], d[ok]], axis=1),
                          np.stack([a[ok], d[ok], c[ok]], axis=1)]).reshape(-1, 3)
    return tri, terrain_colors(tri[:, 2])


class RosScene:
    """Builds one run's ROS 2 messages tick by tick (rosbags' Jazzy types).

    Parameters
    ----------
    config : RunConfig
        The resolved configuration (followers, spacing, side).
    surface : Surface
    path_window : int, optional
        ``/path`` carries the last ``path_window`` poses (None: every pose so far).
    rod_pieces : int
        Straight pieces of each rod's line strip.
    """

    def __init__(self, config, surface: Surface, path_window: int | None = None,
                 rod_pieces: int = EXPORT_ROD_PIECES) -> None:
        store = ros2.typestore()
        self.types = store.types
        self.serialize = store.serialize_cdr
        self.config, self.surface = config, surface
        self.n_agents = config.followers + 1
        self.path_window, self.rod_pieces = path_window, rod_pieces
        self._paths: list[list] = [[] for _ in range(self.n_agents)]
        self._colors = [self._color(*agent_color(k, self.n_agents)) for k in range(self.n_agents)]

    # --- small message pieces ------------------------------------------------------------------

    def _color(self, r: float, g: float, b: float, a: float = 1.0):
        return self.types["std_msgs/msg/ColorRGBA"](r=float(r), g=float(g), b=float(b),
                                                    a=float(a))

    def header(self, t: float):
        sec, nanosec = stamp_parts(t)
        T = self.types
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=sec, nanosec=nanosec), frame_id=ros2.FRAME)

    def point(self, x: float, y: float, z: float):
        return self.types["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=float(z))

    def height(self, x: float, y: float) -> float:
        """``F(x, y)``; NaN where the surface refuses the point (outside its domain)."""
        try:
            return float(self.surface.height(np.array([x, y])))
        except ValueError:
            return math.nan

    def _pose(self, row: dict) -> tuple[tuple[float, float, float], tuple]:
        """Position and orientation quaternion of an agent's row."""
        x, y = row["pos_x"], row["pos_y"]
        p = np.array([x, y])
        orientation = surface_quaternion(self.surface.gradient(p),
                                         (row["heading_x"], row["heading_y"]))
        return (float(x), float(y), float(self.surface.height(p))), orientation

    # --- messages ------------------------------------------------------------------------------

    def tick_messages(self, rows: Sequence[dict]) -> list[tuple[str, str, object]]:
        """``(topic, type, message)`` of one tick (rows in agent order), in the order of
        :func:`protocol.ros2.run_topics`, markers included: ``/clock`` and ``/tf`` once;
        per agent its pose and path, for a follower its ideal position, and on estimated
        ticks its estimate and required range; ``/swarm/markers`` with the agents and rods;
        last ``/diagnostics`` (:meth:`diagnostics`: the rows carry each follower's formation
        health so far, :meth:`protocol.health.ColumnHealth.add_tick`)."""
        if len(rows) != self.n_agents or [r["agent"] for r in rows] != list(range(self.n_agents)):
            raise ValueError(f"a tick needs one row per agent 0..{self.n_agents - 1} in order")
        T = self.types
        header = self.header(rows[0]["t"])
        poses = [self._pose(row) for row in rows]
        Vector3, Quaternion = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
        quats = [Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]) for _, q in poses]
        out: list[tuple[str, str, object]] = [
            (*ros2.CLOCK, T["rosgraph_msgs/msg/Clock"](clock=header.stamp)),
            (*ros2.TF, T["tf2_msgs/msg/TFMessage"](transforms=[
                T["geometry_msgs/msg/TransformStamped"](
                    header=header, child_frame_id=f"agent_{k}",
                    transform=T["geometry_msgs/msg/Transform"](
                        translation=Vector3(x=pos[0], y=pos[1], z=pos[2]), rotation=quat))
                for k, ((pos, _), quat) in enumerate(zip(poses, quats, strict=True))]))]
        markers = self._markers(rows, header, poses)
        for k, (row, ((x, y, z), _), quat) in enumerate(zip(rows, poses, quats, strict=True)):
            stamped = T["geometry_msgs/msg/PoseStamped"](
                header=header, pose=T["geometry_msgs/msg/Pose"](position=self.point(x, y, z),
                                                                orientation=quat))
            path = self._paths[k]
            path.append(stamped)
            if self.path_window is not None and len(path) > self.path_window:
                del path[0]
            out.append((ros2.agent_topic(k, "pose"), ros2.AGENT_TOPICS["pose"][0], stamped))
            out.append((ros2.agent_topic(k, "path"), ros2.AGENT_TOPICS["path"][0],
                        T["nav_msgs/msg/Path"](header=header, poses=list(path))))
            if k == 0:
                continue
            out.append(self._point_stamped(k, "ideal", header, row["ideal_x"], row["ideal_y"]))
            if row.get("est_x") is not None:
                out.append(self._point_stamped(k, "estimate", header, row["est_x"], row["est_y"]))
                out.append((ros2.agent_topic(k, "required_range"),
                            ros2.AGENT_TOPICS["required_range"][0],
                            T["std_msgs/msg/Float64"](data=float(row["required_range"]))))
        out.append((*ros2.MARKERS, markers))
        out.append((*ros2.DIAGNOSTICS, self.diagnostics(rows, header)))
        return out

    def diagnostics(self, rows: Sequence[dict], header):
        """The ``/diagnostics`` message of one tick: per follower a ``DiagnosticStatus``
        named ``swarm_world: agent_<k> formation`` (hardware id ``agent_<k>``) whose values are
        the tick's formation error and the follower's :data:`protocol.health.HEALTH_COLUMNS`
        so far (the rows must carry them: :meth:`protocol.health.ColumnHealth.add_tick`), each
        as ``repr`` of the number (a float64 round trip; empty for none), with the tolerance
        and whether it missed the tick. Level ``ERROR`` while it stands beyond the tolerance,
        ``WARN`` once back within it after a broken tick (the run's verdict is failed
        already), ``OK`` while no tick broke; ``ERROR`` too at a tick without a formation
        error (its ideal place is off the surface's domain), which counts as broken."""
        T = self.types
        Status, KeyValue = T["diagnostic_msgs/msg/DiagnosticStatus"], T[
            "diagnostic_msgs/msg/KeyValue"]
        tolerance = self.config.formation_tolerance
        statuses = []
        for row in rows[1:]:
            missing = [name for name in HEALTH_COLUMNS if name not in row]
            if missing:
                raise ValueError(f"agent {row['agent']}'s row has no {', '.join(missing)}: "
                                 "count the tick with protocol.health.ColumnHealth.add_tick")
            error, broken = row.get("formation_error"), row["broken_ticks"]
            if error is None:
                level, message = Status.ERROR, ("its ideal place is off the surface's domain: "
                                                "not in formation")
            elif error > tolerance:
                level = Status.ERROR
                message = f"{error:.3g} m from its place, beyond {tolerance:g} m"
            elif broken:
                level, message = Status.WARN, (f"within {tolerance:g} m; the formation broke at "
                                               f"{broken} of its ticks")
            else:
                level, message = Status.OK, f"within {tolerance:g} m"
            if row.get("missed"):
                message += " (missed this tick)"
            values = {"formation_error": error, **{n: row[n] for n in HEALTH_COLUMNS},
                      "formation_tolerance": tolerance, "missed": int(row.get("missed") or 0)}
            statuses.append(Status(
                level=level, name=f"{ros2.NODE_NAME}: agent_{row['agent']} formation",
                message=message, hardware_id=f"agent_{row['agent']}",
                values=[KeyValue(key=key, value=_text(value)) for key, value in values.items()]))
        return T[ros2.DIAGNOSTICS[1]](header=header, status=statuses)

    def control_messages(self, controls: Sequence[dict]) -> list[tuple[str, str, object, float]]:
        """``(topic, type, message, stamp)`` of one tick's control steps (``controls.csv``
        rows, in their order): on ``/swarm/agent_<k>/cmd_vel`` a ``geometry_msgs/msg/Twist``
        in the robot's frame (``agent_<k>``: x along its heading, z its surface normal) with
        ``linear.x`` the commanded speed and ``angular.z`` the commanded turn rate, stamped
        (a twist has no header: the bag's record time) with the step's time ``t``."""
        T = self.types
        Vector3 = T["geometry_msgs/msg/Vector3"]
        msgtype = ros2.AGENT_TOPICS["cmd_vel"][0]
        return [(ros2.agent_topic(c["agent"], "cmd_vel"), msgtype,
                 T[msgtype](linear=Vector3(x=float(c["speed"]), y=0.0, z=0.0),
                            angular=Vector3(x=0.0, y=0.0, z=float(c["turn"]))), c["t"])
                for c in controls]

    def _point_stamped(self, agent: int, name: str, header, x: float, y: float):
        msg = self.types["geometry_msgs/msg/PointStamped"](
            header=header, point=self.point(x, y, self.height(x, y)))
        return ros2.agent_topic(agent, name), ros2.AGENT_TOPICS[name][0], msg

    def _marker(self, header, ns: str, marker_id: int, kind: int, points: list, *,
                width: float, color, colors: Iterable = ()):
        T = self.types
        M = T["visualization_msgs/msg/Marker"]
        return M(header=header, ns=ns, id=marker_id, type=kind, action=M.ADD,
                 pose=T["geometry_msgs/msg/Pose"](
                     position=self.point(0, 0, 0),
                     orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
                 scale=T["geometry_msgs/msg/Vector3"](x=width, y=width, z=width), color=color,
                 lifetime=T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
                 frame_locked=False, points=points, colors=list(colors),
                 texture_resource="", texture=T["sensor_msgs/msg/CompressedImage"](
                     header=header, format="", data=np.zeros(0, dtype=np.uint8)),
                 uv_coordinates=[], text="", mesh_resource="",
                 mesh_file=T["visualization_msgs/msg/MeshFile"](
                     filename="", data=np.zeros(0, dtype=np.uint8)),
                 mesh_use_embedded_materials=False)

    def rod_points(self, holder: dict) -> list:
        """The rod ``holder`` (a row) holds, sampled along its geodesic; empty if the geodesic
        cannot be followed (it leaves the surface's domain)."""
        p = np.array([holder["pos_x"], holder["pos_y"]])
        try:
            v = geometry.rod_normal(self.surface, p, (holder["heading_x"], holder["heading_y"]),
                                    self.config.side_sign)
            samples = geometry.geodesic_points(self.surface, p, v, self.config.spacing,
                                               self.rod_pieces)
        except geometry.SurfaceDomainError:
            return []
        return [self.point(x, y, self.surface.height(xy)) for xy, (x, y) in
                zip(samples, samples.tolist(), strict=True)]

    def _markers(self, rows: Sequence[dict], header, poses: list):
        M = self.types["visualization_msgs/msg/Marker"]
        d = self.config.spacing
        agents = self._marker(header, "agents", 0, M.SPHERE_LIST,
                              [self.point(*pos) for pos, _ in poses], width=0.25 * d,
                              color=self._colors[0], colors=self._colors)
        rods = [self._marker(header, "rods", k, M.LINE_STRIP, self.rod_points(rows[k - 1]),
                             width=0.04 * d, color=self._color(0.85, 0.1, 0.1))
                for k in range(1, self.n_agents)]
        return self.types["visualization_msgs/msg/MarkerArray"](markers=[agents, *rods])

    def terrain(self, points: np.ndarray, cells: int, t: float = 0.0):
        """``/swarm/markers`` message holding the terrain under ``points`` as one
        TRIANGLE_LIST marker (namespace ``terrain``), per-vertex colours by height."""
        M = self.types["visualization_msgs/msg/Marker"]
        vertices, colors = terrain_triangles(self.surface, points, self.config.spacing, cells)
        marker = self._marker(self.header(t), "terrain", 0, M.TRIANGLE_LIST,
                              [self.point(*v) for v in vertices], width=1.0,
                              color=self._color(1, 1, 1), colors=[self._color(*c) for c in colors])
        return self.types["visualization_msgs/msg/MarkerArray"](markers=[marker])


def _text(value: float | int | None) -> str:
    """A diagnostic value: an integer as such, a number as the ``repr`` of its float64 (read
    back exactly with ``float``), none as empty.

    >>> [_text(3), _text(np.float64(0.1)), _text(None)]
    ['3', '0.1', '']
    """
    if value is None:
        return ""
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return str(int(value))
    return repr(float(value))


class Ros2Publisher:
    """Publishes a run's ROS 2 topics on an open Zenoh session, as rmw_zenoh would: one node
    ``/swarm_world`` (entity 0) with one publisher per topic (entities 1, 2, … in the order of
    :func:`protocol.ros2.run_topics`; a drive run's followers' ``cmd_vel`` included), each
    with its liveliness token, its key expression, the CDR payload and the attachment (its own
    sequence number from 1, the wall clock in ns, its GID). Samples are sent with congestion
    control DROP, reliably (rmw_zenoh's choice for a reliable keep-last publisher): a slow
    ROS 2 subscriber never holds up the run.

    Parameters
    ----------
    session : zenoh.Session
    config : RunConfig
        ``ros_domain`` names the domain; ``motion`` ``drive`` adds the ``cmd_vel`` topics.
    surface : Surface
    ideal : ndarray, shape (n_agents, n_ticks, 2)
        The ideal formation: the terrain covers its box.
    """

    def __init__(self, session: zenoh.Session, config, surface: Surface,
                 ideal: np.ndarray) -> None:
        self.scene = RosScene(config, surface, path_window=LIVE_PATH_POSES,
                              rod_pieces=LIVE_ROD_PIECES)
        domain, followers = config.ros_domain, config.followers
        drive = config.drives
        node, *tokens = ros2.world_tokens(domain, followers, str(session.zid()), drive=drive)
        self._publishers: dict[str, tuple] = {}
        self._declared: list = [session.liveliness().declare_token(node)]
        for (topic, _), key, token in zip(ros2.run_topics(followers, drive),
                                          ros2.world_keys(domain, followers, drive=drive),
                                          tokens, strict=True):
            publisher = session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.DROP,
                reliability=zenoh.Reliability.RELIABLE)
            self._declared += [publisher, session.liveliness().declare_token(token)]
            self._publishers[topic] = (publisher, ros2.gid(token), [1])
        terrain = self.scene.terrain(ideal, LIVE_TERRAIN_CELLS)
        self._terrain = bytes(self.scene.serialize(terrain, ros2.MARKERS[1]))
        self._terrain_due = Period(TERRAIN_EVERY_S)

    def _put(self, topic: str, payload: bytes) -> None:
        publisher, source, sequence = self._publishers[topic]
        publisher.put(payload, attachment=ros2.attachment(sequence[0], time.time_ns(), source))
        sequence[0] += 1

    def publish_tick(self, rows: Sequence[dict], controls: Sequence[dict] = ()) -> None:
        """Publish one completed tick (ticks in order) from what it recorded: its rows (with
        the formation health the recorder counted, ``RunRecorder.add_tick``), then
        its control steps (``cmd_vel``, each robot's in step order); and the terrain when it
        is due."""
        if self._terrain_due(time.monotonic()):
            self._put(ros2.MARKERS[0], self._terrain)
        for topic, msgtype, message in self.scene.tick_messages(rows):
            self._put(topic, bytes(self.scene.serialize(message, msgtype)))
        for topic, msgtype, message, _ in self.scene.control_messages(controls):
            self._put(topic, bytes(self.scene.serialize(message, msgtype)))

    def undeclare(self) -> None:
        undeclare_all(self._declared)
