"""Landmarks as parallel arrays: what every stage of the pipeline passes on.

A :class:`Landmarks` holds L landmarks -- planes, corners, edges or unknown
reflectors -- as arrays whose first axis is the landmark.  It mirrors the
``sonar_ring/LandmarkArray`` message field for field, so the ROS layer converts
it without a loop, and the core (localisation, classification, mapping) works on it with
numpy.

Frames and units: positions in metres in one frame (the sensor frame for
per-ping landmarks, ``odom`` for the map), angles in radians counter-clockwise.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

UNKNOWN, PLANE, CORNER, EDGE, CORNER_OR_EDGE = 0, 1, 2, 3, 4
"""Landmark classes (the constants of ``Landmark.msg``).  CORNER_OR_EDGE is a map's: a fixed point (motion
ruled out a plane) whose wavefront's curvature has not yet told a corner from an edge."""

CLASS_NAMES = ("unknown", "plane", "corner", "edge", "corner_or_edge")
"""Lower-case name of each class code, indexable by the code."""


@dataclass(frozen=True)
class Landmarks:
    """L landmarks as parallel arrays (index i of every field is landmark i).

    Attributes
    ----------
    landmark_class : ndarray of uint8, shape (L,)
        UNKNOWN, PLANE, CORNER, EDGE, or (maps) CORNER_OR_EDGE.
    position : ndarray, shape (L, 2)
        Plane: foot point G of the perpendicular from the transmitter; corner and
        edge: the vertical line's trace, m.
    normal : ndarray, shape (L, 2)
        Planes: unit normal pointing from the wall towards the sensor; zero
        otherwise.
    covariance : ndarray, shape (L, 2, 2)
        Covariance of ``position``, m^2.
    confidence : ndarray of float32, shape (L,)
        0..1, margin of the deciding classification test (0 when undecided).
    segment : ndarray, shape (L, 2, 2)
        Planes: the observed extent's two end points; points: the point twice, m.
    observations : ndarray of uint32, shape (L,)
        Sightings merged into the landmark (1 for a single ping).
    group : ndarray of uint16, shape (L,)
        Receiver group that produced the landmark.
    echo : ndarray of uint32, shape (L,)
        Row of the echo in its ping.
    valid : ndarray of bool, shape (L,)
        False where the landmark could not be computed; ``reason`` says why.
    reason : ndarray of uint8, shape (L,)
        0 (OK) or the reason code of ``sonar_ring.localise``.
    """

    landmark_class: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    covariance: np.ndarray
    confidence: np.ndarray
    segment: np.ndarray
    observations: np.ndarray
    group: np.ndarray
    echo: np.ndarray
    valid: np.ndarray
    reason: np.ndarray

    def __len__(self) -> int:
        return int(self.landmark_class.shape[0])

    @property
    def bearing(self) -> np.ndarray:
        """``atan2(y, x)`` of each position in its frame, shape (L,), rad."""
        return np.arctan2(self.position[:, 1], self.position[:, 0])

    @property
    def range(self) -> np.ndarray:
        """Distance of each position from the frame origin, shape (L,), m."""
        return np.hypot(self.position[:, 0], self.position[:, 1])

    def select(self, index) -> Landmarks:
        """The landmarks picked by a boolean mask (shape (L,)) or an index array."""
        index = np.asarray(index)
        if index.size == 0 and index.dtype != bool:
            index = index.astype(np.intp)  # an empty list is an empty index, not floats
        if index.dtype == bool:
            if index.shape != (len(self),):
                raise IndexError(f"Landmarks.select: a mask of shape {index.shape} for {len(self)} landmarks")
            index = np.flatnonzero(index)  # once, not once per field
        # take: for 2-D and 3-D fields faster than indexing with an array
        return Landmarks(*(getattr(self, name).take(index, axis=0) for name in _FIELDS))

    def with_class(self, landmark_class, confidence) -> Landmarks:
        """A copy with new classes and confidences (shapes (L,))."""
        # Built directly: dataclasses.replace walks the fields in Python.
        return Landmarks(landmark_class=np.asarray(landmark_class, dtype=np.uint8), position=self.position,
                         normal=self.normal, covariance=self.covariance,
                         confidence=np.asarray(confidence, dtype=np.float32), segment=self.segment,
                         observations=self.observations, group=self.group, echo=self.echo, valid=self.valid,
                         reason=self.reason)

    @staticmethod
    def empty() -> Landmarks:
        """No landmarks."""
        return make_landmarks(np.empty(0, np.uint8), np.empty((0, 2)))

    @staticmethod
    def concatenate(parts) -> Landmarks:
        """All landmarks of ``parts`` (a sequence of Landmarks), in order."""
        parts = list(parts)
        if not parts:
            return Landmarks.empty()
        return Landmarks(*(np.concatenate([getattr(p, name) for p in parts]) for name in _FIELDS))


