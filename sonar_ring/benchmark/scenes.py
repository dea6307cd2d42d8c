"""The benchmark's standard scenes: simulated ring echoes with their truth, and a bearing sweep.

* :func:`standard_scenes` -- Browne's 48-pair ring (``browne_ring``) in the
  shipped scenes: ``single_wall``, ``single_corner`` and ``single_pole`` seen
  from random poses 0.5-5 m from the reflector (random yaw, so every pair and
  both tiers take part), and one lap of ``room``.  The simulator computes the
  noise-free echoes and their truth once; :meth:`StandardScenes.noisy_tof`
  adds Gaussian time-of-flight noise per level, as ``simulate.Noise(tof=...)``
  does, so every noise level sees the same echoes in the same order.
* :func:`bearing_sweep` -- one pair of the ring and virtual images at bearings
  -80..80 deg and 0.5-5 m: the receivers' +-10 deg acceptance keeps the ring's
  own echoes near the pair axis, and the bearing formulas are to be judged over
  the whole half-plane.

Frames and units: the sensor frame of the ring (REP 103), metres, seconds, radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sonar_ring import simulate
from sonar_ring.geometry import Layout, load_layout, speed_of_sound

RING = "browne_ring"
SINGLE_SCENES = ("single_wall", "single_corner", "single_pole")
NEAREST, FARTHEST = 0.5, 5.0
"""Range of the reflector from the ring centre in the single-reflector scenes, m."""

SWEEP_MAX_BEARING = math.radians(80.0)
SWEEP_SPEED = float(speed_of_sound(20.0, 50.0))
"""Speed of sound of the bearing sweep, m/s (20 degC, 50 % RH, as the single scenes)."""


@dataclass(frozen=True)
class PairRows:
    """Echo rows heard by both receivers of a ring pair, with their truth; N rows, sensor frame.

    Attributes
    ----------
    scene : ndarray of int, shape (N,)
        Index into :attr:`StandardScenes.names`.
    table_row : ndarray of int, shape (N,)
        Row of the scenes' stacked table.
    tx, rx1, rx2 : ndarray, shape (N, 2)
        Horizontal positions of the emitter and the pair's receivers (R1 counter-clockwise), m.
    dz : ndarray, shape (N, 2)
        Emitter minus receiver height, m.
    speed : ndarray, shape (N,)
        Speed of sound of the row's scene, m/s.
    truth_class : ndarray of int, shape (N,)
        PLANE, CORNER or EDGE.
    truth_position : ndarray, shape (N, 2)
        A plane's foot point from the emitter, a corner's or an edge's vertex, m.
    truth_reflection : ndarray, shape (N, 2)
        Where the echo heard by R1 left the reflector (Browne's X for a plane), m.
    yaw, separation, radius : ndarray, shape (N,)
        The pair's facing (rad), receiver separation D and distance R of its
        mid-point from the emitter (m): Browne's pair frame.
    """

    scene: np.ndarray
    table_row: np.ndarray
    tx: np.ndarray
    rx1: np.ndarray
    rx2: np.ndarray
    dz: np.ndarray
    speed: np.ndarray
    truth_class: np.ndarray
    truth_position: np.ndarray
    truth_reflection: np.ndarray
    yaw: np.ndarray
    separation: np.ndarray
    radius: np.ndarray

    def __len__(self) -> int:
        return int(self.scene.size)

    def select(self, index) -> PairRows:
        """The rows picked by a boolean mask or an index array."""
        return PairRows(**{name: value[index] for name, value in vars(self).items()})

    @property
    def truth_range(self) -> np.ndarray:
        """Distance of the true landmark from the emitter (ring centre), shape (N,), m."""
        return np.hypot(*(self.truth_position - self.tx).T)


@dataclass(frozen=True)
class StandardScenes:
    """Noise-free simulated echoes of the ring in the standard scenes.

    Attributes
    ----------
    layout : Layout
        ``browne_ring``.
    names : tuple of str
        Scene names; ``table["scene"]`` indexes them.
    table : dict of str to ndarray
        The stacked pings of all scenes (:func:`sonar_ring.simulate.stack_pings`)
        with ``ping`` numbered across scenes and ``scene`` (N,) per row.
    pairs : PairRows
        The rows of ``table`` heard by both receivers.
    """

    layout: Layout
    names: tuple
    table: dict
    pairs: PairRows

    def noisy_tof(self, sigma_tof: float, rng: np.random.Generator) -> np.ndarray:
        """Times of flight of every table row with independent Gaussian noise, shape (N, 2), s."""
        tof = self.table["tof"]
        return tof + rng.normal(0.0, sigma_tof, tof.shape) if sigma_tof > 0 else tof.copy()

    def paths(self, tof: np.ndarray) -> np.ndarray:
        """Path lengths ``c * tof`` of :attr:`pairs` from times of flight of every table row, (N_pairs, 2), m."""
        return self.pairs.speed[:, None] * tof[self.pairs.table_row]


def sweep_poses(scene: simulate.Scene, count: int, rng: np.random.Generator) -> np.ndarray:
    """Sensor poses ``(x, y, yaw)`` seeing a single-reflector scene's reflector from 0.5-5 m, shape (count, 3).

    Corner scenes: within 30 deg of the corner's bisector, inside it; edge scenes:
    any direction; wall scenes: in front of the wall (the side of the scene's
    ``sensor_pose``), along its middle 3/4.  Yaw is uniform.
    """
    distance = rng.uniform(NEAREST, FARTHEST, count)
    yaw = rng.uniform(0.0, 2.0 * math.pi, count)
    if len(scene.corner_point):
        bisector = scene.corner_arm[0].sum(axis=0)
        centre = math.atan2(bisector[1], bisector[0])
        angle = centre + rng.uniform(-math.radians(30.0), math.radians(30.0), count)
        origin = scene.corner_point[0]
    elif len(scene.edges):
        angle = rng.uniform(0.0, 2.0 * math.pi, count)
        origin = scene.edges[0]
    else:
        start, end = scene.walls[0]
        along = end - start
        normal = np.array([-along[1], along[0]]) / np.hypot(*along)
        if np.dot(scene.sensor_pose[:2] - start, normal) < 0:
            normal = -normal
        origin = start[None, :] + rng.uniform(0.125, 0.875, count)[:, None] * along
        return np.column_stack([origin + distance[:, None] * normal, yaw])
    offset = np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    return np.column_stack([origin + distance[:, None] * offset, yaw])


def _pair_rows(layout: Layout, table: dict) -> PairRows:
    complete = np.flatnonzero(np.all(np.isfinite(table["tof"]), axis=1))
    group = table["group"][complete]
    transmitter = layout.transmitters[table["transmitter"][complete]]
    receivers = layout.receivers[layout.groups[group]]
    tx = transmitter[:, :2]
    middle = receivers[:, :, :2].mean(axis=1)
    facing = middle - tx
    speed = table["speed_of_sound"][table["ping"][complete]]
    return PairRows(
        scene=table["scene"][complete],
        table_row=complete,
        tx=tx,
        rx1=receivers[:, 0, :2],
        rx2=receivers[:, 1, :2],
        dz=transmitter[:, None, 2] - receivers[:, :, 2],
        speed=speed,
        truth_class=table["truth_class"][complete],
        truth_position=table["truth_position"][complete],
        truth_reflection=table["truth_reflection_point"][complete, 0],
        yaw=np.arctan2(facing[:, 1], facing[:, 0]),
        separation=np.hypot(*(receivers[:, 1, :2] - receivers[:, 0, :2]).T),
        radius=np.hypot(*facing.T),
    )


def standard_scenes(poses_per_scene: int, room_stride: int, rng: np.random.Generator) -> StandardScenes:
    """Simulate the ring in the standard scenes, noise-free.

    Parameters
    ----------
    poses_per_scene : int
        Pings in each single-reflector scene (:func:`sweep_poses`).
    room_stride : int
        Every ``room_stride``-th pose of the room's lap at the ring's ping rate
        (1: the whole lap, 1240 pings).
    rng : numpy.random.Generator
        Draws the poses.
    """
    layout = load_layout(RING)
    names, tables = [], []
    for name in (*SINGLE_SCENES, "room"):
        scene = simulate.load_scene(name)
        if name == "room":
            poses = scene.trajectory.poses(layout.ping_rate)[1][::room_stride]
        else:
            poses = sweep_poses(scene, poses_per_scene, rng)
        tables.append(simulate.stack_pings(simulate.Simulator(scene, layout).run(poses)))
        names.append(name)
    offsets = np.cumsum([0] + [len(t["speed_of_sound"]) for t in tables[:-1]])
    table = {key: np.concatenate([t[key] for t in tables]) for key in tables[0] if key != "ping"}
    table["ping"] = np.concatenate([t["ping"] + offset for t, offset in zip(tables, offsets, strict=True)])
    table["scene"] = np.concatenate([np.full(t["group"].size, k) for k, t in enumerate(tables)])
    return StandardScenes(layout, tuple(names), table, _pair_rows(layout, table))


@dataclass(frozen=True)
class BearingSweep:
    """Path lengths of virtual images seen by pair 0 of the ring over a wide range of bearings.

    Attributes
    ----------
    tx, rx1, rx2 : ndarray, shape (2,)
        Emitter and receivers, m, sensor frame (the pair faces +x).
    separation : float
        D, m.
    bearing : ndarray, shape (N,)
        True bearing of the virtual image at R1 from the pair's axis (Browne's
        phi_1, counter-clockwise positive), rad.
    distance : ndarray, shape (N,)
        Distance of the virtual image from R1, m.
    d1, d2 : ndarray, shape (N,)
        Exact path lengths (computed in extended precision, rounded), m.
    speed : float
        Speed of sound, m/s.
    """

    tx: np.ndarray
    rx1: np.ndarray
    rx2: np.ndarray
    separation: float
    bearing: np.ndarray
    distance: np.ndarray
    d1: np.ndarray
    d2: np.ndarray
    speed: float

    def noisy_paths(self, sigma_tof: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``(d1, d2)`` with independent Gaussian time-of-flight noise ``sigma_tof`` (s), m."""
        if sigma_tof == 0:
            return self.d1, self.d2
        sigma_path = self.speed * sigma_tof
        return (self.d1 + rng.normal(0.0, sigma_path, self.d1.shape),
                self.d2 + rng.normal(0.0, sigma_path, self.d2.shape))


