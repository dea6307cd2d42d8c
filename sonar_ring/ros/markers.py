"""RViz markers for landmarks: a few markers per ping, however many landmarks.

Planes are one LINE_LIST (a short segment along the wall through each foot
point, or the observed extent where it is longer), corners, edges and unknown
reflectors one POINTS marker each.  Colours are by class, alpha by confidence
(per point where confidences differ, else the marker's colour);
namespaces and ids are fixed, so each ping replaces the previous markers, and a
lifetime makes them vanish when pings stop.

The MarkerArray is written straight into its serialized (CDR) form from the
arrays, and published as such: built from message objects, each point would be
a ``geometry_msgs/Point`` made in Python, a cost per point -- and a map's
covariance ellipses alone have 32 points each.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from visualization_msgs.msg import Marker

from sonar_ring.landmarks import CLASS_NAMES, CORNER, CORNER_OR_EDGE, EDGE, PLANE, UNKNOWN, Landmarks, ellipse_outlines
from sonar_ring.ros.convert import Cdr

CLASS_COLOURS = {
    PLANE: (0.15, 0.45, 1.0),
    CORNER: (1.0, 0.3, 0.15),
    EDGE: (0.1, 0.8, 0.3),
    CORNER_OR_EDGE: (0.95, 0.7, 0.1),
    UNKNOWN: (0.7, 0.7, 0.7),
}
"""RGB of each class."""

MIN_ALPHA = 0.3
"""Alpha at zero confidence, so undecided landmarks still show."""


@dataclass(frozen=True)
class MarkerParts:
    """The fields of one ``visualization_msgs/Marker`` that vary here; the rest keep their defaults.

    Attributes
    ----------
    ns : str
        Namespace; the id is 0, so a new message replaces the previous one.
    type : int
        ``Marker.LINE_LIST`` or ``Marker.POINTS``.
    scale : tuple of float
        ``scale.x, scale.y, scale.z``, m (line width; point width and height).
    color : tuple of float
        r, g, b, a in [0, 1].
    points : ndarray, shape (P, 2)
        x, y in the header's frame, m; z is 0.
    colors : ndarray, shape (P, 4) or (0, 4)
        Per-point r, g, b, a, or none (the marker's ``color`` applies).
    lifetime : float
        s before RViz removes it; 0 keeps it.
    """

    ns: str
    type: int
    scale: tuple
    color: tuple
    points: np.ndarray
    colors: np.ndarray
    lifetime: float = 0.0

    def __post_init__(self) -> None:
        points, colors = np.asarray(self.points).shape, np.asarray(self.colors).shape
        if len(self.scale) != 3 or len(self.color) != 4:
            raise ValueError(f"marker {self.ns!r}: scale needs 3 values and color 4, got {self.scale!r}, "
                             f"{self.color!r}")
        if len(points) != 2 or points[1] != 2 or colors not in ((points[0], 4), (0, 4)):
            raise ValueError(f"marker {self.ns!r}: points must be (P, 2) and colors (P, 4) or (0, 4), got {points} "
                             f"and {colors}")
        if not (math.isfinite(self.lifetime) and self.lifetime >= 0):
            raise ValueError(f"marker {self.ns!r}: lifetime must be finite and >= 0 s, got {self.lifetime!r}")


def serialize_markers(markers: list[MarkerParts], header) -> bytes:
    """A serialized ``visualization_msgs/MarkerArray`` of ``markers``, all with ``header`` (message or decoded).

    The message ``rclpy.serialization.serialize_message`` gives for the same
    MarkerArray built from message objects: same length, same fields when
    decoded (padding bytes are zero here; CDR leaves them unspecified).
    Publishers take it as it is (``test/test_markers.py``).
    """
    cdr = Cdr()
    cdr.pack("I", len(markers), align=4)
    # Every marker's header: the same bytes, 4-aligned wherever they go.
    stamped = Cdr()
    stamped.header(header.stamp.sec, header.stamp.nanosec, header.frame_id)
    header_bytes = bytes(stamped.buffer[4:])
    for marker in markers:
        cdr.align(4)
        cdr.buffer += header_bytes
        cdr.string(marker.ns)
        cdr.pack("iii", 0, marker.type, Marker.ADD, align=4)
        # pose (origin, identity orientation) and scale; color, lifetime and frame_locked
        cdr.pack("10d", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, *marker.scale, align=8)
        whole = int(marker.lifetime)
        cdr.pack("4fiI?", *marker.color, whole, int(round((marker.lifetime - whole) * 1e9)), False, align=4)
        # An empty sequence is its length alone: no numpy for the empty markers of most pings.
        points, colors = marker.points, marker.colors
        if len(points):
            points = np.zeros((len(points), 3))
            points[:, :2] = marker.points
        cdr.array(points, 8)
        cdr.array(np.asarray(colors, dtype=np.float32).reshape(-1, 4) if len(colors) else colors, 4)
        cdr.buffer += _MARKER_TAIL
    return bytes(cdr.buffer)


def _marker_tail() -> bytes:
    """The fields after ``colors``, all empty: the same bytes for every marker (``colors`` ends 4-aligned)."""
    cdr = Cdr()
    cdr.string("")  # texture_resource
    cdr.header(0, 0, "")  # texture: sensor_msgs/CompressedImage
    cdr.string("")
    cdr.array(np.empty(0, dtype=np.uint8), 1)
    cdr.array(np.empty((0, 2), dtype=np.float32), 4)  # uv_coordinates
    cdr.string("")  # text
    cdr.string("")  # mesh_resource
    cdr.string("")  # mesh_file: filename, data
    cdr.array(np.empty(0, dtype=np.uint8), 1)
    cdr.pack("?", False, align=1)  # mesh_use_embedded_materials
    return bytes(cdr.buffer[4:])


_MARKER_TAIL = _marker_tail()

_NO_COLOURS = np.empty((0, 4), dtype=np.float32)
_NO_COLOURS.flags.writeable = False
_NO_POINTS = np.empty((0, 2))
_NO_POINTS.flags.writeable = False


def _coloured(landmark_class: int, confidence: np.ndarray, repeat: int) -> tuple[tuple, np.ndarray]:
    """Colour by class, alpha by confidences (one or more): the marker colour, per-point colours if alphas differ."""
    r, g, b = CLASS_COLOURS[landmark_class]
    alpha = MIN_ALPHA + (1.0 - MIN_ALPHA) * confidence.clip(0.0, 1.0)
    colour = (r, g, b, float(alpha[0]))
    if alpha.min() == alpha.max():  # one alpha for all (False with NaN, which then shows per point)
        return colour, _NO_COLOURS
    per_point = np.repeat(alpha, repeat)
    return colour, np.column_stack([np.full((per_point.size, 3), (r, g, b)), per_point]).astype(np.float32)


def plane_segments(landmarks: Landmarks, min_length: float) -> np.ndarray:
    """End points of the line drawn for each plane, shape (L, 2, 2), m.

    The observed extent where it is at least ``min_length`` long, else a segment
    of ``min_length`` along the wall centred on the foot point.
    """
    ends = landmarks.segment
    length = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=-1)
    along = np.stack([-landmarks.normal[:, 1], landmarks.normal[:, 0]], axis=-1)
    short = landmarks.position[:, None, :] + np.array([-0.5, 0.5])[None, :, None] * min_length * along[:, None, :]
    return np.where((length >= min_length)[:, None, None], ends, short)


def landmark_markers(landmarks: Landmarks, namespace: str, lifetime: float, point_size: float = 0.06,
                     line_width: float = 0.03, min_plane_length: float = 0.25) -> list[MarkerParts]:
    """One marker per class in ``namespace/<class>``; ``lifetime`` 0 keeps them forever."""
    markers = []
    shown = np.where(landmarks.valid, landmarks.landmark_class, len(CLASS_NAMES))
    # Each class's rows, in row order: one stable sort, not one comparison and search per class.
    order = shown.argsort(kind="stable")
    bounds = shown[order].searchsorted(np.arange(len(CLASS_NAMES) + 1)).tolist()
    for code, name in enumerate(CLASS_NAMES):
        rows = order[bounds[code]:bounds[code + 1]]
        kind, scale, repeat = ((Marker.LINE_LIST, (line_width, 0.0, 0.0), 2) if code == PLANE
                               else (Marker.POINTS, (point_size, point_size, 0.0), 1))
        if not rows.size:  # as most classes in most pings: no numpy
            colour, colours, points = (*CLASS_COLOURS[code], 1.0), _NO_COLOURS, _NO_POINTS
        else:
            colour, colours = _coloured(code, landmarks.confidence[rows], repeat)
            points = (plane_segments(landmarks, min_plane_length).take(rows, axis=0).reshape(-1, 2) if code == PLANE
                      else landmarks.position.take(rows, axis=0))
        markers.append(MarkerParts(f"{namespace}/{name}", kind, scale, colour, points, colours, lifetime))
    return markers


EXPLAINED_COLOURS = {"multipath": (0.8, 0.2, 0.8, 0.8), "impossible": (0.5, 0.1, 0.1, 0.8)}
"""RGBA of the landmarks the map explained, by how."""


def explained_markers(explained: dict, namespace: str, point_size: float = 0.04) -> list[MarkerParts]:
    """One POINTS marker per way the map explains a landmark (``namespace/explained/<how>``).

    ``explained`` maps each name of :data:`EXPLAINED_COLOURS` to positions (P, 2), m.
    """
    return [MarkerParts(f"{namespace}/explained/{how}", Marker.POINTS, (point_size, point_size, 0.0), colour,
                        np.asarray(explained[how], dtype=float).reshape(-1, 2), _NO_COLOURS)
            for how, colour in EXPLAINED_COLOURS.items()]


def covariance_ellipses(landmarks: Landmarks, namespace: str, sigma: float = 2.0, sides: int = 16) -> MarkerParts:
    """A LINE_LIST of ``sigma``-sigma position ellipses, one per point landmark."""
    chosen = landmarks.select(landmarks.valid & (landmarks.landmark_class != PLANE)
                              & np.all(np.isfinite(landmarks.covariance), axis=(1, 2)))
    ring = ellipse_outlines(chosen.position, chosen.covariance, sigma, sides)  # (L, S+1, 2)
    pairs = np.stack([ring[:, :-1], ring[:, 1:]], axis=2).reshape(-1, 2)
    return MarkerParts(f"{namespace}/covariance", Marker.LINE_LIST, (0.005, 0.0, 0.0), (0.9, 0.9, 0.2, 0.8), pairs,
                       np.empty((0, 4), dtype=np.float32))
