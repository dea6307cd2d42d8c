"""Sensor layouts, the medium and the transducers' beam width.

A *layout* says where the transmitters and receivers of one sensor are, which way
they face, and how receivers are grouped: a Browne ring pair (2 receivers, one
emitter at the ring centre), a Barshan & Kuc transducer pair (2 transducers that
both transmit and receive) or a Kreczmer triad (3 receivers, one emitter).

Frames and units (REP 103): metres, radians, seconds; the sensor frame has x
forward, y left, z up, yaw counter-clockwise from +x.  Every localisation problem
of the package is solved in the horizontal (x, y) plane of this frame; heights
only enter through the vertical correction ``sqrt(d**2 - dz**2)``.

Layouts are read from YAML (``config/layouts/*.yaml``).  Two forms exist:

* ``ring:`` -- Browne's ring, generated from a few documented parameters;
* ``transducers:`` -- an explicit list, for pairs, linear arrays and triads.

A malformed file raises :class:`LayoutError` naming the file, the field and the
expected value.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml


def _find_config_dir() -> Path:
    """The package's ``config/`` folder, wherever this module was installed from.

    A source checkout has it beside the package; ``pip install`` and ``colcon``
    both install it as ``<prefix>/share/sonar_ring/config``.
    """
    here = Path(__file__).resolve()
    for parent in here.parents:
        for candidate in (parent / "share" / "sonar_ring" / "config", parent / "config"):
            if (candidate / "layouts").is_dir():
                return candidate
    raise FileNotFoundError(f"sonar_ring: no config/layouts folder above {here}")


CONFIG_DIR = _find_config_dir()
"""The package's ``config/`` folder (layouts, scenes, node parameters)."""

KINDS = ("ring", "pair", "triad")
"""Group kinds: ring pairs (single emitter), transducer pairs (both transmit), triads."""


MAX_RING_PAIRS = 1024
"""Most receiver pairs a ring layout may have (0.35 deg apart); more is a typing error, not a sensor."""
MAX_PING_RATE = 2000.0
"""Fastest ping rate a layout may give, Hz (the driver's ``ping_rate`` range)."""
MAX_SENSOR_EXTENT = 100.0
"""Largest |coordinate| of a transducer, m: a sensor is smaller; more is a typing error (and would overflow)."""


class LayoutError(ValueError):
    """A layout file or mapping is malformed; the message names file and field."""


@dataclass(frozen=True)
class GroupPlan:
    """A layout's groups seen from above (:attr:`Layout.plan`); G groups, K receivers, M transmitters each.

    Attributes
    ----------
    receivers : ndarray, shape (G, K, 2)
        Horizontal receiver positions, m, sensor frame.
    transmitters : ndarray, shape (G, M, 2)
        Horizontal transmitter positions, m.
    height_offset : ndarray, shape (G, M, K)
        Transmitter minus receiver height, m (:meth:`Layout.height_offset`).
    facing : ndarray, shape (G, 2)
        Unit vector along each group's facing.
    yaw : ndarray, shape (G,)
        That facing's angle, rad (:meth:`Layout.group_yaw`).
    receiver_yaw, transmitter_yaw : ndarray, shape (G, K) and (G, M)
        The facing of each group's receivers and transmitters, rad.
    """

    receivers: np.ndarray
    transmitters: np.ndarray
    height_offset: np.ndarray
    facing: np.ndarray
    yaw: np.ndarray
    receiver_yaw: np.ndarray
    transmitter_yaw: np.ndarray


