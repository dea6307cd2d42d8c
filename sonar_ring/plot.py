"""Pictures of a scene, the sensor and the simulated echoes (matplotlib).

Only the command line imports this module, and only when a picture is asked
for, so the numpy core never needs matplotlib.  Figures are drawn on an
off-screen Agg canvas: no display and no pyplot global state.

Everything is drawn in the scene's world frame (m): walls as black lines,
corners as red squares, edges as green triangles, the sensor's receivers as
grey dots and its transmitters as stars, and each echo's reflection point
(where the sound a receiver heard last touched the reflector) as a dot in the
colour of the reflector's class, joined to its receiver by a thin line.
:func:`save_map_png` draws a landmark map over the true scene and the robot's
path (the demo's ``map.png``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from sonar_ring.geometry import Layout
from sonar_ring.landmarks import CORNER_OR_EDGE, UNKNOWN, Landmarks, ellipse_outlines
from sonar_ring.simulate import CLASS_NAMES, CORNER, EDGE, PLANE, Ping, Scene

CLASS_COLOURS = {PLANE: "tab:blue", CORNER: "tab:red", EDGE: "tab:green", CORNER_OR_EDGE: "tab:orange",
                 UNKNOWN: "tab:grey"}
"""Colour of each class code."""


def to_world(points, pose) -> np.ndarray:
    """Sensor-frame points (..., 2) to the world frame for a sensor ``pose`` (x, y, yaw)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.asarray(points) @ np.array([[c, s], [-s, c]]) + pose[:2]


def draw_scene(ax, scene: Scene, prefix: str = "") -> None:
    """Walls, corners and edges of ``scene`` on the axes ``ax``; legend labels start with ``prefix``."""
    for start, end in scene.walls:
        ax.plot([start[0], end[0]], [start[1], end[1]], color="black", linewidth=2.0, solid_capstyle="butt",
                label=f"{prefix}wall")
    if len(scene.corner_point):
        ax.scatter(*scene.corner_point.T, marker="s", s=60, facecolors="none", edgecolors=CLASS_COLOURS[CORNER],
                   linewidths=1.5, label=f"{prefix}corner", zorder=3)
    if len(scene.edges):
        ax.scatter(*scene.edges.T, marker="^", s=60, facecolors="none", edgecolors=CLASS_COLOURS[EDGE],
                   linewidths=1.5, label=f"{prefix}edge", zorder=3)


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
    figure, ax = _world_figure((9, 7.5), dpi=110)
    draw_scene(ax, scene)
    poses = np.array([p.pose for p in pings]).reshape(-1, 3)
    if len(pings) > 1:
        ax.plot(poses[:, 0], poses[:, 1], color="grey", linestyle="--", linewidth=1.0, label="trajectory")
    for ping in pings:
        draw_echoes(ax, ping, layout, rays=len(pings) == 1)
    draw_sensor(ax, layout, poses[0])
    _legend(ax, loc="upper right")
    echoes = sum(p.n_echoes for p in pings)
    return _save(figure, ax, path, title or f"{scene.name} / {layout.name}: {len(pings)} ping(s), {echoes} echoes")


def _world_figure(size, dpi: int):
    """An off-screen figure and its axes, for drawing in the world frame."""
    figure = Figure(figsize=size, dpi=dpi)
    FigureCanvasAgg(figure)
    return figure, figure.add_subplot()


def _save(figure, ax, path, title: str, fontsize: float | None = None) -> Path:
    """Equal axes in metres, the title and a grid; write the PNG and return its path."""
    ax.set_aspect("equal")
    ax.set_xlabel("x [m] (world)")
    ax.set_ylabel("y [m] (world)")
    ax.set_title(title, fontsize=fontsize)
    ax.grid(True, linewidth=0.3)
    figure.tight_layout()
    path = Path(path)
    figure.savefig(path)
    return path


def _legend(ax, **where) -> None:
    """One legend entry per label (walls and ellipses are drawn piece by piece under one label)."""
    handles, labels = ax.get_legend_handles_labels()
    unique = dict(zip(labels, handles, strict=True))
    ax.legend(unique.values(), unique.keys(), fontsize=8, framealpha=0.9, **where)


