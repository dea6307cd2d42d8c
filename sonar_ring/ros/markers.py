"""RViz markers for landmarks: a few markers per ping, however many landmarks.

Planes are one LINE_LIST (a short segment along the wall through each foot
point, or the observed extent where it is longer), corners, edges and unknown
reflectors one POINTS marker each.  Colours are by class, alpha by confidence
(per point where confidences differ, else the marker's colour);
namespaces and ids are fixed, so each ping replaces the previous markers, and a
lifetime makes them vanish when pings stop.
"""

from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from sonar_ring.landmarks import CLASS_NAMES, CORNER, EDGE, PLANE, UNKNOWN, Landmarks, ellipse_outlines

CLASS_COLOURS = {
    PLANE: (0.15, 0.45, 1.0),
    CORNER: (1.0, 0.3, 0.15),
    EDGE: (0.1, 0.8, 0.3),
    UNKNOWN: (0.7, 0.7, 0.7),
}
"""RGB of each class."""

MIN_ALPHA = 0.3
"""Alpha at zero confidence, so undecided landmarks still show."""


def _duration(seconds: float) -> Duration:
    whole = int(seconds)
    return Duration(sec=whole, nanosec=int(round((seconds - whole) * 1e9)))


def _colour(marker: Marker, landmark_class: int, confidence: np.ndarray, repeat: int) -> None:
    """Colour by class, alpha by confidence: one marker colour when every landmark has the same alpha.

    A per-point colour list costs a message object per point, so it is built only
    where alphas differ (decided landmarks); undecided ones all have zero confidence.
    """
    r, g, b = CLASS_COLOURS[landmark_class]
    alpha = MIN_ALPHA + (1.0 - MIN_ALPHA) * np.clip(confidence, 0.0, 1.0)
    uniform = alpha.size == 0 or bool(np.all(alpha == alpha[0]))
    marker.color = ColorRGBA(r=r, g=g, b=b, a=float(alpha[0]) if alpha.size else 1.0)
    if not uniform:
        marker.colors = [ColorRGBA(r=r, g=g, b=b, a=float(a)) for a in np.repeat(alpha, repeat)]


def _points(xy: np.ndarray) -> list[Point]:
    return [Point(x=float(x), y=float(y)) for x, y in xy]


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


def landmark_markers(landmarks: Landmarks, header, namespace: str, lifetime: float,
                     point_size: float = 0.06, line_width: float = 0.03, min_plane_length: float = 0.25) -> MarkerArray:
    """One marker per class in ``namespace/<class>``; ``lifetime`` 0 keeps them forever."""
    markers = []
    for code, name in enumerate(CLASS_NAMES):
        chosen = landmarks.select(landmarks.valid & (landmarks.landmark_class == code))
        marker = Marker(header=header, ns=f"{namespace}/{name}", id=0, action=Marker.ADD,
                        lifetime=_duration(lifetime), frame_locked=False)
        marker.pose.orientation.w = 1.0
        if code == PLANE:
            marker.type = Marker.LINE_LIST
            marker.scale.x = line_width
            marker.points = _points(plane_segments(chosen, min_plane_length).reshape(-1, 2))
            _colour(marker, code, chosen.confidence, 2)
        else:
            marker.type = Marker.POINTS
            marker.scale.x = marker.scale.y = point_size
            marker.points = _points(chosen.position)
            _colour(marker, code, chosen.confidence, 1)
        markers.append(marker)
    return MarkerArray(markers=markers)


def covariance_ellipses(landmarks: Landmarks, header, namespace: str, sigma: float = 2.0,
                        sides: int = 16) -> Marker:
    """A LINE_LIST of ``sigma``-sigma position ellipses, one per point landmark."""
    chosen = landmarks.select(landmarks.valid & (landmarks.landmark_class != PLANE)
                              & np.all(np.isfinite(landmarks.covariance), axis=(1, 2)))
    ring = ellipse_outlines(chosen.position, chosen.covariance, sigma, sides)  # (L, S+1, 2)
    pairs = np.stack([ring[:, :-1], ring[:, 1:]], axis=2).reshape(-1, 2)
    marker = Marker(header=header, ns=f"{namespace}/covariance", id=0, type=Marker.LINE_LIST, action=Marker.ADD)
    marker.pose.orientation.w = 1.0
    marker.scale.x = 0.005
    marker.color = ColorRGBA(r=0.9, g=0.9, b=0.2, a=0.8)
    marker.points = _points(pairs)
    return marker