@dataclass(frozen=True)
class Layout:
    """One sensor: transducer positions, facing, beams and receiver groups.

    Attributes
    ----------
    name : str
        Layout name (the YAML file stem by convention).
    kind : str
        One of :data:`KINDS`; every group of a layout has the same kind.
    transmitters : ndarray, shape (T, 3)
        Transmitter positions in the sensor frame, m.
    transmitter_yaw : ndarray, shape (T,)
        Facing of each transmitter, rad.  Ignored where ``isotropic_emitter``.
    receivers : ndarray, shape (R, 3)
        Receiver positions in the sensor frame, m.
    receiver_yaw : ndarray, shape (R,)
        Facing (acoustic axis) of each receiver, rad.
    groups : ndarray of int, shape (G, K)
        Receiver indices of each group (K = 2 for pairs, 3 for triads), ordered
        left to right as seen looking along the group's facing: column 0 is the
        counter-clockwise-most receiver (Browne's R1, Barshan & Kuc's a,
        Kreczmer's R0), so bearings come out counter-clockwise positive.
    group_transmitters : ndarray of int, shape (G, M)
        Transmitters whose echoes each group reports (M = 1 for a single emitter,
        2 for a Barshan & Kuc pair).
    beam_half_angle : float
        Receiver acceptance half-angle, rad (Polaroid 7000: 10 deg).
    isotropic_emitter : bool
        True where the emitter radiates equally in every horizontal direction
        (Browne's conical reflector); False for piston transducers.
    frequency : float
        Carrier frequency, Hz (wavelength = c / frequency).
    aperture_radius : float
        Transducer radius ``a`` of the piston model, m.
    ping_rate : float
        Pings per second the hardware runs at, Hz.
    max_range : float
        Largest range the receivers report, m.
    transducer_of_transmitter : ndarray of int, shape (T,)
        Receiver index that is the same physical transducer as each transmitter,
        or -1 (Barshan & Kuc transducers both transmit and receive).
    """

    name: str
    kind: str
    transmitters: np.ndarray
    transmitter_yaw: np.ndarray
    receivers: np.ndarray
    receiver_yaw: np.ndarray
    groups: np.ndarray
    group_transmitters: np.ndarray
    beam_half_angle: float
    isotropic_emitter: bool
    frequency: float
    aperture_radius: float
    ping_rate: float
    max_range: float
    transducer_of_transmitter: np.ndarray

    @property
    def n_groups(self) -> int:
        """Number of receiver groups G."""
        return int(self.groups.shape[0])

    @property
    def receivers_per_group(self) -> int:
        """Receivers in each group K (2 for pairs, 3 for triads)."""
        return int(self.groups.shape[1])

    def group_receivers(self) -> np.ndarray:
        """Receiver positions of every group, shape (G, K, 3), m."""
        return self.receivers[self.groups]

    def group_centre(self) -> np.ndarray:
        """Mid-point of each group's receivers, shape (G, 3), m."""
        return self.group_receivers().mean(axis=1)

    def group_viewpoint(self) -> np.ndarray:
        """Where each group's echoes are seen from: the mean of its transmitters' horizontal positions, (G, 2), m.

        A single emitter's own position (the centre of Browne's ring, a triad module's emitter); the middle of a
        Barshan & Kuc pair.  A wall's echo returns from the foot of the perpendicular from there.
        """
        return self.transmitters[self.group_transmitters, :2].mean(axis=1)

    def group_yaw(self) -> np.ndarray:
        """Facing of each group (mean receiver yaw, wrapped), shape (G,), rad."""
        yaw = self.receiver_yaw[self.groups]
        return np.arctan2(np.sin(yaw).mean(axis=1), np.cos(yaw).mean(axis=1))

    def group_separation(self) -> np.ndarray:
        """Horizontal distance between the outermost receivers of each group, (G,), m."""
        ends = self.group_receivers()[:, [0, -1], :2]
        return np.linalg.norm(ends[:, 1] - ends[:, 0], axis=-1)

    def height_offset(self) -> np.ndarray:
        """Transmitter minus receiver height, shape (G, M, K), m.

        This is the ``dz`` of the exact vertical correction for each group, each of
        its transmitters and each of its receivers.
        """
        tz = self.transmitters[self.group_transmitters, 2]  # (G, M)
        rz = self.receivers[self.groups, 2]  # (G, K)
        return tz[:, :, None] - rz[:, None, :]

    @functools.cached_property
    def plan(self) -> GroupPlan:
        """The groups' horizontal geometry, computed at first use and kept (read-only arrays).

        For per-echo code that indexes it by group on every ping; the layout is
        immutable, so it never goes stale.
        """
        yaw = self.group_yaw()
        arrays = tuple(np.ascontiguousarray(array, dtype=float) for array in (
            self.group_receivers()[..., :2], self.transmitters[self.group_transmitters, :2], self.height_offset(),
            np.stack([np.cos(yaw), np.sin(yaw)], axis=-1), yaw, self.receiver_yaw[self.groups],
            self.transmitter_yaw[self.group_transmitters]))
        for array in arrays:
            array.flags.writeable = False
        return GroupPlan(*arrays)

    def wavelength(self, speed_of_sound: float) -> float:
        """Carrier wavelength at the given speed of sound, m."""
        return speed_of_sound / self.frequency


