"""Scenes and a physically based forward model for the three sensors.

A *scene* lists its reflectors -- walls (vertical planes given as segments),
right-angle corners where two walls meet, and edges (convex junctions, poles,
chair legs: vertical lines) -- all extruded vertically without limit.  The
forward model computes, for one sensor pose, what the hardware would report:
for every receiver group, every transmitter of the group and every reflector
that returns an echo, the time of flight at each receiver of the group, the
amplitude and (for Kreczmer triads) the phase delays; and with every echo the
ground truth that produced it.  Only the listed reflectors echo: there are no
higher-order reflections beyond a corner's double bounce.  What a robot measures
beside that -- multipath, spurious and late echoes, missed echoes, the wrong
speed of sound, drifting odometry -- is added by :mod:`sonar_ring.realism`, which
builds on the steps of :meth:`Simulator.ping` (:meth:`~Simulator.place`,
:meth:`~Simulator.hear`, :meth:`~Simulator.measure`, :meth:`~Simulator.echo_rows`).

Physics, exact for vertically extruded reflectors (horizontal distances are
taken in the scene's (x, y) plane, ``dz`` is transmitter minus receiver height):

* wall: image ``T'`` of the transmitter in the wall line, horizontal path
  ``|T' - R|``; the echo exists only when ``T`` and ``R`` are on the same side
  and the reflection point (where ``R T'`` crosses the wall line) lies on the
  segment;
* corner: double reflection, ``T'' = 2 C - T``, horizontal path ``|T'' - R|``;
  the echo exists only when ``T`` and ``R`` are inside the corner's quadrant
  and both reflection points lie on the two walls' segments;
* edge: diffraction at the edge point ``P``, horizontal path ``|T - P| + |P - R|``;
* every path: ``d = sqrt(h**2 + dz**2)``; blocked when any of its horizontal
  legs crosses a wall of the scene; dropped beyond the receive window
  ``d > 2 * layout.max_range``.

Amplitudes follow Barshan & Kuc (1990): the product of the transmit and the
receive gain (their eq 4), each ``exp(-2 alpha**2 / theta0**2)`` (eq 3) of the
horizontal angle ``alpha`` between the leg and the transducer's axis, with
``theta0 = asin(0.61 lambda / a)`` (eq 2; 90 deg when ``0.61 lambda / a >= 1``,
where the piston has no first null).  This reproduces their eqs 5-11.  The
ring's emitter is isotropic (gain 1).  A receiver hears nothing beyond its
acceptance half-angle ``layout.beam_half_angle``, and a directional transmitter
(the same kind of transducer) sends nothing beyond it.  Each reflector class has a
relative reflectivity (defaults :data:`DEFAULT_REFLECTIVITY`; Barshan & Kuc
note edges echo much more weakly than planes and corners).  A time-variable
gain is assumed, as in the paper, so amplitudes do not fall with range, and
``A_max = 1`` is the amplitude of a plane at normal incidence on the axes of
both transducers.  Amplitudes below the detection threshold (default -30 dB,
the paper's) are not reported.

Noise (:class:`Noise`): Gaussian time-of-flight noise, amplitude noise (the
paper's sigma = 2 % of ``A_max``), zero-crossing jitter for the phase delays,
and an optional timer that truncates times to whole ticks (Kreczmer's 0.33 us).
Random numbers come only from the ``numpy.random.Generator`` passed in.

Frames and units: scenes live in a world (``odom``) frame; a pose is the sensor
frame's ``(x, y, yaw)`` in it (m, m, rad); everything a :class:`Ping` returns is
in the sensor frame (m, s, rad; REP 103).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from sonar_ring import image_method
from sonar_ring.compiled import kernel
from sonar_ring.echoes import EchoArrays
from sonar_ring.geometry import Layout, config_path, read_config, speed_of_sound

# The class codes of Landmark.msg, defined once in sonar_ring.landmarks; re-exported
# because ground truth is labelled with them.
from sonar_ring.landmarks import CLASS_NAMES as CLASS_NAMES
from sonar_ring.landmarks import CORNER as CORNER
from sonar_ring.landmarks import EDGE as EDGE
from sonar_ring.landmarks import PLANE as PLANE
from sonar_ring.landmarks import UNKNOWN as UNKNOWN

# --------------------------------------------------------------------------- constants

REFLECTOR_TYPES = {"wall": PLANE, "corner": CORNER, "edge": EDGE}
"""Scene-file reflector ``type`` and the class code of its echoes."""

DIRECT, MULTIPATH, SPURIOUS, LATE = 0, 1, 2, 3
"""Where an echo row came from (:attr:`Ping.truth_origin`): a reflector of the scene, or none of them --
a double bounce, clutter, or the previous ping's echo (:mod:`sonar_ring.realism`)."""

ORIGIN_NAMES = ("direct", "multipath", "spurious", "late")
"""Name of each origin code, indexable by the code."""

DEFAULT_REFLECTIVITY = {"plane": 1.0, "corner": 1.0, "edge": 0.3}
"""Relative echo strength per class; a scene file may override any of them."""

DEFAULT_THRESHOLD = 10.0 ** (-30.0 / 20.0)
"""Detection threshold, relative to ``A_max``: -30 dB (Barshan & Kuc, section II)."""


class SceneError(ValueError):
    """A scene file or mapping is malformed; the message names file and field."""


# --------------------------------------------------------------------------- scene