_FIELDS = tuple(f.name for f in fields(Landmarks))
"""The field names of :class:`Landmarks`, in order."""


def make_landmarks(landmark_class, position, *, normal=None, covariance=None, confidence=None, segment=None,
                   observations=None, group=None, echo=None, valid=None, reason=None) -> Landmarks:
    """Build :class:`Landmarks`, filling every field not given with its neutral value.

    Neutral values: zero normal, zero covariance, zero confidence, the point
    itself as its segment, one observation, group and echo 0, valid, reason 0.
    """
    position = np.asarray(position, dtype=float).reshape(-1, 2)
    count = position.shape[0]

    def filled(value, shape, dtype, default):
        if value is None:
            return np.full(shape, default, dtype=dtype)
        return np.broadcast_to(np.asarray(value, dtype=dtype), shape).copy()

    if segment is None:
        segment = np.repeat(position[:, None, :], 2, axis=1)
    return Landmarks(
        landmark_class=filled(landmark_class, (count,), np.uint8, UNKNOWN),
        position=position,
        normal=filled(normal, (count, 2), float, 0.0),
        covariance=filled(covariance, (count, 2, 2), float, 0.0),
        confidence=filled(confidence, (count,), np.float32, 0.0),
        segment=filled(segment, (count, 2, 2), float, 0.0),
        observations=filled(observations, (count,), np.uint32, 1),
        group=filled(group, (count,), np.uint16, 0),
        echo=filled(echo, (count,), np.uint32, 0),
        valid=filled(valid, (count,), bool, True),
        reason=filled(reason, (count,), np.uint8, 0),
    )


def check_landmarks(landmarks, caller: str) -> None:
    """Raise ``ValueError`` (naming ``caller``) unless ``landmarks`` is a :class:`Landmarks` of consistent shapes."""
    if not isinstance(landmarks, Landmarks):
        raise ValueError(f"{caller}: expected sonar_ring.landmarks.Landmarks, got {type(landmarks).__name__}")
    count = len(landmarks)
    expected = {"position": (count, 2), "normal": (count, 2), "covariance": (count, 2, 2),
                "segment": (count, 2, 2)}
    for name, shape in expected.items():
        actual = np.shape(getattr(landmarks, name))
        if actual != shape:
            raise ValueError(f"{caller}: Landmarks.{name} must have shape {shape} for {count} landmarks, "
                             f"got {actual}")
    for name in ("landmark_class", "confidence", "observations", "group", "echo", "valid", "reason"):
        actual = np.shape(getattr(landmarks, name))
        if actual != (count,):
            raise ValueError(f"{caller}: Landmarks.{name} must have shape ({count},), got {actual}")


def ellipse_outlines(position, covariance, sigma: float = 2.0, sides: int = 48) -> np.ndarray:
    """Closed ``sigma``-sigma outlines of 2-D Gaussians, shape (L, sides + 1, 2), m.

    ``position`` (L, 2) m and ``covariance`` (L, 2, 2) m^2, e.g. of
    :class:`Landmarks`; the first point of each outline is repeated at its end.
    """
    values, vectors = np.linalg.eigh(covariance)
    angle = np.linspace(0.0, 2.0 * np.pi, sides + 1)
    circle = np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    axes = vectors * (sigma * np.sqrt(np.clip(values, 0.0, None)))[:, None, :]
    return np.asarray(position)[:, None, :] + np.einsum("lij,sj->lsi", axes, circle)