# --------------------------------------------------------------------------- medium

def speed_of_sound(temperature_c, relative_humidity=0.0, pressure_pa=101325.0):
    """Speed of sound in air, m/s, vectorised over its arguments.

    Ideal-gas dry-air value ``20.05 * sqrt(T_v)`` with the virtual temperature
    ``T_v`` accounting for water vapour (saturation pressure by the Magnus
    formula).  At 20 degC dry: 343.3 m/s; 20 degC, 50 % RH: 344.0 m/s.  Near room
    temperature dc/dT / c is about 1.7e-3 per K, so 1 K of temperature error is
    1.7 mm of range per metre.

    Parameters
    ----------
    temperature_c : array_like
        Air temperature, degC (> -273.15).
    relative_humidity : array_like
        Relative humidity in percent, 0..100.
    pressure_pa : array_like
        Static pressure, Pa.
    """
    t = np.asarray(temperature_c, dtype=float)
    rh = np.asarray(relative_humidity, dtype=float)
    if np.any(t <= -273.15) or np.any((rh < 0) | (rh > 100)) or np.any(np.asarray(pressure_pa) <= 0):
        raise ValueError("speed_of_sound: need temperature > -273.15 degC, 0 <= humidity <= 100 %, pressure > 0")
    kelvin = t + 273.15
    vapour_pressure = rh / 100.0 * 611.2 * np.exp(17.62 * t / (243.12 + t))
    virtual_kelvin = kelvin / (1.0 - vapour_pressure / pressure_pa * (1.0 - 0.622))
    return 20.05 * np.sqrt(virtual_kelvin)


# --------------------------------------------------------------------------- beams

def beam_half_angle(wavelength, aperture_radius):
    """Far-field half-angle of a piston transducer, rad (Barshan & Kuc eq 2).

    ``theta0 = asin(0.61 * lambda / a)``; 10.05 deg for lambda = 5.72 mm, a = 20 mm.
    """
    ratio = 0.61 * np.asarray(wavelength, dtype=float) / np.asarray(aperture_radius, dtype=float)
    if np.any(ratio > 1) or np.any(ratio <= 0):
        raise ValueError("beam_half_angle: need 0 < 0.61 * wavelength / aperture_radius <= 1")
    return np.arcsin(ratio)


# --------------------------------------------------------------------------- loading

def config_path(folder: str, name: str) -> Path:
    """Path of a shipped config file by name, e.g. ``config_path("layouts", "browne_ring")``."""
    return CONFIG_DIR / folder / f"{name}.yaml"


def shipped_params(layout_name: str) -> Path | None:
    """The node parameters shipped for a layout (``config/params/<name>.yaml``), None where it has none."""
    path = config_path("params", layout_name)
    return path if path.is_file() else None


def layout_path(name: str) -> Path:
    """Path of a shipped layout by name, e.g. ``layout_path("browne_ring")``."""
    return config_path("layouts", name)