@dataclass(frozen=True)
class Trajectory:
    """A robot path through a scene, sampled at a ping rate.

    Attributes
    ----------
    waypoints : ndarray, shape (P, 2)
        Way points in the world frame, m; the sensor moves along straight
        lines between them at constant speed.
    speed : float
        Speed along the path, m/s.
    loop : bool
        True to return from the last way point to the first (one lap).
    yaw : float or None
        Fixed sensor yaw, rad (a rail or a sideways-moving robot); None to face
        along the direction of travel.
    turn_rate : float
        Facing the direction of travel, the robot turns on the spot at each way
        point at this rate, rad/s (a loop also turns back to its first leg at
        the end of the lap).
    """

    waypoints: np.ndarray
    speed: float
    loop: bool
    yaw: float | None
    turn_rate: float = math.radians(60.0)

    def poses(self, rate: float) -> tuple[np.ndarray, np.ndarray]:
        """Sample one pass of the path at ``rate`` pings per second.

        Parameters
        ----------
        rate : float
            Pings per second, Hz (normally ``layout.ping_rate``).

        Returns
        -------
        times : ndarray, shape (N,)
            Ping times from the start, s.
        poses : ndarray, shape (N, 3)
            Sensor pose ``(x, y, yaw)`` at each time, world frame, m and rad.
        """
        points = np.vstack([self.waypoints, self.waypoints[:1]]) if self.loop else self.waypoints
        legs = np.diff(points, axis=0)
        heading = np.arctan2(legs[:, 1], legs[:, 0])
        # The way points' knots: (time, x, y, yaw) at the start and end of every leg and turn.
        turns = np.zeros(len(legs) + 1)  # before each leg, and after the last
        if self.yaw is None:
            turns[1:-1] = np.remainder(np.diff(heading) + np.pi, 2.0 * np.pi) - np.pi
            if self.loop:
                turns[-1] = np.remainder(heading[0] - heading[-1] + np.pi, 2.0 * np.pi) - np.pi
        knot_time, knot = [0.0], [[*points[0], heading[0] if self.yaw is None else self.yaw]]
        for index, leg in enumerate(legs):
            yaw = knot[-1][2]
            if turns[index]:
                knot_time.append(knot_time[-1] + abs(turns[index]) / self.turn_rate)
                yaw = yaw + turns[index]
                knot.append([*points[index], yaw])
            knot_time.append(knot_time[-1] + math.hypot(*leg) / self.speed)
            knot.append([*points[index + 1], yaw])
        if turns[-1]:
            knot_time.append(knot_time[-1] + abs(turns[-1]) / self.turn_rate)
            knot.append([*points[-1], knot[-1][2] + turns[-1]])
        knot_time, knot = np.array(knot_time), np.array(knot)
        # A loop's last sample would repeat the first; an open path ends on its last way point.
        count = int(math.floor(knot_time[-1] * rate + 1e-9)) + (0 if self.loop else 1)
        time = np.arange(count) / rate
        x, y, yaw = (np.interp(time, knot_time, knot[:, axis]) for axis in range(3))
        return time, np.column_stack([x, y, np.remainder(yaw + np.pi, 2.0 * np.pi) - np.pi])


@dataclass(frozen=True)
class Scene:
    """Reflectors, air and an optional trajectory, in the world frame.

    Reflector index ``f`` (``truth_reflector`` of a ping) counts the file's
    ``reflectors`` list in order; ``kind_index[f]`` is its row in ``walls``,
    ``corner_point`` (and the other corner arrays) or ``edges``, whichever its
    class says.

    Attributes
    ----------
    name : str
        Scene name (the YAML file stem by convention).
    reflector_names : tuple of str
        Name of each reflector, shape (F,).
    reflector_class : ndarray of int, shape (F,)
        :data:`PLANE`, :data:`CORNER` or :data:`EDGE` for each reflector.
    kind_index : ndarray of int, shape (F,)
        Row of each reflector in the array of its kind.
    walls : ndarray, shape (W, 2, 2)
        Wall segments ``[[x0, y0], [x1, y1]]``, m.  Every wall also blocks paths.
    corner_point : ndarray, shape (C, 2)
        Corner vertices, m.
    corner_arm : ndarray, shape (C, 2, 2)
        Unit vectors along the corner's two walls, away from the vertex.
    corner_arm_length : ndarray, shape (C, 2)
        Length of those walls, m.
    corner_walls : ndarray of int, shape (C, 2)
        Row in ``walls`` of each corner's two walls.
    edges : ndarray, shape (E, 2)
        Edge (vertical line) positions, m.
    reflectivity : ndarray, shape (4,)
        Relative echo strength indexed by class code (UNKNOWN unused).
    temperature_c : float
        Air temperature, degC.
    relative_humidity : float
        Relative humidity, percent.
    sensor_pose : ndarray, shape (3,)
        Default sensor pose ``(x, y, yaw)``, m and rad.
    trajectory : Trajectory or None
        Robot path for mapping runs, if the scene has one.
    realism : dict of str to float
        The scene file's ``realism:`` block: fields of
        :class:`sonar_ring.realism.Realism` that replace a profile's for this
        scene (checked by :func:`sonar_ring.realism.profile`).
    """

    name: str
    reflector_names: tuple
    reflector_class: np.ndarray
    kind_index: np.ndarray
    walls: np.ndarray
    corner_point: np.ndarray
    corner_arm: np.ndarray
    corner_arm_length: np.ndarray
    corner_walls: np.ndarray
    edges: np.ndarray
    reflectivity: np.ndarray
    temperature_c: float
    relative_humidity: float
    sensor_pose: np.ndarray
    trajectory: Trajectory | None
    realism: dict = field(default_factory=dict)

    @property
    def n_reflectors(self) -> int:
        """Number of reflectors F."""
        return len(self.reflector_names)

    @property
    def speed_of_sound(self) -> float:
        """Speed of sound in the scene's air, m/s."""
        return float(speed_of_sound(self.temperature_c, self.relative_humidity))


def scene_path(name: str) -> Path:
    """Path of a shipped scene by name, e.g. ``scene_path("room")``."""
    return config_path("scenes", name)


def load_scene(source) -> Scene:
    """Load a scene from a shipped name, a YAML path or a mapping.

    Raises
    ------
    SceneError
        Naming the file, the field and the expected value on any problem.
    """
    mapping, where = read_config(source, "scenes", SceneError)
    if where != "<mapping>":
        mapping.setdefault("name", Path(where).stem)
    return _scene_from_mapping(mapping, where)


_SCENE_KEYS = {"name", "description", "temperature_c", "relative_humidity", "reflectivity",
               "sensor_pose", "reflectors", "trajectory", "realism"}
_REFLECTOR_KEYS = {"wall": {"type", "name", "from", "to"},
                   "corner": {"type", "name", "walls"},
                   "edge": {"type", "name", "at"}}


def _number(value, where, field, low=-math.inf, high=math.inf, low_open=False):
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise SceneError(f"{where}: field '{field}' must be a number, got {value!r}") from None
    too_low = number <= low if low_open else number < low
    if not math.isfinite(number) or too_low or number > high:
        bound = f"{'>' if low_open else '>='} {low}" if math.isfinite(low) else "finite"
        upper = f" and <= {high}" if math.isfinite(high) else ""
        raise SceneError(f"{where}: field '{field}' must be a number {bound}{upper}, got {value!r}")
    return number


MAX_COORDINATE = 1e6
"""Largest |coordinate| of a scene, m (and |yaw|, deg): beyond it a value is a typing error, and would overflow."""


def _point(value, where, field, size=2):
    if not (isinstance(value, list | tuple) and len(value) == size):
        shape = "[x, y]" if size == 2 else "[x, y, yaw_deg]"
        raise SceneError(f"{where}: field '{field}' must be {shape} in m, got {value!r}")
    return [_number(v, where, field, low=-MAX_COORDINATE, high=MAX_COORDINATE) for v in value]


