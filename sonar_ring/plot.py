"""Pictures of a scene, the sensor and the simulated echoes (matplotlib).

Only the command line imports this module, and only when a picture is asked
for, so the numpy core never needs matplotlib.  Figures are drawn on an
off-screen Agg canvas: no display and no pyplot global state.

Everything is drawn in the scene's world frame (m): walls as black lines,
corners as red squares, edges as green triangles, the sensor's receivers as
grey dots and its transmitters as stars, and each echo's reflection point
(where the sound a receiver heard last touched the reflector) as a dot in the
colour of the reflector's class, joined to its receiver by a thin line.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from sonar_ring.geometry import Layout
from sonar_ring.simulate import CLASS_NAMES, CORNER, EDGE, PLANE, Ping, Scene

CLASS_COLOURS = {PLANE: "tab:blue", CORNER: "tab:red", EDGE: "tab:green"}
"""Colour of each reflector class code."""


def to_world(points, pose) -> np.ndarray:
    """Sensor-frame points (..., 2) to the world frame for a sensor ``pose`` (x, y, yaw)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.asarray(points) @ np.array([[c, s], [-s, c]]) + pose[:2]


def draw_scene(ax, scene: Scene) -> None:
    """Walls, corners and edges of ``scene`` on the axes ``ax``."""
    for start, end in scene.walls:
        ax.plot([start[0], end[0]], [start[1], end[1]], color="black", linewidth=2.0, solid_capstyle="butt")
    if len(scene.corner_point):
        ax.scatter(*scene.corner_point.T, marker="s", s=60, facecolors="none", edgecolors=CLASS_COLOURS[CORNER],
                   linewidths=1.5, label="corner", zorder=3)
    if len(scene.edges):
        ax.scatter(*scene.edges.T, marker="^", s=60, facecolors="none", edgecolors=CLASS_COLOURS[EDGE],
                   linewidths=1.5, label="edge", zorder=3)


def draw_sensor(ax, layout: Layout, pose) -> None:
    """The layout's receivers, transmitters and facing at ``pose`` (x, y, yaw)."""
    receivers = to_world(layout.receivers[:, :2], pose)
    transmitters = to_world(layout.transmitters[:, :2], pose)
    ax.scatter(*receivers.T, s=6, color="dimgrey", zorder=4, label="receivers")
    ax.scatter(*transmitters.T, marker="*", s=90, color="black", zorder=5, label="transmitters")
    heading = pose[:2] + 0.25 * np.array([np.cos(pose[2]), np.sin(pose[2])])
    ax.annotate("", xy=heading, xytext=pose[:2], arrowprops=dict(arrowstyle="->", color="black"), zorder=5)


def draw_echoes(ax, ping: Ping, layout: Layout, rays: bool = True) -> None:
    """Reflection points of a ping's echoes, coloured by the true class.

    Parameters
    ----------
    ax : matplotlib Axes
    ping : Ping
        A simulated ping (sensor-frame reflection points and its true pose).
    layout : Layout
        The layout the ping came from (receiver positions for the rays).
    rays : bool
        Also draw a thin line from each receiver to the point it heard.
    """
    for code, colour in CLASS_COLOURS.items():
        rows = ping.truth_class == code
        if not rows.any():
            continue
        points = ping.truth_reflection_point[rows]  # (n, K, 2)
        heard = np.isfinite(points[..., 0])
        world = to_world(points[heard], ping.pose)
        if rays:
            receivers = layout.receivers[layout.groups[ping.group[rows]]][..., :2][heard]
            start = to_world(receivers, ping.pose)
            ax.plot(np.stack([start[:, 0], world[:, 0]]), np.stack([start[:, 1], world[:, 1]]),
                    color=colour, linewidth=0.4, alpha=0.5)
        ax.scatter(*world.T, s=14 if rays else 3, color=colour, zorder=6, label=f"{CLASS_NAMES[code]} echo")


def save_png(path, scene: Scene, layout: Layout, pings, title: str | None = None) -> Path:
    """Draw the scene, the sensor and the echoes of ``pings`` into a PNG file.

    One ping: the sensor at its pose with a ray per heard echo.  Several pings
    (a trajectory): the path, the sensor at the first pose and the reflection
    points of every ping, without rays.

    Returns
    -------
    Path
        The file written.
    """
    figure = Figure(figsize=(9, 7.5), dpi=110)
    FigureCanvasAgg(figure)
    ax = figure.add_subplot()
    draw_scene(ax, scene)
    poses = np.array([p.pose for p in pings]).reshape(-1, 3)
    if len(pings) > 1:
        ax.plot(poses[:, 0], poses[:, 1], color="grey", linestyle="--", linewidth=1.0, label="trajectory")
    for ping in pings:
        draw_echoes(ax, ping, layout, rays=len(pings) == 1)
    draw_sensor(ax, layout, poses[0])
    handles, labels = ax.get_legend_handles_labels()
    unique = dict(zip(labels, handles, strict=True))
    ax.legend(unique.values(), unique.keys(), loc="upper right", fontsize=8, framealpha=0.9)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m] (world)")
    ax.set_ylabel("y [m] (world)")
    echoes = sum(p.n_echoes for p in pings)
    ax.set_title(title or f"{scene.name} / {layout.name}: {len(pings)} ping(s), {echoes} echoes")
    ax.grid(True, linewidth=0.3)
    path = Path(path)
    figure.savefig(path)
    return path