def load_layout(source) -> Layout:
    """Load a layout from a shipped name, a YAML path or a mapping.

    Raises :class:`LayoutError` naming the file and the field on any problem.
    """
    mapping, where = read_config(source, "layouts", LayoutError)
    return _layout_from_mapping(mapping, where)


def read_config(source, folder: str, error: type[ValueError]) -> tuple[dict, str]:
    """The mapping of a config file, and where it came from (for error messages).

    ``source`` is a mapping (returned as is, from ``"<mapping>"``), a path to a
    YAML file, or a bare name of a shipped file in ``config/<folder>/``.  A file
    that cannot be read, is not YAML or is not a mapping raises ``error`` with
    the path and the reason.
    """
    if isinstance(source, dict):
        return source, "<mapping>"
    path = Path(source)
    if not path.suffix:
        path = config_path(folder, str(source))
    what = folder.rstrip("s")
    try:
        mapping = yaml.safe_load(path.read_bytes())
    except OSError as exc:
        raise error(f"{path}: cannot read {what} ({exc.strerror})") from exc
    except yaml.YAMLError as exc:
        # PyYAML spreads its message over several lines; a log line wants one.
        raise error(f"{path}: not valid YAML ({' '.join(str(exc).split())})") from exc
    if not isinstance(mapping, dict):
        raise error(f"{path}: expected a mapping of fields at the top level, got {type(mapping).__name__}")
    return mapping, str(path)


def _field(mapping, key, where, kind=float, positive=True, high=math.inf):
    """``mapping[key]``: a count in 1..``high`` (``kind`` int) or a number, > 0 if ``positive``, |x| <= ``high``."""
    if kind is int:
        expected = f"an integer in 1..{high:g}"
    elif positive:
        expected = "a finite number > 0" + (f" and <= {high:g}" if high < math.inf else "")
    else:
        expected = f"a number in -{high:g}..{high:g}" if high < math.inf else "a finite number"
    if not isinstance(mapping, dict):
        raise LayoutError(f"{where}: expected a mapping with field '{key}' ({expected}), got {mapping!r}")
    if key not in mapping:
        raise LayoutError(f"{where}: missing field '{key}' ({expected})")
    value = mapping[key]
    try:
        if isinstance(value, bool) or (kind is int and value != int(value)):
            raise TypeError
        value = kind(value)
    except (TypeError, ValueError, OverflowError):
        raise LayoutError(f"{where}: field '{key}' must be {expected}, got {value!r}") from None
    if not (math.isfinite(value) and (value > 0 or not positive) and abs(value) <= high):
        raise LayoutError(f"{where}: field '{key}' must be {expected}, got {value!r}")
    return value


_COMMON_FIELDS = ("name", "kind", "beam_half_angle_deg", "frequency_hz", "aperture_radius", "ping_rate_hz",
                  "max_range")
_LAYOUT_FIELDS = {"ring": _COMMON_FIELDS + ("ring",),
                  "pair": _COMMON_FIELDS + ("transducers", "groups", "isotropic_emitter"),
                  "triad": _COMMON_FIELDS + ("transducers", "groups", "isotropic_emitter")}
"""Fields a layout of each kind may have; any other is a typing error (an optional field would be ignored)."""


def _known_fields(mapping: dict, allowed, where: str) -> None:
    unknown = sorted(set(mapping) - set(allowed), key=str)
    if unknown:
        raise LayoutError(f"{where}: unknown field {unknown[0]!r} (expected some of {sorted(allowed)})")