def _scene_from_mapping(m: dict, where: str) -> Scene:
    unknown = set(m) - _SCENE_KEYS
    if unknown:
        first = sorted(unknown, key=str)[0]
        raise SceneError(f"{where}: unknown field {first!r} (expected some of {sorted(_SCENE_KEYS)})")
    temperature = _number(m.get("temperature_c", 20.0), where, "temperature_c", low=-273.15, low_open=True)
    humidity = _number(m.get("relative_humidity", 0.0), where, "relative_humidity", low=0.0, high=100.0)
    reflectivity = dict(DEFAULT_REFLECTIVITY)
    given = m.get("reflectivity", {})
    if not isinstance(given, dict) or set(given) - set(reflectivity):
        raise SceneError(f"{where}: field 'reflectivity' must map some of {sorted(reflectivity)} "
                         f"to numbers in (0, 1], got {given!r}")
    for cls, value in given.items():
        reflectivity[cls] = _number(value, where, f"reflectivity.{cls}", low=0.0, high=1.0, low_open=True)
    pose = _point(m.get("sensor_pose", [0.0, 0.0, 0.0]), where, "sensor_pose", size=3)
    pose[2] = math.radians(pose[2])

    items = m.get("reflectors")
    if not isinstance(items, list) or not items:
        raise SceneError(f"{where}: field 'reflectors' must be a non-empty list of {{type: wall|corner|edge, ...}}")
    names, classes, kind_index = [], [], []
    walls, wall_rows, edges, corner_specs = [], {}, [], []
    for k, item in enumerate(items):
        here = f"{where}: reflectors[{k}]"
        if not isinstance(item, dict) or not isinstance(item.get("type"), str) or item["type"] not in REFLECTOR_TYPES:
            got = item.get("type") if isinstance(item, dict) else item
            raise SceneError(f"{here}: field 'type' must be one of {', '.join(REFLECTOR_TYPES)}, got {got!r}")
        kind = item["type"]
        extra = set(item) - _REFLECTOR_KEYS[kind]
        if extra:
            raise SceneError(f"{here}: unknown field {sorted(extra, key=str)[0]!r} for a {kind} "
                             f"(expected {sorted(_REFLECTOR_KEYS[kind])})")
        name = str(item.get("name", f"{kind}{k}"))
        if name in names:
            raise SceneError(f"{here}: field 'name' must be unique, {name!r} is used twice")
        names.append(name)
        classes.append(REFLECTOR_TYPES[kind])
        if kind == "wall":
            start, end = _point(item.get("from"), here, "from"), _point(item.get("to"), here, "to")
            if start == end:
                raise SceneError(f"{here}: fields 'from' and 'to' must differ (a wall needs a length)")
            wall_rows[name] = len(walls)
            kind_index.append(len(walls))
            walls.append([start, end])
        elif kind == "edge":
            kind_index.append(len(edges))
            edges.append(_point(item.get("at"), here, "at"))
        else:
            kind_index.append(len(corner_specs))
            corner_specs.append((here, item.get("walls")))

    walls = np.array(walls, dtype=float).reshape(-1, 2, 2)
    corner_point, corner_arm, corner_length, corner_walls = _corners(corner_specs, walls, wall_rows)
    trajectory = _trajectory(m["trajectory"], f"{where}: trajectory") if "trajectory" in m else None
    return Scene(
        name=str(m.get("name", Path(where).stem)),
        reflector_names=tuple(names),
        reflector_class=np.array(classes, dtype=int),
        kind_index=np.array(kind_index, dtype=int),
        walls=walls,
        corner_point=corner_point,
        corner_arm=corner_arm,
        corner_arm_length=corner_length,
        corner_walls=corner_walls,
        edges=np.array(edges, dtype=float).reshape(-1, 2),
        reflectivity=np.array([0.0, reflectivity["plane"], reflectivity["corner"], reflectivity["edge"]]),
        temperature_c=temperature,
        relative_humidity=humidity,
        sensor_pose=np.array(pose),
        trajectory=trajectory,
        realism=_realism_block(m.get("realism", {}), where),
    )


def _realism_block(block, where: str) -> dict:
    """The ``realism:`` block: names to numbers (:func:`sonar_ring.realism.profile` checks names and ranges)."""
    if not isinstance(block, dict) or not all(isinstance(key, str) for key in block):
        raise SceneError(f"{where}: field 'realism' must map effect fields to numbers, got {block!r}")
    return {key: _number(value, where, f"realism.{key}") for key, value in block.items()}


def _corners(specs, walls, wall_rows):
    """Vertex, arms and arm lengths of each corner from the two walls it names.

    The walls must share an end point (the vertex) and be perpendicular; the
    corner reflects between them on the side their other ends lie on.
    """
    point, arm, length, rows = [], [], [], []
    for here, pair in specs:
        if not (isinstance(pair, list) and len(pair) == 2 and all(str(n) in wall_rows for n in pair)):
            raise SceneError(f"{here}: field 'walls' must name two walls of the scene, got {pair!r}")
        first, second = (walls[wall_rows[str(n)]] for n in pair)
        gaps = np.linalg.norm(first[:, None, :] - second[None, :, :], axis=-1)
        i, j = np.unravel_index(np.argmin(gaps), gaps.shape)
        if gaps[i, j] > 1e-9:
            raise SceneError(f"{here}: field 'walls': {pair[0]!r} and {pair[1]!r} must share an end point "
                             f"(closest ends are {gaps[i, j]:.3g} m apart)")
        arms = np.array([first[1 - i] - first[i], second[1 - j] - second[j]])
        lengths = np.linalg.norm(arms, axis=-1)
        if not (np.all(np.isfinite(lengths)) and np.all(lengths > 0)):
            raise SceneError(f"{here}: field 'walls': {pair[0]!r} and {pair[1]!r} must have lengths a float can "
                             f"hold, got {float(lengths[0])!r} and {float(lengths[1])!r} m")
        arms = arms / lengths[:, None]
        if abs(arms[0] @ arms[1]) > 1e-9:
            angle = math.degrees(math.acos(np.clip(arms[0] @ arms[1], -1, 1)))
            raise SceneError(f"{here}: field 'walls': {pair[0]!r} and {pair[1]!r} must meet at 90 deg, "
                             f"they meet at {angle:.6g} deg")
        point.append(first[i])
        arm.append(arms)
        length.append(lengths)
        rows.append([wall_rows[str(n)] for n in pair])
    return (np.array(point, dtype=float).reshape(-1, 2), np.array(arm, dtype=float).reshape(-1, 2, 2),
            np.array(length, dtype=float).reshape(-1, 2), np.array(rows, dtype=int).reshape(-1, 2))


MAX_LAP_SECONDS = 3600.0
"""Longest lap of a scene trajectory, s: the simulator samples a lap's poses at once (2000 Hz: 7.2 M poses)."""


