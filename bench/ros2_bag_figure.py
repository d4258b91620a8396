"""The picture of an exported bag (``python bench/ros2_bag_figure.py [--bag BAG] [--out PNG]``).

Without ``--bag`` it runs a 3-follower ``wavy`` case (40 ticks, agents in-process) and exports
it. Then it reads the bag back with rosbags and draws, from its messages alone (no run folder,
no surface): the terrain mesh of the first ``/swarm/markers`` message, every agent's poses
(``/swarm/agent_<k>/pose``) and the rods (line strips of ``/swarm/markers``) every 8th tick,
in 3-D and from above. Default output: ``docs/figures/ros2_bag.png``.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from protocol import ros2  # noqa: E402
from protocol.config import LENGTH  # noqa: E402

ROD_EVERY = 8


def read_bag(bag: Path) -> tuple[np.ndarray, np.ndarray, dict[int, np.ndarray], list]:
    """Terrain triangles (m, 3, 3) and colours (m, 3), each agent's positions (n, 3), and the
    rods (tick index, list of (p, 3) points) of every ``/swarm/markers`` message of a tick
    (not a terrain's)."""
    from rosbags.rosbag2 import Reader

    store = ros2.typestore()
    poses: dict[int, list] = {}
    markers = []
    with Reader(bag) as reader:
        for connection, _, raw in reader.messages():
            topic = connection.topic
            if topic == ros2.MARKERS[0]:
                markers.append(store.deserialize_cdr(raw, connection.msgtype))
            elif topic.startswith("/swarm/agent_") and topic.endswith("/pose"):
                agent = int(topic.split("/")[2].removeprefix("agent_"))
                p = store.deserialize_cdr(raw, connection.msgtype).pose.position
                poses.setdefault(agent, []).append((p.x, p.y, p.z))
    [terrain] = markers[0].markers
    vertices = np.array([(v.x, v.y, v.z) for v in terrain.points]).reshape(-1, 3, 3)
    colors = np.array([(c.r, c.g, c.b) for c in terrain.colors]).reshape(-1, 3, 3).mean(axis=1)
    ticks = [array for array in markers  # the terrain is recorded again every 5 s
             if all(m.ns != "terrain" for m in array.markers)]
    rods = [(j, [np.array([(p.x, p.y, p.z) for p in m.points]) for m in array.markers
                 if m.ns == "rods"]) for j, array in enumerate(ticks)]
    return vertices, colors, {k: np.array(v) for k, v in sorted(poses.items())}, rods


def draw(bag: Path, out: Path) -> Path:
    from world.ros2 import agent_color

    vertices, colors, poses, rods = read_bag(bag)
    fig = plt.figure(figsize=(13, 5.6))
    # drawn in this order (matplotlib's depth sorting would hide trails behind the mesh)
    ax3 = fig.add_subplot(1, 2, 1, projection="3d", computed_zorder=False)
    ax3.add_collection3d(Poly3DCollection(vertices, facecolors=colors, edgecolors="none",
                                          alpha=0.8, zorder=1))
    top = fig.add_subplot(1, 2, 2)
    top.tripcolor(vertices[:, :, 0].ravel(), vertices[:, :, 1].ravel(),
                  np.arange(vertices.shape[0] * 3).reshape(-1, 3),
                  facecolors=vertices[:, :, 2].mean(axis=1), cmap="gist_earth", alpha=0.6,
                  shading="flat")
    for k, path in poses.items():
        color = agent_color(k, len(poses))
        label = "leader" if k == 0 else f"follower {k}"
        ax3.plot(*path.T, color=color, lw=2 if k == 0 else 1.3, label=label, zorder=3)
        top.plot(path[:, 0], path[:, 1], color=color, lw=2 if k == 0 else 1.3, label=label)
    for j, strips in rods:
        if j % ROD_EVERY and j != len(rods) - 1:
            continue
        for strip in strips:
            ax3.plot(*strip.T, color="crimson", lw=1.6, zorder=4)
            top.plot(strip[:, 0], strip[:, 1], color="crimson", lw=1.6)
    lo, hi = vertices.reshape(-1, 3).min(axis=0), vertices.reshape(-1, 3).max(axis=0)
    ax3.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2] + 0.5),
            xlabel=f"x ({LENGTH})", ylabel=f"y ({LENGTH})", zlabel=f"z = F(x, y) ({LENGTH})")
    ax3.view_init(elev=38, azim=-120)
    ax3.set_title("terrain mesh, poses and rods (every 8th tick), 3-D")
    top.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), aspect="equal", xlabel=f"x ({LENGTH})",
            ylabel=f"y ({LENGTH})", title="from above; rods in red")
    top.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=len(poses), fontsize=9)
    fig.suptitle(f"Read back from the exported bag alone: {bag.name} ({len(poses) - 1} "
                 f"followers, {len(rods)} ticks)")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bag", type=Path, help="an exported bag (default: run and export one)")
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "figures" / "ros2_bag.png")
    args = p.parse_args()
    if args.bag is not None:
        print(f"figure: {draw(args.bag, args.out)}")
        return
    from protocol.config import RunConfig
    from swarm.launch import launch
    from swarm.ros2_export import export_run

    with tempfile.TemporaryDirectory(prefix="ros2-figure-") as tmp:
        run = Path(tmp) / "wavy-3"
        summary = launch(RunConfig(run_id="ros2-figure", surface="wavy", followers=3,
                                   ticks=40), run, in_process=True)
        if not summary["complete"]:
            raise RuntimeError(summary["reason"])
        print(f"figure: {draw(export_run(run), args.out)}")


if __name__ == "__main__":
    main()