def draw_map(ax, landmarks: Landmarks, sigma: float = 2.0, magnify: float = 1.0) -> None:
    """A landmark map (world frame) on ``ax``: walls as their observed extent, points with ``sigma`` ellipses.

    Colours by class (:data:`CLASS_COLOURS`); corners, edges and unknown
    reflectors as filled dots; the ellipses drawn ``magnify`` times their size
    (the legend says so).
    """
    walls = landmarks.select(landmarks.valid & (landmarks.landmark_class == PLANE))
    if len(walls):
        ax.add_collection(LineCollection(walls.segment, colors=CLASS_COLOURS[PLANE], linewidths=3.0, alpha=0.75,
                                         label="map: plane", zorder=4))
    points = landmarks.select(landmarks.valid & (landmarks.landmark_class != PLANE))
    for code in (CORNER, EDGE, CORNER_OR_EDGE, UNKNOWN):
        chosen = points.select(points.landmark_class == code)
        if len(chosen):
            ax.scatter(*chosen.position.T, s=14, color=CLASS_COLOURS[code], label=f"map: {CLASS_NAMES[code]}",
                       zorder=5)
    if len(points):
        label = f"map: {sigma:g}σ ellipse" + (f" ×{magnify:g}" if magnify != 1 else "")
        ax.add_collection(LineCollection(ellipse_outlines(points.position, points.covariance, sigma * magnify),
                                         colors=[CLASS_COLOURS[int(c)] for c in points.landmark_class],
                                         linewidths=0.8, label=label, zorder=5))


def visible_magnification(covariance, extent: float, sigma: float = 2.0, share: float = 0.025) -> float:
    """A 1-2-5 magnification that makes the ellipses of a map visible at the scale of the plot.

    The median half-length of the ``sigma`` ellipses of ``covariance`` (L, 2, 2),
    m^2, times the factor is at least ``share`` of ``extent`` (m, the plot's
    size); 1 when it already is.
    """
    if not len(covariance):
        return 1.0
    semi_axis = sigma * float(np.median(np.sqrt(np.clip(np.linalg.eigvalsh(covariance)[:, -1], 0.0, None))))
    wanted = share * extent / max(semi_axis, 1e-12)
    if wanted <= 1.0:
        return 1.0
    decade = 10.0 ** np.floor(np.log10(wanted))
    return float(max(step * decade for step in (1.0, 2.0, 5.0) if step * decade <= wanted))


PATH_STYLES = ({"color": "dimgrey", "linestyle": "--"}, {"color": "tab:orange", "linestyle": "-"},
               {"color": "tab:purple", "linestyle": "-"})
"""Line styles of the robot paths :func:`save_map_png` draws, in order (the truth first)."""


def save_map_png(path, scene: Scene, paths: dict, landmarks: Landmarks, title: str) -> Path:
    """Draw the true scene, robot paths and an estimated map into a PNG file.

    Parameters
    ----------
    path : str or Path
        The PNG to write.
    scene : Scene
        The truth: walls, corners, edges (world frame).
    paths : dict of str to array_like, shape (P, 2) or (P, 3)
        Robot positions (x, y, [yaw]) in the world frame, m, by legend label:
        the true path first, then estimates (the odometry, ...), in the styles
        of :data:`PATH_STYLES`.
    landmarks : Landmarks
        The map, world frame.
    title : str
        Figure title.

    Returns
    -------
    Path
        The file written.
    """
    figure, ax = _world_figure((8.8, 6.0), dpi=100)
    draw_scene(ax, scene, prefix="true ")
    drawn = [np.asarray(robot_path, dtype=float) for robot_path in paths.values()]
    for (label, robot_path), style in zip(zip(paths, drawn, strict=True), PATH_STYLES, strict=False):
        ax.plot(robot_path[:, 0], robot_path[:, 1], linewidth=1.0, label=label, **style)
    ax.plot(*drawn[0][0, :2], marker="o", color="dimgrey", linestyle="none", label="start")
    points = landmarks.select(landmarks.valid & (landmarks.landmark_class != PLANE))
    extent = float(np.ptp(np.concatenate([scene.walls.reshape(-1, 2), *(p[:, :2] for p in drawn)]), axis=0).max())
    draw_map(ax, landmarks, magnify=visible_magnification(points.covariance, extent))
    _legend(ax, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    ax.autoscale_view()
    return _save(figure, ax, path, title, fontsize=10)