def _trajectory(t, where) -> Trajectory:
    if not isinstance(t, dict) or set(t) - {"waypoints", "speed", "loop", "yaw_deg", "turn_rate_deg"}:
        raise SceneError(f"{where}: expected a mapping with 'waypoints', 'speed' and optional 'loop', 'yaw_deg', "
                         "'turn_rate_deg'")
    points = t.get("waypoints")
    if not isinstance(points, list) or len(points) < 2:
        raise SceneError(f"{where}: field 'waypoints' must be a list of at least two [x, y], got {points!r}")
    waypoints = np.array([_point(p, where, f"waypoints[{k}]") for k, p in enumerate(points)])
    if np.any(np.all(np.diff(waypoints, axis=0) == 0, axis=1)):
        raise SceneError(f"{where}: field 'waypoints' must not repeat a point twice in a row")
    loop = t.get("loop", True)
    if not isinstance(loop, bool):
        raise SceneError(f"{where}: field 'loop' must be true or false, got {loop!r}")
    yaw = t.get("yaw_deg")
    speed = _number(t.get("speed"), where, "speed", low=0.0, low_open=True)
    path = np.vstack([waypoints, waypoints[:1]]) if loop else waypoints
    with np.errstate(over="ignore"):
        length = float(np.sum(np.hypot(*np.diff(path, axis=0).T)))
    if not length / speed <= MAX_LAP_SECONDS:  # the driver samples a whole lap of poses at start
        raise SceneError(f"{where}: field 'speed' must make one lap last at most {MAX_LAP_SECONDS:g} s "
                         f"(the path is {length:.6g} m long), got {speed!r}")
    turn_rate = _number(t.get("turn_rate_deg", 60.0), where, "turn_rate_deg", low=0.0, high=3600.0, low_open=True)
    return Trajectory(
        waypoints=waypoints,
        speed=speed,
        loop=loop,
        yaw=None if yaw is None else math.radians(_number(yaw, where, "yaw_deg")),
        turn_rate=math.radians(turn_rate),
    )


# --------------------------------------------------------------------------- ping

@dataclass(frozen=True)
class Noise:
    """Measurement noise of a simulated sensor; all zero means exact data.

    Attributes
    ----------
    tof : float
        Standard deviation of each receiver's time of flight, s.
    amplitude : float
        Standard deviation of each amplitude, relative to ``A_max``
        (Barshan & Kuc measured 0.02).
    phase : float
        Standard deviation of each receiver's rising zero-crossing time, s;
        the phase delays of a triad take it twice (receiver k and receiver 0).
    timer : float
        Timer tick, s (Kreczmer: 0.33e-6); 0 disables.  Times are counted in
        whole ticks of a free-running clock whose phase at the ping is uniform
        (drawn per ping), so a reading is unbiased with an error under one tick;
        truncating the true time instead would bias every reading by -tick/2.
    """

    tof: float = 0.0
    amplitude: float = 0.0
    phase: float = 0.0
    timer: float = 0.0

    def __post_init__(self):
        for name in ("tof", "amplitude", "phase", "timer"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"Noise: field '{name}' must be a finite number >= 0, got {value!r}")

    @property
    def random(self) -> bool:
        """True when any random noise is switched on (a generator is needed)."""
        return self.tof > 0 or self.amplitude > 0 or self.phase > 0 or self.timer > 0


NOISE_FREE = Noise()
"""Exact times of flight, amplitudes and phase delays."""


@dataclass(frozen=True)
class Ping:
    """Everything one ping of one sensor reports, plus the truth behind it.

    One row is one echo from one reflector, heard by the K receivers of group
    ``group[n]`` after transmitter ``transmitter[n]`` fired.  Rows are sorted by
    group, transmitter, then arrival time (earliest receiver).  All positions are
    in the sensor frame.

    Attributes
    ----------
    layout : str
        Name of the layout the indices refer to.
    time : float
        Time of the ping (from the start of a run), s.
    pose : ndarray, shape (3,)
        True sensor pose ``(x, y, yaw)`` in the world frame, m and rad.
    speed_of_sound : float
        Speed of sound of the air the echoes travelled in, m/s.
    group : ndarray of int, shape (N,)
        Receiver group index in the layout.
    transmitter : ndarray of int, shape (N,)
        Index into ``layout.transmitters`` of the transmitter that fired.
    tof : ndarray, shape (N, K)
        Time of flight transmitter -> reflector -> receiver k, s; NaN where
        receiver k of the group did not hear this echo.
    amplitude : ndarray, shape (N, K)
        Echo amplitude relative to ``A_max``; NaN where not heard.
    phase_delay : ndarray, shape (N, K - 1) for triads, else (N, 0)
        Kreczmer's ``t0k``: time from receiver 0's rising zero crossing to the
        next rising zero crossing of receiver k, i.e. ``(arrival_k - arrival_0)``
        modulo one carrier period ``1 / layout.frequency``, in ``[0, period)``, s.
        NaN where receiver 0 or receiver k did not hear the echo.
    truth_reflector : ndarray of int, shape (N,)
        Index of the reflector in the scene's ``reflectors`` list; -1 for an
        echo of no reflector (``truth_origin`` not :data:`DIRECT`).
    truth_class : ndarray of int, shape (N,)
        :data:`PLANE`, :data:`CORNER` or :data:`EDGE`; :data:`UNKNOWN` for an
        echo of no reflector.
    truth_origin : ndarray of int, shape (N,)
        :data:`DIRECT` (a reflector of the scene), or what made an echo of no
        reflector: :data:`MULTIPATH`, :data:`SPURIOUS`, :data:`LATE`
        (:mod:`sonar_ring.realism`).
    truth_position : ndarray, shape (N, 2)
        The landmark as the localiser defines it, m: for a plane the foot point
        ``G = (T + T') / 2`` of the perpendicular from the transmitter that fired
        to the wall line; for a corner or an edge, its vertex.
    truth_normal : ndarray, shape (N, 2)
        Planes: unit normal of the wall pointing from the wall to the
        transmitter's side (``(T - T') / |T - T'|``); NaN for corners and edges.
    truth_reflection_point : ndarray, shape (N, K, 2)
        Where the echo heard by receiver k last touched the reflector (the
        point a receiver "sees"), m; NaN where not heard.  Truth positions,
        normals and reflection points are NaN for an echo of no reflector.
    """

    layout: str
    time: float
    pose: np.ndarray
    speed_of_sound: float
    group: np.ndarray
    transmitter: np.ndarray
    tof: np.ndarray
    amplitude: np.ndarray
    phase_delay: np.ndarray
    truth_reflector: np.ndarray
    truth_class: np.ndarray
    truth_origin: np.ndarray
    truth_position: np.ndarray
    truth_normal: np.ndarray
    truth_reflection_point: np.ndarray

    @property
    def n_echoes(self) -> int:
        """Number of echo rows N."""
        return int(self.group.shape[0])

    @property
    def echoes(self) -> EchoArrays:
        """What the hardware would report of this ping (no ground truth)."""
        return EchoArrays(layout=self.layout, speed_of_sound=self.speed_of_sound, group=self.group,
                          transmitter=self.transmitter, tof=self.tof, amplitude=self.amplitude,
                          phase_delay=self.phase_delay)