def bearing_sweep(count: int, rng: np.random.Generator) -> BearingSweep:
    """Virtual images at uniform bearings in +-80 deg and distances 0.5-5 m from R1 of the ring's pair 0."""
    layout = load_layout(RING)
    rx1, rx2 = layout.group_receivers()[0, :, :2]
    tx = layout.transmitters[layout.group_transmitters[0, 0], :2]
    bearing = rng.uniform(-SWEEP_MAX_BEARING, SWEEP_MAX_BEARING, count)
    distance = rng.uniform(NEAREST, FARTHEST, count)
    exact = np.longdouble
    image = rx1.astype(exact) + distance.astype(exact)[:, None] * np.stack(
        [np.cos(bearing.astype(exact)), np.sin(bearing.astype(exact))], axis=-1)
    d2 = np.sqrt(np.sum(np.square(image - rx2.astype(exact)), axis=-1)).astype(float)
    return BearingSweep(tx, rx1, rx2, float(np.hypot(*(rx2 - rx1))), bearing, distance, distance.copy(), d2,
                        SWEEP_SPEED)


def ring_scene(kind: str, range_m: float) -> simulate.Scene:
    """One reflector straight ahead of the sensor: ``wall``, ``pole`` or ``corner`` at ``range_m`` (m).

    The wall is 20 m long; the corner's arms, 1.5 ``range_m`` long, open towards the sensor.
    """
    if kind == "wall":
        reflectors = [{"type": "wall", "name": "wall", "from": [range_m, -10.0], "to": [range_m, 10.0]}]
    elif kind == "pole":
        reflectors = [{"type": "edge", "name": "pole", "at": [range_m, 0.0]}]
    else:
        arm = 1.5 * range_m / math.sqrt(2)
        reflectors = [{"type": "wall", "name": "left", "from": [range_m, 0.0], "to": [range_m - arm, arm]},
                      {"type": "wall", "name": "right", "from": [range_m, 0.0], "to": [range_m - arm, -arm]},
                      {"type": "corner", "name": "corner", "walls": ["left", "right"]}]
    return simulate.load_scene({"name": f"{kind}_{range_m}", "reflectors": reflectors})
