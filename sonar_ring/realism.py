"""What a robot measures, beside what the scene reflects: the effects of a real world, each switchable.

The forward model (:mod:`sonar_ring.simulate`) computes the echoes a scene's
reflectors return to a sensor at a known pose in known air.  A robot measures
something else, and every effect of that lives here, beside the forward model,
as a small function of the scene, the pose and a seeded generator:

* **wheel odometry** (:class:`WheelOdometry`): what wheel encoders report of the
  true motion -- each increment's distance scaled by ``1 + odometry_scale_error``
  and both its distance and heading perturbed by Gaussian noise whose variance
  grows with the distance the wheels rolled (``odometry_distance_noise``, m/sqrt(m);
  ``odometry_heading_noise``, rad/sqrt(m)), its heading biased by
  ``odometry_heading_bias`` rad per metre driven (unequal wheel diameters).
  The wheels roll ``|ds| + track_width / 2 * |dtheta|`` in an increment, so a
  turn on the spot is noisy too.  Odometry starts at the true first pose:
  ``odom`` and the scene's world frame coincide at the start.
* **speed of sound** (:func:`air_speed`): the air is ``temperature_offset`` K
  warmer than the scene's ``temperature_c``, which is what the nodes assume
  (the pings report its speed of sound), and warms by ``temperature_drift`` K
  per minute; echoes travel at the true air's speed, so ranges scale by
  ``c_true / c_assumed``.
* **missed echoes** (:func:`miss_probability`): air turbulence and surface
  texture make an echo's amplitude fluctuate about the forward model's value,
  log-normally with ``fading_db`` dB standard deviation; a receiver misses the
  echo when the fluctuation takes it below the detection threshold, which an
  echo at the threshold does half the time and one 6 dB above it
  ``Phi(-6 / fading_db)`` of the time.
* **spurious echoes** (:func:`spurious_paths`): clutter, people and chair legs
  that are not in the scene -- a Poisson number (mean ``spurious_rate`` per
  receiver group and ping) of point scatterers, each at a random range and
  bearing in a random group's beam for one ping, heard by every group that
  hears such a point; their strength is uniform between twice the threshold and
  an edge's reflectivity.
* **multipath** (:func:`multipath_paths`): second-order reflections that are not
  a right-angle corner's double bounce -- wall then wall (parallel walls, a wall
  and a pillar's face), wall then edge and edge then wall (a pole or a pillar's
  edge seen in a wall) -- from the image method, with the two reflectivities
  times ``multipath_gain`` (what the second reflection and the longer path's
  spreading lose), so a single-bounce model sees a reflector where there is none.
* **late echoes** (:func:`late_echoes`): the receivers listen until the next
  ping fires; an echo arriving later is heard by the next ping, ``c / ping_rate``
  metres of path early, as a near phantom.  Its amplitude is what the time-variable
  gain makes of it: the gain compensates spherical spreading and air absorption
  (ISO 9613-1, :func:`air_absorption`) for the apparent path, not the true one,
  so the phantom is ``(d_apparent / d_true) 10^(-alpha (d_true - d_apparent) / 20)``
  of the true echo.  Off with ``late_echoes = 0``.

:class:`World` puts them together ping by ping.  Every effect draws from a
generator of its own (seeded from the run's seed and the effect), so an effect
switched on leaves every other value unchanged, and the ``ideal`` profile is
the forward model value for value.

Profiles (:data:`PROFILES`): ``ideal`` (all effects off: the forward model) and
``realistic`` (a typical indoor differential-drive robot carrying Browne's ring
in an office).  A scene file's ``realism:`` block and the driver's parameters
override single fields of a profile.

Frames and units: scenes and poses in the world frame (m, rad); odometry in
``odom``, which starts at the true first pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from sonar_ring import image_method
from sonar_ring.geometry import Layout, speed_of_sound
from sonar_ring.image_method import POINT_WALL, WALL_POINT, WALL_WALL
from sonar_ring.poses import compose, relative_pose
from sonar_ring.simulate import (
    DEFAULT_THRESHOLD,
    EDGE,
    LATE,
    MULTIPATH,
    NOISE_FREE,
    PLANE,
    SPURIOUS,
    Heard,
    Noise,
    Paths,
    Ping,
    Placement,
    Scene,
    SceneError,
    Simulator,
)

# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class Realism:
    """The effects of a real world and their sizes; every field 0 switches its effect off.

    Attributes
    ----------
    odometry_scale_error : float
        Relative error of the distance the wheels report (0.01: 1 % too far).
    odometry_distance_noise : float
        Standard deviation of the reported distance per square root of the
        distance rolled, m/sqrt(m).
    odometry_heading_noise : float
        Standard deviation of the reported heading change per square root of
        the distance rolled, rad/sqrt(m).
    odometry_heading_bias : float
        Heading change reported per metre driven that did not happen, rad/m.
    track_width : float
        Distance between the wheels, m: a turn ``dtheta`` rolls each wheel
        ``track_width / 2 * |dtheta|``.
    temperature_offset : float
        True air temperature minus the one the nodes assume (the scene's), K.
    temperature_drift : float
        Change of the true air temperature, K per minute.
    fading_db : float
        Standard deviation of an echo's log-normal amplitude fluctuation, dB.
    spurious_rate : float
        Mean number of spurious echoes (phantom point scatterers) per receiver
        group and ping.
    multipath_gain : float
        Amplitude of a second-order reflection relative to the product of its
        two reflectivities.
    late_echoes : float
        1 to hear an echo that arrives after the next ping fired in that ping, 0 not to.
    """

    odometry_scale_error: float = 0.0
    odometry_distance_noise: float = 0.0
    odometry_heading_noise: float = 0.0
    odometry_heading_bias: float = 0.0
    track_width: float = 0.4
    temperature_offset: float = 0.0
    temperature_drift: float = 0.0
    fading_db: float = 0.0
    spurious_rate: float = 0.0
    multipath_gain: float = 0.0
    late_echoes: float = 0.0

    def __post_init__(self):
        for name, (low, high) in RANGES.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not (low <= value <= high):
                raise ValueError(f"Realism: field '{name}' must be a number in [{low:g}, {high:g}], got {value!r}")
        if self.late_echoes not in (0, 1):
            raise ValueError(f"Realism: field 'late_echoes' must be 0 or 1, got {self.late_echoes!r}")

    @property
    def odometry_exact(self) -> bool:
        """True when the odometry reports the true motion."""
        return not (self.odometry_scale_error or self.odometry_distance_noise or self.odometry_heading_noise
                    or self.odometry_heading_bias)

    def effects(self) -> tuple[str, ...]:
        """Names of the effects switched on (:data:`EFFECTS`), in their order."""
        return tuple(name for name, switches in EFFECTS.items() if any(getattr(self, f) for f in switches))

    def only(self, effect: str) -> Realism:
        """The same realism with every effect but ``effect`` (a key of :data:`EFFECTS`) switched off."""
        if effect not in EFFECTS:
            raise ValueError(f"Realism.only: effect must be one of {', '.join(EFFECTS)}, got {effect!r}")
        return replace(IDEAL, **{name: getattr(self, name) for name in EFFECTS[effect]},
                       track_width=self.track_width)


DESCRIPTIONS = {
    "odometry_scale_error": "relative error of the distance the wheels report (0.01: 1 % too far)",
    "odometry_distance_noise": "distance noise of the wheel odometry, m per sqrt(m) rolled",
    "odometry_heading_noise": "heading noise of the wheel odometry, rad per sqrt(m) rolled",
    "odometry_heading_bias": "heading the wheel odometry gains per metre driven, rad/m",
    "track_width": "distance between the wheels, m (a turn on the spot rolls them)",
    "temperature_offset": "true air temperature minus the assumed (the scene's), K",
    "temperature_drift": "change of the true air temperature, K/min",
    "fading_db": "log-normal fading of echo amplitudes, dB (misses near the threshold)",
    "spurious_rate": "phantom echoes (clutter) per receiver group and ping",
    "multipath_gain": "amplitude of second-order reflections relative to their reflectivities' product",
    "late_echoes": "1: an echo arriving after the next ping fired is heard by that ping",
}
"""One line per field, with its unit: the driver's parameter descriptions and the command line's help."""

RANGES = {
    "odometry_scale_error": (-0.5, 0.5),
    "odometry_distance_noise": (0.0, 1.0),
    "odometry_heading_noise": (0.0, 1.0),
    "odometry_heading_bias": (-1.0, 1.0),
    "track_width": (0.01, 10.0),
    "temperature_offset": (-50.0, 50.0),
    "temperature_drift": (-10.0, 10.0),
    "fading_db": (0.0, 30.0),
    "spurious_rate": (0.0, 100.0),
    "multipath_gain": (0.0, 1.0),
    "late_echoes": (0.0, 1.0),
}
"""Accepted range of each field: beyond it a value is a typing error, not a world."""

EFFECTS = {
    "odometry": ("odometry_scale_error", "odometry_distance_noise", "odometry_heading_noise",
                 "odometry_heading_bias"),
    "speed_of_sound": ("temperature_offset", "temperature_drift"),
    "misses": ("fading_db",),
    "spurious": ("spurious_rate",),
    "multipath": ("multipath_gain",),
    "late": ("late_echoes",),
}
"""Each effect and the fields that switch it on (any of them non-zero)."""

IDEAL = Realism()
"""Today's forward model: exact odometry, the assumed air, every echo present and real."""

REALISTIC = Realism(
    # Wheel odometry of an indoor differential-drive robot.  A 1 % distance error is a 1 mm error
    # of a 100 mm wheel's radius (tyre wear, load); 0.005 rad/m is a 0.2 % difference between the
    # two wheels' diameters on a 0.4 m track; the noise (1 cm and 0.01 rad per sqrt(m)) is what
    # slip on floor joints and carpet edges adds.  4.5 cm of drift after a 13 m lap of the room.
    odometry_scale_error=0.01,
    odometry_distance_noise=0.01,
    odometry_heading_noise=0.01,
    odometry_heading_bias=0.005,
    track_width=0.4,
    # The nodes assume the scene's temperature; the air is 2 K warmer (a thermometer away from
    # the sensor, or 20 degC assumed in a 22 degC room) and warms by 1 K in 20 minutes (HVAC):
    # 0.35 % of range, 1.2 cm at 3 m.
    temperature_offset=2.0,
    temperature_drift=0.05,
    # An assumption, not a measurement: echoes within 3 dB of the threshold are missed one time
    # in six or more, those 9 dB above it almost never.
    fading_db=3.0,
    # A busy room: about one phantom per ping around the 48-pair ring.
    spurious_rate=0.02,
    # Second-order reflections at half the amplitude of their two reflectivities' product (what an
    # independent image-method room left in, the multipath case the echo tests are held to).
    multipath_gain=0.5,
    late_echoes=1.0,
)
"""A typical indoor robot with Browne's ring; the comments give where each number comes from."""

PROFILES = {"ideal": IDEAL, "realistic": REALISTIC}
"""The named worlds."""


def profile(name: str, overrides=None, where: str = "realism") -> Realism:
    """The realism of profile ``name`` with some fields replaced.

    Parameters
    ----------
    name : str
        A key of :data:`PROFILES`.
    overrides : mapping of str to number, optional
        Field values that replace the profile's (the driver's parameters, the
        command line's ``--realism``).
    where : str
        Where the overrides come from, for the error message.

    Raises
    ------
    SceneError
        Naming ``where``, the field and the expected value.
    """
    if name not in PROFILES:
        raise SceneError(f"{where}: profile must be one of {', '.join(PROFILES)}, got {name!r}")
    return _replaced(PROFILES[name], overrides, where)


def scene_realism(scene: Scene, name: str, overrides=None, where: str = "realism") -> Realism:
    """Profile ``name``, then the scene file's ``realism:`` block, then ``overrides`` (each replacing fields).

    Raises
    ------
    SceneError
        Naming the scene or ``where``, the field and the expected value.
    """
    in_scene = profile(name, scene.realism, where=f"scene '{scene.name}': realism")
    return _replaced(in_scene, overrides, where)


def _replaced(realism: Realism, overrides, where: str) -> Realism:
    overrides = dict(overrides or {})
    unknown = sorted(set(overrides) - set(RANGES), key=str)
    if unknown:
        raise SceneError(f"{where}: unknown field {unknown[0]!r} (expected some of {sorted(RANGES)})")
    try:
        return replace(realism, **{key: _number(value) for key, value in overrides.items()})
    except ValueError as error:
        raise SceneError(f"{where}: {str(error).removeprefix('Realism: ')}") from None


def _number(value):
    """A YAML or parameter value as a float where it is a number (bools stay bools, to be refused)."""
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else value


# --------------------------------------------------------------------------- odometry


class WheelOdometry:
    """What wheel encoders report of a robot's true motion, integrated into poses in ``odom``.

    Each call of :meth:`step` takes the next true pose, corrupts the increment
    from the previous one (in the previous pose's frame: forward and sideways
    distance, heading change) as the module docstring describes, and returns
    the odometry's pose.  With every odometry field of ``realism`` 0 it
    returns the true poses.

    Parameters
    ----------
    realism : Realism
    rng : numpy.random.Generator
        Only this object draws from it.
    """

    def __init__(self, realism: Realism, rng: np.random.Generator):
        self.realism = realism
        self._rng = rng
        self._true: np.ndarray | None = None
        self._pose: np.ndarray | None = None
        self.distance = 0.0
        """Distance the robot's centre has travelled, m."""

    def step(self, true_pose) -> np.ndarray:
        """The odometry's pose ``(x, y, yaw)`` in ``odom`` when the robot is at ``true_pose`` (world), m and rad."""
        true_pose = np.asarray(true_pose, dtype=float)
        if self._true is None:
            self._true, self._pose = true_pose.copy(), true_pose.copy()
            return self._pose.copy()
        forward, sideways, turn = relative_pose(self._true, true_pose)
        self._true = true_pose.copy()
        distance = math.hypot(forward, sideways)
        self.distance += distance
        if not self.realism.odometry_exact:
            r = self.realism
            rolled = distance + 0.5 * r.track_width * abs(turn)
            along = (1.0 + r.odometry_scale_error) + r.odometry_distance_noise * math.sqrt(rolled) * \
                self._rng.standard_normal() / max(distance, 1e-12)
            forward, sideways = forward * along, sideways * along
            signed = math.copysign(distance, forward)
            turn += r.odometry_heading_bias * signed + r.odometry_heading_noise * math.sqrt(rolled) * \
                self._rng.standard_normal()
        self._pose = compose(self._pose, (forward, sideways, turn))
        return self._pose.copy()


# --------------------------------------------------------------------------- air


def air_speed(scene: Scene, realism: Realism, time: float) -> float:
    """Speed of sound in the true air ``time`` s into a run, m/s (the scene's is what the nodes assume)."""
    temperature = scene.temperature_c + realism.temperature_offset + realism.temperature_drift * time / 60.0
    return float(speed_of_sound(temperature, scene.relative_humidity))


def air_absorption(frequency: float, temperature_c: float, relative_humidity: float,
                   pressure_pa: float = 101325.0) -> float:
    """Atmospheric absorption of sound, dB/m (ISO 9613-1:1993, eqs 3-5 and Annex B).

    Parameters
    ----------
    frequency : float
        Hz.
    temperature_c : float
        Air temperature, degC.
    relative_humidity : float
        Percent.
    pressure_pa : float
        Pa.
    """
    reference_pressure, reference_temperature, triple_point = 101325.0, 293.15, 273.16
    temperature = temperature_c + 273.15
    pressure = pressure_pa / reference_pressure
    saturation = 10.0 ** (-6.8346 * (triple_point / temperature) ** 1.261 + 4.6151)
    humidity = relative_humidity * saturation / pressure  # molar concentration of water vapour, %
    ratio = temperature / reference_temperature
    oxygen = pressure * (24.0 + 4.04e4 * humidity * (0.02 + humidity) / (0.391 + humidity))
    nitrogen = pressure * ratio ** -0.5 * (9.0 + 280.0 * humidity * math.exp(-4.170 * (ratio ** (-1.0 / 3.0) - 1.0)))
    f2 = frequency ** 2
    return 8.686 * f2 * (1.84e-11 / pressure * ratio ** 0.5 + ratio ** -2.5 * (
        0.01275 * math.exp(-2239.1 / temperature) / (oxygen + f2 / oxygen)
        + 0.1068 * math.exp(-3352.0 / temperature) / (nitrogen + f2 / nitrogen)))


# --------------------------------------------------------------------------- misses


def miss_probability(amplitude, threshold: float, fading_db: float) -> np.ndarray:
    """Probability that a receiver misses an echo of ``amplitude`` (relative to ``A_max``), shape of ``amplitude``.

    ``Phi(-20 log10(amplitude / threshold) / fading_db)``: the chance that a
    log-normal fluctuation of ``fading_db`` dB takes the echo below ``threshold``.
    """
    margin_db = 20.0 * np.log10(np.asarray(amplitude, dtype=float) / threshold)
    if fading_db == 0:
        return (margin_db < 0).astype(float)
    scale = fading_db * math.sqrt(2.0)
    return np.reshape([0.5 * math.erfc(margin / scale) for margin in margin_db.reshape(-1)], margin_db.shape)


# --------------------------------------------------------------------------- spurious echoes


def spurious_paths(simulator: Simulator, placement: Placement, rate: float, rng: np.random.Generator,
                   first_source: int) -> Paths:
    """Phantom point scatterers of one ping, as a path family heard like edges.

    A Poisson number with mean ``rate`` times the receiver groups; each in a
    random group's beam (bearing within the acceptance half-angle of its facing)
    at a range uniform in ``[0.2 m, layout.max_range]`` from the group's
    centre, with a strength uniform between twice the threshold and an edge's
    reflectivity.  Row keys count from ``first_source``.
    """
    layout = simulator.layout
    count = rng.poisson(rate * layout.n_groups)
    group = rng.integers(0, layout.n_groups, count)
    bearing = layout.plan.yaw[group] + placement.pose[2] + rng.uniform(-1.0, 1.0, count) * layout.beam_half_angle
    distance = rng.uniform(0.2, layout.max_range, count)
    centre = placement.rx[group].mean(axis=1)
    point = centre + distance[:, None] * np.stack([np.cos(bearing), np.sin(bearing)], axis=-1)
    strength = rng.uniform(2.0 * simulator.threshold, simulator.scene.reflectivity[EDGE], count)
    return _point_family(placement, point, first_source + np.arange(count), strength, SPURIOUS)


def _point_family(placement: Placement, point, source, strength, origin: int) -> Paths:
    """Paths that diffract at points ``point`` (F, 2): ``|T - P| + |P - R|`` for every group, slot and receiver."""
    p = point[:, None, None, None, :]
    t = placement.tx[None, :, :, None, :]
    r = placement.rx[None, :, None, :, :]
    out, back = p - t, p - r
    horizontal = np.hypot(out[..., 0], out[..., 1]) + np.hypot(back[..., 0], back[..., 1])
    unknown = np.full((len(point),) + placement.tx.shape, np.nan)
    return Paths(source=source, strength=strength, origin=origin, horizontal=horizontal,
                 exists=np.ones(horizontal.shape, dtype=bool), out_point=p, in_point=p, legs=[(t, p), (p, r)],
                 truth_position=unknown, truth_normal=unknown)


# --------------------------------------------------------------------------- multipath


_ON_LINE = 1e-6
"""m: an edge this close to a wall's line is that wall's end, not something the wall mirrors."""


def multipath_paths(simulator: Simulator, placement: Placement, gain: float, first_source: int) -> list[Paths]:
    """Second-order reflections of the scene by the image method: wall -> wall, wall -> edge, edge -> wall.

    Every ordered pair of walls that is not one of the scene's corners, and every
    wall with every edge not on its line, is one family member (row key from
    ``first_source`` in that order).  A path exists where each reflection point
    lies on its wall's segment, on the side the sound comes from; the blocking
    and beam tests are :meth:`Simulator.hear`'s.

    Returns
    -------
    list of Paths
        Wall-wall, wall-edge and edge-wall families (those the scene has).
    """
    scene = simulator.scene
    walls = len(scene.walls)
    corner = np.zeros((walls, walls), dtype=bool)
    corner[scene.corner_walls[:, 0], scene.corner_walls[:, 1]] = True
    corner |= corner.T
    first, second = np.nonzero(~corner & ~np.eye(walls, dtype=bool))
    plane = scene.reflectivity[PLANE]
    families = []
    source = first_source
    if first.size:
        families.append(_second_order(simulator, placement, WALL_WALL, first, second, np.arange(first.size) + source,
                                      np.full(first.size, gain * plane * plane)))
        source += first.size
    if len(scene.edges) and walls:
        offsets = np.abs(_dot(scene.edges[None, :, :] - simulator.wall_start[:, None, :],
                              simulator.wall_normal[:, None, :]))  # (W, E)
        wall, edge = np.nonzero(offsets > _ON_LINE)
        strength = np.full(wall.size, gain * plane * scene.reflectivity[EDGE])
        families.append(_second_order(simulator, placement, WALL_POINT, wall, edge, np.arange(wall.size) + source,
                                      strength))
        source += wall.size
        families.append(_second_order(simulator, placement, POINT_WALL, edge, wall, np.arange(wall.size) + source,
                                      strength))
    return families


def _second_order(simulator: Simulator, placement: Placement, kind: int, first, second, source, strength) -> Paths:
    """The family of double bounces ``kind`` (:mod:`sonar_ring.image_method`) at the walls and edges of each member.

    ``first`` and ``second`` (F,) are rows of the scene's walls or edges, as
    ``kind`` says; every member's paths for every group, slot and receiver.
    """
    tx, rx = placement.tx, placement.rx
    groups, slots = tx.shape[:2]
    member, group, slot = (index.reshape(-1) for index in np.indices((len(first), groups, slots)))
    # Through the module: a kernel imported by name stays the wrapper that compiles at first use.
    horizontal, exists, first_point, last_point = image_method.double_bounces(
        np.full(member.size, kind), first[member], second[member], group, slot,
        simulator.wall_start, simulator.wall_direction, simulator.wall_normal, simulator.wall_length,
        np.ascontiguousarray(simulator.scene.edges), tx, rx, 0.0)
    shape = (len(first),) + tx.shape[:2] + rx.shape[1:2]
    first_point, last_point = first_point.reshape(shape + (2,)), last_point.reshape(shape + (2,))
    t = tx[None, :, :, None, :]
    r = rx[None, :, None, :, :]
    unknown = np.full((len(first),) + tx.shape, np.nan)
    return Paths(source=source, strength=strength, origin=MULTIPATH, horizontal=horizontal.reshape(shape),
                 exists=exists.reshape(shape), out_point=first_point, in_point=last_point,
                 legs=[(t, first_point), (first_point, last_point), (last_point, r)], truth_position=unknown,
                 truth_normal=unknown)


def _dot(u, v):
    return u[..., 0] * v[..., 0] + u[..., 1] * v[..., 1]


# --------------------------------------------------------------------------- late echoes


def late_echoes(heard: Heard, listened: float, absorption_db_per_m: float, first_source: int) -> Heard:
    """The echoes of ``heard`` (one ping's, unmeasured) that arrive after the next ping fired, as that ping hears them.

    ``listened`` is the path (m) the sound travels in one ping period; an echo
    of path ``d > listened`` is heard ``listened`` early, with the amplitude the
    time-variable gain gives it (module docstring; ``absorption_db_per_m`` from
    :func:`air_absorption`).  Each keeps its receiver; row keys count from
    ``first_source``, one per echo row of the ping that sent it.
    """
    late = heard.take(heard.path > listened)
    apparent = late.path - listened
    amplitude = late.amplitude * apparent / late.path * 10.0 ** (-absorption_db_per_m * listened / 20.0)
    _, row = np.unique(np.stack([late.source, late.group, late.slot]), axis=1, return_inverse=True)
    unknown = np.full((len(late), 2), np.nan)
    return replace(late, source=first_source + row.reshape(-1), origin=np.full(len(late), LATE), path=apparent,
                   amplitude=amplitude, truth_position=unknown, truth_normal=unknown, in_point=unknown)


# --------------------------------------------------------------------------- the world


_STREAMS = {"odometry": 1, "misses": 2, "spurious": 3, "multipath": 4, "late": 5}
"""Each effect's generator: ``default_rng([seed, stream])``; the forward model's own is ``default_rng(seed)``."""


class World:
    """A scene as a robot measures it: the forward model and the realism effects, ping by ping.

    Parameters
    ----------
    scene : Scene
    layout : Layout
    realism : Realism
        The effects (:data:`IDEAL`: the forward model exactly).
    noise : Noise
        Measurement noise of every echo (the forward model's).
    seed : int
        Seed of every generator: the forward model's noise uses
        ``default_rng(seed)`` as :meth:`Simulator.ping` would, each effect one of its own.
    ping_rate : float, optional
        Pings per second, Hz (the late echoes' period); default the layout's.
    threshold : float
        Detection threshold relative to ``A_max``.

    Attributes
    ----------
    simulator : Simulator
        The forward model.
    odometry : WheelOdometry
        Feed it the true poses in order (:meth:`odometry_pose`).
    """

    def __init__(self, scene: Scene, layout: Layout, realism: Realism = IDEAL, *, noise: Noise = NOISE_FREE,
                 seed: int = 0, ping_rate: float | None = None, threshold: float = DEFAULT_THRESHOLD):
        self.simulator = Simulator(scene, layout, threshold)
        self.realism = realism
        self.noise = noise
        self.ping_rate = float(ping_rate or layout.ping_rate)
        self._rng = np.random.default_rng(seed)
        self._streams = {name: np.random.default_rng([seed, stream]) for name, stream in _STREAMS.items()}
        self.odometry = WheelOdometry(realism, self._streams["odometry"])
        self._absorption = air_absorption(layout.frequency, scene.temperature_c + realism.temperature_offset,
                                          scene.relative_humidity)
        self._late: Heard | None = None
        # Row keys past the scene's reflectors: an effect's echoes never share a row with a reflector's.
        self._first_source = scene.n_reflectors

    def odometry_pose(self, true_pose) -> np.ndarray:
        """The odometry's pose ``(x, y, yaw)`` in ``odom`` with the robot next at ``true_pose`` (world)."""
        return self.odometry.step(true_pose)

    def ping(self, pose, time: float) -> Ping:
        """One ping with the sensor at ``pose`` (world x, y, yaw), ``time`` s into the run.

        Stateful: a ping hears the late echoes of the one before it.
        """
        simulator, r = self.simulator, self.realism
        placement = simulator.place(pose)
        speed = air_speed(simulator.scene, r, time)
        max_path = simulator.max_path
        listened = speed / self.ping_rate
        if r.late_echoes:
            reflections = simulator.reflections(placement, max_path=listened + max_path)
            own = reflections.take(reflections.path <= min(listened, max_path))
        else:
            own = simulator.reflections(placement)
        heard = [simulator.measure(own, self.noise, self._rng, speed)]
        source = self._first_source
        families = multipath_paths(simulator, placement, r.multipath_gain, source) if r.multipath_gain else []
        if families:  # a scene of one wall and no edge has no second-order path
            paths = [simulator.hear(family, placement, min(listened, max_path) if r.late_echoes else max_path)
                     for family in families]
            heard.append(simulator.measure(Heard.concatenate(paths), self.noise, self._streams["multipath"], speed))
            source += sum(len(family.source) for family in families)
        if r.spurious_rate:
            family = spurious_paths(simulator, placement, r.spurious_rate, self._streams["spurious"], source)
            heard.append(simulator.measure(simulator.hear(family, placement), self.noise, self._streams["spurious"],
                                           speed))
            source += len(family.source)
        if r.late_echoes:
            if self._late is not None:
                heard.append(simulator.measure(replace(self._late, source=self._late.source + source), self.noise,
                                               self._streams["late"], speed))
            self._late = late_echoes(reflections, listened, self._absorption, 0)
        measured = Heard.concatenate(heard)
        if r.fading_db:
            missed = self._streams["misses"].random(len(measured)) < miss_probability(
                measured.amplitude, simulator.threshold, r.fading_db)
            measured = measured.take(~missed)
        return simulator.echo_rows(measured, placement, self.noise, self._rng, time,
                                   simulator.scene.speed_of_sound)


def origins(ping: Ping) -> np.ndarray:
    """Echo rows per origin code (:data:`~sonar_ring.simulate.DIRECT` ... :data:`~sonar_ring.simulate.LATE`), (4,)."""
    return np.bincount(ping.truth_origin, minlength=LATE + 1)