PING_ROW_FIELDS = ("group", "transmitter", "tof", "amplitude", "phase_delay", "truth_reflector",
                   "truth_class", "truth_origin", "truth_position", "truth_normal", "truth_reflection_point")
"""Fields of :class:`Ping` with one entry per echo row."""


def stack_pings(pings) -> dict:
    """Concatenate the rows of several pings into one table of arrays.

    Parameters
    ----------
    pings : sequence of Ping
        Pings of one layout.

    Returns
    -------
    dict of str to ndarray
        Every field of :data:`PING_ROW_FIELDS` with the rows of all pings in
        order, ``ping`` (N,) the index of the ping each row came from, and the
        per-ping ``time`` (P,), ``pose`` (P, 3) and ``speed_of_sound`` (P,).
    """
    if not pings:
        raise ValueError("stack_pings: need at least one ping")
    table = {name: np.concatenate([getattr(p, name) for p in pings]) for name in PING_ROW_FIELDS}
    table["ping"] = np.repeat(np.arange(len(pings)), [p.n_echoes for p in pings])
    table["time"] = np.array([p.time for p in pings])
    table["pose"] = np.array([p.pose for p in pings]).reshape(-1, 3)
    table["speed_of_sound"] = np.array([p.speed_of_sound for p in pings])
    return table


def transducer_half_angle(layout: Layout, speed: float) -> float:
    """Gaussian beam half-angle ``theta0`` of the layout's transducers, rad.

    Barshan & Kuc eq 2, ``asin(0.61 lambda / a)`` with ``lambda = speed /
    layout.frequency``; 90 deg for transducers so small (``0.61 lambda >= a``)
    that the piston has no first null, such as Kreczmer's 10 mm receivers.
    """
    ratio = 0.61 * layout.wavelength(speed) / layout.aperture_radius
    return float(np.arcsin(min(ratio, 1.0)))


def _cross(u, v):
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _dot(u, v):
    return u[..., 0] * v[..., 0] + u[..., 1] * v[..., 1]


def _angle_off_axis(direction, axis):
    """Signed angle from unit ``axis`` to ``direction`` (both (..., 2)), rad."""
    return np.arctan2(_cross(axis, direction), _dot(axis, direction))


@dataclass
class Paths:
    """Echo paths of one family (a reflector kind, or an effect's), broadcast over (F, G, M, K).

    F counts the family's members (reflectors, or an effect's paths), G the
    receiver groups, M a group's transmitter slots and K its receivers.

    Attributes
    ----------
    source : ndarray of int, shape (F,)
        Row key of each member: the reflector's index in the scene, or an
        effect's own number (at least the scene's reflector count), so each
        member's echoes make rows of their own.
    strength : ndarray, shape (F,)
        Echo strength of each member before the beam gains, relative to
        ``A_max`` (a reflector's reflectivity; an effect's product of them and
        its losses).
    origin : int
        :data:`DIRECT` for the scene's reflectors, else the effect's origin code.
    horizontal : ndarray, shape (F, G, M, K)
        Horizontal path length transmitter -> member -> receiver, m.
    exists : ndarray of bool, shape (F, G, M, K)
        Where the path is geometrically possible.
    out_point, in_point : ndarray, shape (F, G, M, K, 2) or broadcastable
        Where the transmitted ray first meets the member and where the received
        ray last leaves it, world frame, m (beam angles, the truth's reflection point).
    legs : list of (start, end)
        Horizontal legs of the path, each end broadcastable to (F, G, M, K, 2);
        a wall crossing any of them blocks the path.
    truth_position, truth_normal : ndarray, shape (F, G, M, 2)
        Ground truth of the landmark the member makes (see :class:`Ping`); NaN for effects.
    """

    source: np.ndarray
    strength: np.ndarray
    origin: int
    horizontal: np.ndarray
    exists: np.ndarray
    out_point: np.ndarray
    in_point: np.ndarray
    legs: list
    truth_position: np.ndarray
    truth_normal: np.ndarray


@dataclass(frozen=True)
class Placement:
    """The sensor's transducers in the world frame at one pose (what every path family needs).

    Attributes
    ----------
    pose : ndarray, shape (3,)
        Sensor pose ``(x, y, yaw)``, world frame, m and rad.
    rotation : ndarray, shape (2, 2)
        Sensor-to-world rotation by ``yaw``.
    tx : ndarray, shape (G, M, 2)
        Each group's transmitters, m.
    rx : ndarray, shape (G, K, 2)
        Each group's receivers, m.
    tx_axis : ndarray, shape (G, M, 1, 2)
        Unit vectors along the transmitters' axes.
    rx_axis : ndarray, shape (G, 1, K, 2)
        Unit vectors along the receivers' axes.
    """

    pose: np.ndarray
    rotation: np.ndarray
    tx: np.ndarray
    rx: np.ndarray
    tx_axis: np.ndarray
    rx_axis: np.ndarray


@dataclass(frozen=True)
class Heard:
    """Paths a receiver hears (or, after :meth:`Simulator.measure`, reports), one entry per path and receiver.

    Attributes
    ----------
    source : ndarray of int, shape (n,)
        Row key (:attr:`Paths.source`).
    origin : ndarray of int, shape (n,)
        :data:`DIRECT`, :data:`MULTIPATH`, :data:`SPURIOUS` or :data:`LATE`.
    group, slot, receiver : ndarray of int, shape (n,)
        Receiver group, its transmitter slot and receiver column.
    path : ndarray, shape (n,)
        Path length transmitter -> receiver including the height difference, m.
    amplitude : ndarray, shape (n,)
        Echo amplitude relative to ``A_max`` (measured: with noise, at least the threshold).
    in_point : ndarray, shape (n, 2)
        Where the received ray last left the reflector, world frame, m.
    truth_position, truth_normal : ndarray, shape (n, 2)
        The row's ground truth, world frame (NaN for effects).
    tof, crossing : ndarray, shape (n,)
        Measured time of flight and rising zero-crossing time, s; NaN until
        :meth:`Simulator.measure`.
    """

    source: np.ndarray
    origin: np.ndarray
    group: np.ndarray
    slot: np.ndarray
    receiver: np.ndarray
    path: np.ndarray
    amplitude: np.ndarray
    in_point: np.ndarray
    truth_position: np.ndarray
    truth_normal: np.ndarray
    tof: np.ndarray
    crossing: np.ndarray

    def __len__(self) -> int:
        return int(self.source.shape[0])

    def take(self, index) -> Heard:
        """The entries picked by a boolean mask or an index array."""
        return Heard(*(getattr(self, f.name)[index] for f in fields(Heard)))

    @staticmethod
    def concatenate(parts) -> Heard:
        """The entries of ``parts`` (a non-empty sequence of Heard), in order."""
        return Heard(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(Heard)))