def _layout_from_mapping(m: dict, where: str) -> Layout:
    name = str(m.get("name", Path(where).stem))
    kind = m.get("kind")
    if kind not in KINDS:
        raise LayoutError(f"{where}: field 'kind' must be one of {', '.join(KINDS)}, got {kind!r}")
    _known_fields(m, _LAYOUT_FIELDS[kind], where)
    common = dict(
        name=name,
        kind=kind,
        beam_half_angle=math.radians(_field(m, "beam_half_angle_deg", where)),
        frequency=_field(m, "frequency_hz", where),
        aperture_radius=_field(m, "aperture_radius", where),
        ping_rate=_field(m, "ping_rate_hz", where, high=MAX_PING_RATE),
        max_range=_field(m, "max_range", where),
    )
    if kind == "ring":
        if "ring" not in m or not isinstance(m["ring"], dict):
            raise LayoutError(f"{where}: missing field 'ring' (a mapping) for kind 'ring'")
        parts = _ring_parts(m["ring"], f"{where}: ring")
    else:
        parts = _explicit_parts(m, where, kind)
    layout = Layout(**common, **parts)
    _check_groups(layout, where)
    return layout


def _ring_parts(r: dict, where: str) -> dict:
    """Browne's ring: pairs every ``360/pairs`` deg, tiers alternating pair by pair.

    Pair ``i`` faces ``yaw_i = i * spacing``; its receivers sit on the tier's
    radius, ``separation/2`` either side of the pair's axis.  R1 (group column 0)
    is the counter-clockwise (left) one, so that Browne's eq 4 bearing, positive
    when the echo is nearer R1 (d1 < d2), is counter-clockwise positive as REP 103
    wants.
    """
    _known_fields(r, ("pairs", "separation", "emitter_height", "tiers"), where)
    pairs = _field(r, "pairs", where, int, high=MAX_RING_PAIRS)
    separation = _field(r, "separation", where, high=MAX_SENSOR_EXTENT)
    emitter_height = _field(r, "emitter_height", where, positive=False, high=MAX_SENSOR_EXTENT)
    tiers = r.get("tiers")
    if not isinstance(tiers, list) or not tiers:
        raise LayoutError(f"{where}: field 'tiers' must be a non-empty list of {{radius, height}}")
    for k, t in enumerate(tiers):
        if isinstance(t, dict):
            _known_fields(t, ("radius", "height"), f"{where}: tiers[{k}]")
    tier_radius = [_field(t, "radius", f"{where}: tiers[{k}]", high=MAX_SENSOR_EXTENT) for k, t in enumerate(tiers)]
    tier_height = [_field(t, "height", f"{where}: tiers[{k}]", positive=False, high=MAX_SENSOR_EXTENT)
                   for k, t in enumerate(tiers)]
    index = np.arange(pairs)
    yaw = index * (2 * math.pi / pairs)
    tier = index % len(tiers)
    radius = np.take(tier_radius, tier)
    height = np.take(tier_height, tier)
    axis = np.stack([np.cos(yaw), np.sin(yaw)], axis=-1)
    left = np.stack([-np.sin(yaw), np.cos(yaw)], axis=-1)
    centre = radius[:, None] * axis
    r1 = centre + 0.5 * separation * left
    r2 = centre - 0.5 * separation * left
    receivers_xy = np.stack([r1, r2], axis=1).reshape(-1, 2)
    receivers = np.column_stack([receivers_xy, np.repeat(height, 2)])
    return dict(
        transmitters=np.array([[0.0, 0.0, emitter_height]]),
        transmitter_yaw=np.zeros(1),
        receivers=receivers,
        receiver_yaw=np.repeat(yaw, 2),
        groups=np.arange(2 * pairs).reshape(pairs, 2),
        group_transmitters=np.zeros((pairs, 1), dtype=int),
        isotropic_emitter=True,
        transducer_of_transmitter=np.array([-1]),
    )


def _explicit_parts(m: dict, where: str, kind: str) -> dict:
    """Transducers listed one by one, each with ``roles`` among transmit/receive."""
    items = m.get("transducers")
    if not isinstance(items, list) or not items:
        raise LayoutError(f"{where}: missing field 'transducers' (a non-empty list)")
    tx, tx_yaw, rx, rx_yaw, names_rx, names_tx, same = [], [], [], [], {}, {}, []
    for k, t in enumerate(items):
        here = f"{where}: transducers[{k}]"
        if not isinstance(t, dict):
            raise LayoutError(f"{here}: expected a mapping")
        _known_fields(t, ("name", "position", "yaw_deg", "roles"), here)
        name = str(t.get("name", k))
        pos = t.get("position")
        if not (isinstance(pos, list) and len(pos) == 3):
            raise LayoutError(f"{here}: field 'position' must be [x, y, z] in m, got {pos!r}")
        try:
            pos = [float(v) for v in pos]
        except (TypeError, ValueError, OverflowError):
            pos = [math.nan]
        if not all(abs(v) <= MAX_SENSOR_EXTENT for v in pos):
            raise LayoutError(f"{here}: field 'position' must hold three numbers in -{MAX_SENSOR_EXTENT:g}.."
                              f"{MAX_SENSOR_EXTENT:g} m, got {t['position']!r}")
        yaw = math.radians(_field(t, "yaw_deg", here, positive=False))
        roles = t.get("roles")
        if not (isinstance(roles, list) and roles and all(r in ("transmit", "receive") for r in roles)):
            raise LayoutError(f"{here}: field 'roles' must be a list of 'transmit'/'receive', got {roles!r}")
        if "receive" in roles:
            names_rx[name] = len(rx)
            rx.append(pos)
            rx_yaw.append(yaw)
        if "transmit" in roles:
            names_tx[name] = len(tx)
            tx.append(pos)
            tx_yaw.append(yaw)
            same.append(names_rx.get(name, -1) if "receive" in roles else -1)
    groups = m.get("groups")
    if not isinstance(groups, list) or not groups:
        raise LayoutError(f"{where}: missing field 'groups' (a list of {{receivers, transmitters}})")
    g_rx, g_tx = [], []
    for k, g in enumerate(groups):
        here = f"{where}: groups[{k}]"
        if isinstance(g, dict):
            _known_fields(g, ("receivers", "transmitters"), here)
        try:
            g_rx.append([names_rx[str(n)] for n in g["receivers"]])
            g_tx.append([names_tx[str(n)] for n in g["transmitters"]])
        except (KeyError, TypeError) as exc:
            raise LayoutError(f"{here}: fields 'receivers'/'transmitters' must name transducers "
                              f"with that role ({exc})") from None
    if len({len(g) for g in g_rx}) != 1 or len({len(g) for g in g_tx}) != 1:
        raise LayoutError(f"{where}: field 'groups': every group needs the same number of receivers and transmitters")
    return dict(
        transmitters=np.array(tx, dtype=float).reshape(-1, 3),
        transmitter_yaw=np.array(tx_yaw, dtype=float),
        receivers=np.array(rx, dtype=float).reshape(-1, 3),
        receiver_yaw=np.array(rx_yaw, dtype=float),
        groups=np.array(g_rx, dtype=int),
        group_transmitters=np.array(g_tx, dtype=int),
        isotropic_emitter=bool(m.get("isotropic_emitter", False)),
        transducer_of_transmitter=np.array(same, dtype=int),
    )


def _check_groups(layout: Layout, where: str) -> None:
    expected = {"ring": 2, "pair": 2, "triad": 3}[layout.kind]
    if layout.receivers_per_group != expected:
        raise LayoutError(f"{where}: field 'groups': kind '{layout.kind}' needs {expected} receivers "
                          f"per group, got {layout.receivers_per_group}")
    gaps = np.linalg.norm(np.diff(layout.group_receivers()[:, :, :2], axis=1), axis=-1)
    if np.any(gaps <= 0):
        bad = int(np.argwhere(gaps <= 0)[0, 0])
        raise LayoutError(f"{where}: field 'groups': group {bad} has a zero receiver separation")