def place(layout: Layout, pose) -> Placement:
    """A layout's transducers in a world frame (a scene's, a map's) with the sensor at ``pose``.

    Parameters
    ----------
    layout : Layout
    pose : array_like, shape (3,)
        Sensor pose ``(x, y, yaw)`` in that frame, m and rad.

    Raises
    ------
    ValueError
        If ``pose`` is not three finite numbers.
    """
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (3,) or not all(math.isfinite(value) for value in pose.tolist()):
        raise ValueError(f"place: pose must be finite (x, y, yaw), got {pose!r}")
    plan = layout.plan
    rotation, tx, rx, tx_axis, rx_axis = _placed(plan.transmitters, plan.receivers, plan.transmitter_yaw,
                                                 plan.receiver_yaw, pose)
    return Placement(pose=pose, rotation=rotation, tx=tx, rx=rx, tx_axis=tx_axis, rx_axis=rx_axis)


@kernel
def _placed(transmitters, receivers, transmitter_yaw, receiver_yaw, pose):
    """:func:`place`'s arithmetic: the rotation (2, 2) by the pose's yaw, and tx, rx, tx_axis, rx_axis as there.

    Transmitters (G, M, 2) and receivers (G, K, 2) turned by one product and moved (the product numpy's, so
    the numbers are the same whichever of the two computes them); the axes from the layout's yaws (G, M) and
    (G, K) plus the pose's.
    """
    cos_yaw, sin_yaw = math.cos(pose[2]), math.sin(pose[2])
    rotation = np.array([[cos_yaw, -sin_yaw], [sin_yaw, cos_yaw]])
    groups, slots, receiving = receivers.shape[0], transmitters.shape[1], receivers.shape[1]
    split = groups * slots
    positions = np.concatenate((np.ascontiguousarray(transmitters).reshape(-1, 2),
                                np.ascontiguousarray(receivers).reshape(-1, 2))) @ np.ascontiguousarray(rotation.T)
    positions[:, 0] += pose[0]
    positions[:, 1] += pose[1]
    axes = np.empty((split + groups * receiving, 2))
    for n in range(split):
        yaw = transmitter_yaw[n // slots, n % slots] + pose[2]
        axes[n, 0], axes[n, 1] = math.cos(yaw), math.sin(yaw)
    for n in range(groups * receiving):
        yaw = receiver_yaw[n // receiving, n % receiving] + pose[2]
        axes[split + n, 0], axes[split + n, 1] = math.cos(yaw), math.sin(yaw)
    return (rotation, positions[:split].reshape(groups, slots, 2), positions[split:].reshape(groups, receiving, 2),
            axes[:split].reshape(groups, slots, 1, 2), axes[split:].reshape(groups, 1, receiving, 2))


class Simulator:
    """Forward model of one sensor layout in one scene.

    :meth:`ping` is four steps, public so that :mod:`sonar_ring.realism` can
    add paths of its own between them: :meth:`place` the sensor at a pose,
    :meth:`hear` the scene's reflections (:meth:`reflections`), :meth:`measure`
    them with noise, and pack them into :meth:`echo_rows`.

    Parameters
    ----------
    scene : Scene
        The reflectors and the air.
    layout : Layout
        The sensor.
    threshold : float
        Detection threshold relative to ``A_max``; weaker echoes are not
        reported (default -30 dB).

    Attributes
    ----------
    half_angle : float
        Gaussian beam half-angle ``theta0`` of the transducers, rad.
    speed : float
        Speed of sound in the scene's air, m/s.
    max_path : float
        Longest path the receivers report, ``2 * layout.max_range``, m.
    """

    def __init__(self, scene: Scene, layout: Layout, threshold: float = DEFAULT_THRESHOLD):
        if not (math.isfinite(threshold) and threshold > 0):
            raise ValueError(f"Simulator: threshold must be a finite number > 0, got {threshold!r}")
        self.scene = scene
        self.layout = layout
        self.threshold = float(threshold)
        self.speed = scene.speed_of_sound
        self.half_angle = transducer_half_angle(layout, self.speed)
        self.period = 1.0 / layout.frequency
        self.max_path = 2.0 * layout.max_range
        self._dz = layout.height_offset()  # (G, M, K)
        self._triad = layout.kind == "triad"
        s = scene
        frames = image_method.wall_frames(np.ascontiguousarray(s.walls))
        self.wall_start, self.wall_direction, self.wall_normal, self.wall_length = frames
        # Reflector index of each row of the walls / corners / edges tables (both in file order).
        self._reflectors = {code: np.flatnonzero(s.reflector_class == code) for code in (PLANE, CORNER, EDGE)}

    # ------------------------------------------------------------------ geometry per kind

    def _family(self, code: int) -> dict:
        """Row keys, strengths and origin of the scene's reflectors of one class (:class:`Paths` fields)."""
        reflectors = self._reflectors[code]
        return dict(source=reflectors, strength=self.scene.reflectivity[self.scene.reflector_class[reflectors]],
                    origin=DIRECT)

    def _plane_paths(self, tx, rx) -> Paths:
        """Single reflections: image of T in each wall line (shapes in :class:`Paths`)."""
        a = self.wall_start[:, None, None, None, :]
        u = self.wall_direction[:, None, None, None, :]
        n = self.wall_normal[:, None, None, None, :]
        t = tx[None, :, :, None, :]  # (1, G, M, 1, 2)
        r = rx[None, :, None, :, :]  # (1, G, 1, K, 2)
        side_t = _dot(t - a, n)  # (W, G, M, 1)
        side_r = _dot(r - a, n)  # (W, G, 1, K)
        image = t - 2.0 * side_t[..., None] * n
        same_side = side_t * side_r > 0
        # Where T and R are on opposite sides (or on the line) the fraction is meaningless;
        # ``same_side`` discards those entries.
        with np.errstate(divide="ignore", invalid="ignore"):
            fraction = side_r / (side_r + side_t)
            point = r + fraction[..., None] * (image - r)  # reflection point, (W, G, M, K, 2)
            along = _dot(point - a, u)
        length = self.wall_length[:, None, None, None]
        exists = same_side & (along >= 0) & (along <= length)
        delta = image - r
        foot = tx[None] - side_t[..., 0, None] * n[:, :, :, 0]  # (W, G, M, 2)
        normal = np.sign(side_t[..., 0, None]) * n[:, :, :, 0]
        return Paths(**self._family(PLANE), horizontal=np.hypot(delta[..., 0], delta[..., 1]), exists=exists,
                     out_point=point, in_point=point, legs=[(t, point), (point, r)], truth_position=foot,
                     truth_normal=normal)

    def _corner_paths(self, tx, rx) -> Paths:
        """Double reflections: image ``2C - T``; reflection points on both arms."""
        s = self.scene
        c = s.corner_point[:, None, None, None, :]
        arm_a = s.corner_arm[:, 0][:, None, None, None, :]
        arm_b = s.corner_arm[:, 1][:, None, None, None, :]
        length = s.corner_arm_length[:, None, None, None, :]
        t = tx[None, :, :, None, :]
        r = rx[None, :, None, :, :]
        tu, tv = _dot(t - c, arm_a), _dot(t - c, arm_b)  # (C, G, M, 1)
        ru, rv = _dot(r - c, arm_a), _dot(r - c, arm_b)  # (C, G, 1, K)
        inside = (tu > 0) & (tv > 0) & (ru > 0) & (rv > 0)
        # In coordinates along the arms the image of T through both walls is (-tu, -tv).
        # The straight line from it to R crosses arm B at b = turn / (tu + ru) and,
        # unfolded once, arm A at a = tu b / (b + tv), with turn = tu rv - tv ru: the
        # order "A first" is real when turn >= 0, "B first" (arms swapped) when turn < 0.
        turn = tu * rv - tv * ru
        a_first = turn >= 0
        first_arm = np.where(a_first[..., None], arm_a, arm_b)
        last_arm = np.where(a_first[..., None], arm_b, arm_a)
        first_length = np.where(a_first, length[..., 0], length[..., 1])
        last_length = np.where(a_first, length[..., 1], length[..., 0])
        # Outside the quadrant the denominators may vanish; ``inside`` discards those entries.
        with np.errstate(divide="ignore", invalid="ignore"):
            last = np.where(a_first, turn / (tu + ru), -turn / (tv + rv))
            first = np.where(a_first, tu * last / (last + tv), tv * last / (last + tu))
            first_point = c + first[..., None] * first_arm
            last_point = c + last[..., None] * last_arm
        exists = inside & (first <= first_length) & (last <= last_length)
        delta = 2.0 * c - t - r
        vertex = np.broadcast_to(s.corner_point[:, None, None, :], (len(s.corner_point),) + tx.shape)
        return Paths(**self._family(CORNER), horizontal=np.hypot(delta[..., 0], delta[..., 1]), exists=exists,
                     out_point=first_point, in_point=last_point,
                     legs=[(t, first_point), (first_point, last_point), (last_point, r)],
                     truth_position=vertex, truth_normal=np.full(vertex.shape, np.nan))

    def _edge_paths(self, tx, rx) -> Paths:
        """Diffraction at vertical lines: ``|T - P| + |P - R|``."""
        p = self.scene.edges[:, None, None, None, :]
        t = tx[None, :, :, None, :]
        r = rx[None, :, None, :, :]
        out, back = p - t, p - r
        horizontal = np.hypot(out[..., 0], out[..., 1]) + np.hypot(back[..., 0], back[..., 1])
        vertex = np.broadcast_to(self.scene.edges[:, None, None, :], (len(self.scene.edges),) + tx.shape)
        return Paths(**self._family(EDGE), horizontal=horizontal, exists=np.ones(horizontal.shape, dtype=bool),
                     out_point=p, in_point=p, legs=[(t, p), (p, r)], truth_position=vertex,
                     truth_normal=np.full(vertex.shape, np.nan))

    # ------------------------------------------------------------------ one ping

    def ping(self, pose, *, noise: Noise = NOISE_FREE, rng: np.random.Generator | None = None,
             time: float = 0.0) -> Ping:
        """Simulate one ping with the sensor at ``pose``.

        Parameters
        ----------
        pose : array_like, shape (3,)
            Sensor pose ``(x, y, yaw)`` in the world frame, m and rad.
        noise : Noise
            Measurement noise; :data:`NOISE_FREE` gives exact data.
        rng : numpy.random.Generator, optional
            Source of all random numbers; required when ``noise`` is random.
        time : float
            Time stamp to give the ping, s.

        Returns
        -------
        Ping
            The echoes in the sensor frame with their ground truth.
        """
        if noise.random and rng is None:
            raise ValueError("Simulator.ping: a numpy.random.Generator 'rng' is needed for noisy pings")
        placement = self.place(pose)
        measured = self.measure(self.reflections(placement), noise, rng, self.speed)
        return self.echo_rows(measured, placement, noise, rng, time, self.speed)

    def place(self, pose) -> Placement:
        """The sensor's transducers in the world at ``pose`` (x, y, yaw; m, rad): :func:`place`.

        Raises
        ------
        ValueError
            If ``pose`` is not three finite numbers.
        """
        return place(self.layout, pose)

    def reflections(self, placement: Placement, max_path: float | None = None) -> Heard:
        """What the scene's walls, corners and edges return to the sensor at ``placement`` (no noise).

        ``max_path`` (m) is the receive window, default :attr:`max_path`.
        """
        kinds = ((PLANE, self._plane_paths), (CORNER, self._corner_paths), (EDGE, self._edge_paths))
        return Heard.concatenate([self.hear(kind(placement.tx, placement.rx), placement, max_path)
                                  for code, kind in kinds if self._reflectors[code].size])

    def hear(self, paths: Paths, placement: Placement, max_path: float | None = None) -> Heard:
        """The (member, group, slot, receiver) paths a receiver hears, as flat columns.

        Keeps paths that exist geometrically, fit the receive window
        (``max_path``, m; default :attr:`max_path`), leave a directional
        transmitter and reach the receiver within the acceptance half-angle, and
        are not blocked by a wall.  Amplitudes are the member's strength times
        Barshan & Kuc's transmit and receive gains.
        """
        tx, rx = placement.tx, placement.rx
        shape = paths.horizontal.shape
        acceptance = self.layout.beam_half_angle
        path = np.sqrt(paths.horizontal ** 2 + self._dz ** 2)
        in_point = np.broadcast_to(paths.in_point, shape + (2,))
        receive_angle = _angle_off_axis(in_point - rx[None, :, None, :, :], placement.rx_axis)
        max_path = self.max_path if max_path is None else max_path
        candidate = paths.exists & (path <= max_path) & (np.abs(receive_angle) <= acceptance)
        if self.layout.isotropic_emitter:
            transmit_angle = np.zeros(shape)
        else:
            # A directional transmitter is the same kind of transducer as the receivers:
            # the same beam limits what it sends, which keeps A_ab' = A_ba' (reciprocity)
            # and puts the beam edge where Barshan & Kuc's eq 27 has it.
            out_point = np.broadcast_to(paths.out_point, shape + (2,))
            transmit_angle = _angle_off_axis(out_point - tx[None, :, :, None, :], placement.tx_axis)
            candidate &= np.abs(transmit_angle) <= acceptance
        index = np.nonzero(candidate)
        if self.scene.walls.size and index[0].size:
            starts = np.concatenate([np.broadcast_to(start, shape + (2,))[index] for start, _ in paths.legs])
            ends = np.concatenate([np.broadcast_to(end, shape + (2,))[index] for _, end in paths.legs])
            # Through the module: a kernel imported by name stays the wrapper that compiles at first use.
            blocked = image_method.blocked_legs(starts, ends, self.scene.walls)
            blocked = blocked.reshape(len(paths.legs), -1).any(axis=0)
            index = tuple(i[~blocked] for i in index)
        f, g, m, k = index
        # Barshan & Kuc eqs 3-4: the product of the transmit and receive Gaussian gains.
        gain = np.exp(-2.0 * (transmit_angle[index] ** 2 + receive_angle[index] ** 2) / self.half_angle ** 2)
        unmeasured = np.full(f.size, np.nan)
        return Heard(
            source=paths.source[f],
            origin=np.full(f.size, paths.origin),
            group=g,
            slot=m,
            receiver=k,
            path=path[index],
            amplitude=paths.strength[f] * gain,
            in_point=in_point[index],
            truth_position=paths.truth_position[f, g, m],
            truth_normal=paths.truth_normal[f, g, m],
            tof=unmeasured,
            crossing=unmeasured,
        )

    def measure(self, heard: Heard, noise: Noise, rng, speed: float) -> Heard:
        """What the receivers report of ``heard``: amplitude noise, the threshold, times of flight.

        Amplitudes get Gaussian noise and those below the threshold are dropped;
        the others' arrival is ``path / speed`` (``speed`` of the air the echoes
        travelled in, m/s), reported with Gaussian TOF noise (``tof``) and
        zero-crossing jitter (``crossing``).  Random numbers come from ``rng``
        in a fixed order, so a path family measured with its own generator
        leaves the others' values unchanged.
        """
        amplitude = heard.amplitude
        if noise.amplitude:
            amplitude = amplitude + rng.normal(0.0, noise.amplitude, amplitude.shape)
        keep = amplitude >= self.threshold
        kept = heard.take(keep)
        arrival = kept.path / speed
        tof = arrival + rng.normal(0.0, noise.tof, arrival.shape) if noise.tof else arrival
        crossing = arrival + rng.normal(0.0, noise.phase, arrival.shape) if noise.phase else arrival
        return replace(kept, amplitude=amplitude[keep], tof=tof, crossing=crossing)

    def echo_rows(self, c: Heard, placement: Placement, noise: Noise, rng, time: float,
                  speed_of_sound: float) -> Ping:
        """Pack measured paths into echo rows: one per (source, group, transmitter slot), receivers as columns.

        ``speed_of_sound`` (m/s) is what the ping reports; a timer (``noise.timer``)
        draws its clock's phase from ``rng``.
        """
        K = self.layout.receivers_per_group
        pose = placement.pose
        # One row per (source, group, transmitter slot); receivers are its columns.
        n_slots = self.layout.group_transmitters.shape[1]
        key = (c.source * self.layout.n_groups + c.group) * n_slots + c.slot
        row_key, row = np.unique(key, return_inverse=True)
        N = row_key.size
        tof_table = np.full((N, K), np.nan)
        tof_table[row, c.receiver] = c.tof
        amplitude_table = np.full((N, K), np.nan)
        amplitude_table[row, c.receiver] = c.amplitude
        crossing_table = np.full((N, K), np.nan)
        crossing_table[row, c.receiver] = c.crossing
        point_table = np.full((N, K, 2), np.nan)
        point_table[row, c.receiver] = c.in_point
        first = np.empty(N, dtype=int)
        first[row] = np.arange(row.size)  # any path of a row: they share source, group, slot and truth
        source = c.source[first]
        origin = c.origin[first]
        group = c.group[first]
        transmitter = self.layout.group_transmitters[group, c.slot[first]]
        direct = origin == DIRECT
        reflector = np.where(direct, source, -1)
        truth_class = np.where(direct, self.scene.reflector_class[np.where(direct, source, 0)], UNKNOWN)
        point_table[~direct] = np.nan

        if noise.timer:
            clock = rng.uniform(0.0, noise.timer)  # the counter clock's phase at this ping
            tof_table = np.floor((tof_table + clock) / noise.timer) * noise.timer
        if self._triad:
            phase = np.mod(crossing_table[:, 1:] - crossing_table[:, :1], self.period)
            if noise.timer:
                # Counted from R0's crossing to R_k's on the same clock.
                start = (crossing_table[:, :1] + clock) / noise.timer
                phase = (np.floor(start + phase / noise.timer) - np.floor(start)) * noise.timer
        else:
            phase = np.empty((N, 0))

        order = np.lexsort((np.nanmin(tof_table, axis=1), transmitter, group))
        to_sensor = placement.rotation  # row vectors times R == R.T applied to column vectors

        def sensor_frame(points):
            return (points - pose[:2]) @ to_sensor

        return Ping(
            layout=self.layout.name,
            time=float(time),
            pose=pose.copy(),
            speed_of_sound=float(speed_of_sound),
            group=group[order],
            transmitter=transmitter[order],
            tof=tof_table[order],
            amplitude=amplitude_table[order],
            phase_delay=phase[order],
            truth_reflector=reflector[order],
            truth_class=truth_class[order],
            truth_origin=origin[order],
            truth_position=sensor_frame(c.truth_position[first])[order],
            truth_normal=(c.truth_normal[first] @ to_sensor)[order],
            truth_reflection_point=sensor_frame(point_table)[order],
        )

    def run(self, poses, times=None, *, noise: Noise = NOISE_FREE,
            rng: np.random.Generator | None = None) -> list[Ping]:
        """Simulate a ping at each of several poses.

        Parameters
        ----------
        poses : array_like, shape (P, 3)
            Sensor poses ``(x, y, yaw)``, world frame, m and rad.
        times : array_like, shape (P,), optional
            Ping times, s; default ``arange(P) / layout.ping_rate``.
        noise, rng
            As for :meth:`ping`; one generator serves the whole run.

        Returns
        -------
        list of Ping
        """
        poses = np.asarray(poses, dtype=float).reshape(-1, 3)
        times = np.arange(len(poses)) / self.layout.ping_rate if times is None else np.asarray(times, dtype=float)
        return [self.ping(p, noise=noise, rng=rng, time=t) for p, t in zip(poses, times, strict=True)]


def ping(scene: Scene, layout: Layout, pose=None, *, noise: Noise = NOISE_FREE,
         rng: np.random.Generator | None = None, threshold: float = DEFAULT_THRESHOLD) -> Ping:
    """Simulate one ping (a one-off :class:`Simulator`; reuse one for many pings).

    Parameters
    ----------
    scene : Scene
    layout : Layout
    pose : array_like, shape (3,), optional
        Sensor pose ``(x, y, yaw)``, world frame, m and rad; default the
        scene's ``sensor_pose``.
    noise, rng, threshold
        As for :class:`Simulator` and :meth:`Simulator.ping`.
    """
    pose = scene.sensor_pose if pose is None else pose
    return Simulator(scene, layout, threshold).ping(pose, noise=noise, rng=rng)
