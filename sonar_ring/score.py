"""One map score: a map of landmarks against the scene it was built in, and a pose estimate against the truth.

The referee of the demo, the benchmark and the tests.  Given the map (landmarks in a
frame whose pose in the scene's world frame is known) and the scene:

* an entry of a decided class is **right** for a true reflector of its class
  when it lies within :data:`RIGHT_DISTANCE` of it -- a point of the true point,
  a wall with both ends of its seen extent within it of the true wall's line,
  its direction within :data:`RIGHT_ANGLE`, and its extent overlapping the true
  segment; the best right entry of a reflector **maps** it, every other right
  entry is a **duplicate**;
* an entry with no true reflector of its class within :data:`NEAR_DISTANCE`
  (walls: both ends within it of the true segment) is **wrong class** when a
  reflector of another class is that near, else a **ghost**;
* an entry near a reflector of its class but not right is **misplaced**;
* UNKNOWN and CORNER_OR_EDGE entries are **undecided** when near any
  reflector (a corner or edge for the second), else ghosts;
* a heard reflector without a right entry is **missing**.

Positions: the error of a mapped point (m), the offset of a mapped wall's
middle from the true line (m) and its angle (rad), and how far a mapped wall's
extent runs past the true wall's ends (**overshoot**, m: a costmap would put an
obstacle in free space there).

**Shape**: a map can be right in shape and still off as a whole -- scaled (by
the speed of sound the nodes assume: every range scales with it) and turned
and shifted (where ``map`` was anchored: the heading the odometry had drifted
by before the first landmarks held it).  The similarity transform (scale,
rotation, shift) that best carries the mapped corners and edges onto their true
points (least squares, Umeyama 1991) says how much; each point's distance
after it is its shape error.

:func:`trajectory_error` compares a pose estimate (odometry, SLAM) with the truth.

Frames and units: the scene's world frame, m and rad.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sonar_ring.landmarks import CLASS_NAMES, CORNER, CORNER_OR_EDGE, EDGE, PLANE, UNKNOWN, Landmarks
from sonar_ring.mapping import transform_landmarks
from sonar_ring.simulate import Scene

RIGHT_DISTANCE = 0.05
"""m: a map entry this close to a true reflector of its class (walls: both ends from its line) is right."""
RIGHT_ANGLE = np.radians(2.0)
"""rad: a right wall's direction is within this of the true wall's."""
NEAR_DISTANCE = 0.10
"""m: an entry with no reflector of its class this close is a ghost (or of the wrong class)."""
DECIDED = (PLANE, CORNER, EDGE)
"""The classes a map entry can be scored in."""


@dataclass(frozen=True)
class ClassScore:
    """The map's entries of one class against the scene's reflectors of that class.

    Attributes
    ----------
    heard : int
        True reflectors of the class that the sensor heard.
    mapped : int
        Heard reflectors with a right entry of the class.
    duplicates : int
        Right entries beyond the first of a reflector.
    ghosts : int
        Entries of the class with no true reflector at all within
        :data:`NEAR_DISTANCE`.
    wrong_class : int
        Entries of the class near a reflector of another class only.
    misplaced : int
        Entries near a reflector of the class, not right.
    entries : int
        Entries of the class in the map.
    """

    heard: int = 0
    mapped: int = 0
    duplicates: int = 0
    ghosts: int = 0
    wrong_class: int = 0
    misplaced: int = 0
    entries: int = 0

    @property
    def missing(self) -> int:
        """Heard reflectors of the class without a right entry."""
        return self.heard - self.mapped


@dataclass(frozen=True)
class MapScore:
    """What :func:`score_map` found; see the module docstring for the words.

    Attributes
    ----------
    per_class : dict of str to ClassScore
        ``plane``, ``corner`` and ``edge``.
    undecided : int
        UNKNOWN entries near a true reflector, and CORNER_OR_EDGE entries near a true corner or edge.
    unknown_ghosts : int
        UNKNOWN and CORNER_OR_EDGE entries near none.
    point_error : ndarray, shape (P,)
        Distance of each mapped corner and edge from its true point, m.
    wall_offset, wall_angle : ndarray, shape (W,)
        Distance of each mapped wall's middle from the true line (m) and the
        angle between them (rad).
    wall_overshoot : ndarray, shape (W,)
        How far each mapped wall's extent runs past the true wall's ends (the
        larger of its two ends; 0 inside), m.
    similarity : ndarray, shape (4,)
        Scale, rotation (rad) and shift (m, 2) of the similarity transform that best carries the mapped
        corners and edges onto their true points (module docstring); NaN with fewer than 3 of them.
    shape_error : ndarray, shape (P,)
        Distance of each mapped corner and edge from its true point after that transform, m (as ``point_error``).
    """

    per_class: dict
    undecided: int = 0
    unknown_ghosts: int = 0
    point_error: np.ndarray = field(default_factory=lambda: np.empty(0))
    wall_offset: np.ndarray = field(default_factory=lambda: np.empty(0))
    wall_angle: np.ndarray = field(default_factory=lambda: np.empty(0))
    wall_overshoot: np.ndarray = field(default_factory=lambda: np.empty(0))
    similarity: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))
    shape_error: np.ndarray = field(default_factory=lambda: np.empty(0))

    def total(self, name: str) -> int:
        """Sum of one :class:`ClassScore` count (or property) over the classes."""
        return int(sum(getattr(score, name) for score in self.per_class.values()))

    @property
    def entries(self) -> int:
        """Entries of the map, of every class."""
        return self.total("entries") + self.undecided + self.unknown_ghosts

    @property
    def ghosts(self) -> int:
        """Entries of any class, UNKNOWN included, near no true reflector."""
        return self.total("ghosts") + self.unknown_ghosts

    @property
    def wrong(self) -> int:
        """Entries that are a ghost, a duplicate, of the wrong class or misplaced."""
        return self.ghosts + self.total("duplicates") + self.total("wrong_class") + self.total("misplaced")

    @property
    def complete(self) -> bool:
        """Every heard reflector is mapped with its class, and no entry is wrong or undecided."""
        return self.total("missing") == 0 and self.wrong == 0 and self.undecided == 0

    def summary(self) -> str:
        """One line per class and one for the errors, for a terminal."""
        lines = []
        for name, s in self.per_class.items():
            lines.append(f"{name}: {s.mapped} of {s.heard} heard mapped, {s.duplicates} duplicate, {s.ghosts} ghost, "
                         f"{s.wrong_class} wrong class, {s.misplaced} misplaced ({s.entries} entries)")
        lines.append(f"unknown: {self.undecided} undecided, {self.unknown_ghosts} ghost")
        errors = []
        if self.point_error.size:
            errors.append(f"points median {1e3 * np.median(self.point_error):.1f} mm, "
                          f"max {1e3 * self.point_error.max():.1f} mm")
        if np.isfinite(self.similarity).all():
            errors.append(f"shape {1e3 * np.median(self.shape_error):.1f} mm after scaling by "
                          f"{self.similarity[0]:.4f} and turning by {np.degrees(self.similarity[1]):.2f} deg")
        if self.wall_offset.size:
            errors.append(f"walls median {1e3 * np.median(self.wall_offset):.1f} mm, max angle "
                          f"{np.degrees(self.wall_angle.max()):.2f} deg, overshoot max "
                          f"{1e2 * self.wall_overshoot.max():.1f} cm")
        lines.append("error: " + ("; ".join(errors) or "nothing mapped"))
        return "\n".join(lines)


def score_map(landmarks: Landmarks, scene: Scene, heard=None, map_pose=(0.0, 0.0, 0.0)) -> MapScore:
    """Score a map against the scene (module docstring).

    Parameters
    ----------
    landmarks : Landmarks
        The map's entries (a mapper's snapshot) in the map frame.
    scene : Scene
        The truth.
    heard : array_like of int, optional
        Indices of the scene's reflectors the sensor heard
        (:func:`heard_reflectors`); default all of them.
    map_pose : array_like, shape (3,)
        Pose ``(x, y, yaw)`` of the map frame in the scene's world frame, m and rad.

    Returns
    -------
    MapScore
    """
    world = transform_landmarks(landmarks, np.asarray(map_pose, dtype=float))
    heard = np.arange(scene.n_reflectors) if heard is None else np.unique(np.asarray(heard, dtype=int))
    is_heard = np.zeros(scene.n_reflectors, bool)
    is_heard[heard] = True
    truth = _Truth(scene)
    per_class, point_error, mapped_points, true_points, walls = {}, [], [], [], {}
    for code in DECIDED:
        entries = world.select(world.landmark_class == code)
        distance, right, angle = truth.against(entries, code)  # (E, F) each, F = the scene's reflectors of code
        near_any = truth.near_any(entries)
        own = truth.reflectors[code]
        near_own = (distance <= NEAR_DISTANCE).any(axis=1)
        # Each reflector's best right entry maps it; the other right entries are duplicates (one entry right for
        # two reflectors -- a wall across a doorway, say -- maps both and duplicates neither).
        cost = np.where(right, distance, np.inf)
        best_entry = np.argmin(cost, axis=0) if len(entries) else np.zeros(0, int)
        mapped = np.isfinite(cost.min(axis=0)) if len(entries) else np.zeros(len(own), bool)
        right_entries = right.any(axis=1)
        mapping = np.zeros(len(entries), bool)
        if len(entries):
            mapping[best_entry[mapped]] = True
        per_class[CLASS_NAMES[code]] = ClassScore(
            heard=int(np.count_nonzero(is_heard[own])),
            mapped=int(np.count_nonzero(mapped & is_heard[own])),
            duplicates=int(np.count_nonzero(right_entries & ~mapping)),
            ghosts=int(np.count_nonzero(~near_own & ~near_any)),
            wrong_class=int(np.count_nonzero(~near_own & near_any)),
            misplaced=int(np.count_nonzero(near_own & ~right_entries)),
            entries=len(entries),
        )
        matched = np.flatnonzero(mapped)
        if code == PLANE:
            walls = truth.wall_errors(entries.select(best_entry[matched]), own[matched])
        else:
            point_error.append(distance[best_entry[matched], matched])
            mapped_points.append(entries.position[best_entry[matched]])
            true_points.append(truth.points[code][matched])
    unknown = world.select(world.landmark_class == UNKNOWN)
    fixed = world.select(world.landmark_class == CORNER_OR_EDGE)
    near = np.concatenate([truth.near_any(unknown), truth.near_points(fixed)])
    similarity, shape_error = _similarity(np.concatenate(mapped_points), np.concatenate(true_points))
    return MapScore(per_class=per_class, undecided=int(np.count_nonzero(near)),
                    unknown_ghosts=int(np.count_nonzero(~near)),
                    point_error=np.concatenate(point_error) if point_error else np.empty(0),
                    similarity=similarity, shape_error=shape_error, **walls)


def heard_reflectors(scene: Scene, truth_class, truth_position, truth_normal, tolerance: float = 1e-6) -> np.ndarray:
    """Indices of the scene's reflectors that echo rows came from, from the rows' ground truth in the world frame.

    What the simulator's ``truth`` topic carries per echo row -- the class, the
    landmark's true position (a plane's foot point on the wall's line, a
    corner's or an edge's vertex) and a plane's normal -- names the reflector:
    a point within ``tolerance`` (m), a wall whose line holds the foot point and
    whose normal is the row's (of several, the nearest segment).  Rows of no
    reflector (UNKNOWN class) name none.

    Parameters
    ----------
    scene : Scene
    truth_class : array_like of int, shape (N,)
    truth_position, truth_normal : array_like, shape (N, 2)
        World frame, m (normals: unit vectors, used for planes only).
    """
    truth_class = np.asarray(truth_class)
    position = np.asarray(truth_position, dtype=float).reshape(-1, 2)
    normal = np.asarray(truth_normal, dtype=float).reshape(-1, 2)
    found = []
    for code in DECIDED:
        rows = truth_class == code
        own = np.flatnonzero(scene.reflector_class == code)
        if not rows.any() or not own.size:
            continue
        if code == PLANE:
            walls = scene.walls[scene.kind_index[own]]
            direction = walls[:, 1] - walls[:, 0]
            along = np.abs(normal[rows] @ direction.T) / np.linalg.norm(direction, axis=1)  # (N, W): 0 if normal
            on_line = (_distance_to_lines(position[rows], walls) <= tolerance) & (along <= tolerance)
            distance = np.where(on_line, _distance_to_segments(position[rows], walls), np.inf)
        else:
            points = _points_of(scene, code)[scene.kind_index[own]]
            distance = np.linalg.norm(position[rows][:, None, :] - points[None, :, :], axis=-1)
            distance = np.where(distance <= tolerance, distance, np.inf)
        best = np.argmin(distance, axis=1)
        found.append(own[best[np.isfinite(distance[np.arange(len(best)), best])]])
    return np.unique(np.concatenate(found)) if found else np.empty(0, int)


def trajectory_error(estimate, truth) -> tuple[float, float]:
    """RMS and final position error (m) of poses ``estimate`` (P, 3 or 2) against ``truth`` at the same times."""
    estimate = np.asarray(estimate, dtype=float)
    truth = np.asarray(truth, dtype=float)
    if estimate.shape[0] != truth.shape[0] or estimate.shape[0] == 0:
        raise ValueError(f"trajectory_error: need the same number (> 0) of poses, got {estimate.shape[0]} "
                         f"and {truth.shape[0]}")
    error = np.hypot(estimate[:, 0] - truth[:, 0], estimate[:, 1] - truth[:, 1])
    return float(np.sqrt(np.mean(error ** 2))), float(error[-1])


# --------------------------------------------------------------------------- helpers


class _Truth:
    """The scene's reflectors by class, for distances from map entries."""

    def __init__(self, scene: Scene):
        self.scene = scene
        self.reflectors = {code: np.flatnonzero(scene.reflector_class == code) for code in DECIDED}
        self.walls = scene.walls[scene.kind_index[self.reflectors[PLANE]]]
        self.points = {code: _points_of(scene, code)[scene.kind_index[self.reflectors[code]]]
                       for code in (CORNER, EDGE)}

    def against(self, entries: Landmarks, code: int):
        """Distance (E, F) of entries of class ``code`` from its F reflectors, whether each pair is right, angles."""
        count = len(entries)
        if code == PLANE:
            ends = entries.segment
            line = np.maximum(*(_distance_to_lines(ends[:, end], self.walls) for end in (0, 1)))
            segment = np.maximum(*(_distance_to_segments(ends[:, end], self.walls) for end in (0, 1)))
            angle = _angle_between(ends[:, 1] - ends[:, 0], self.walls[:, 1] - self.walls[:, 0])
            right = (line <= RIGHT_DISTANCE) & (angle <= RIGHT_ANGLE) & _overlaps(ends, self.walls)
            return segment, right, angle
        points = self.points[code]
        offset = entries.position[:, None, :] - points[None, :, :]
        distance = np.linalg.norm(offset, axis=-1).reshape(count, len(points))
        return distance, distance <= RIGHT_DISTANCE, None

    def near_any(self, entries: Landmarks) -> np.ndarray:
        """Whether each entry lies within :data:`NEAR_DISTANCE` of any reflector (walls: both its ends), (E,)."""
        near = np.zeros(len(entries), bool)
        if not len(entries):
            return near
        wall_entries = entries.landmark_class == PLANE
        if len(self.walls):
            ends = entries.segment
            distance = np.maximum(*(_distance_to_segments(ends[:, end], self.walls) for end in (0, 1)))
            near |= (distance <= NEAR_DISTANCE).any(axis=1)
        points = np.concatenate([self.points[CORNER], self.points[EDGE]])
        if len(points):
            distance = np.linalg.norm(entries.position[:, None, :] - points[None, :, :], axis=-1)
            near |= ~wall_entries & (distance <= NEAR_DISTANCE).any(axis=1)
        return near

    def near_points(self, entries: Landmarks) -> np.ndarray:
        """Whether each entry lies within :data:`NEAR_DISTANCE` of a true corner or edge, (E,)."""
        points = np.concatenate([self.points[CORNER], self.points[EDGE]])
        if not len(entries) or not len(points):
            return np.zeros(len(entries), bool)
        distance = np.linalg.norm(entries.position[:, None, :] - points[None, :, :], axis=-1)
        return (distance <= NEAR_DISTANCE).any(axis=1)

    def wall_errors(self, entries: Landmarks, reflectors) -> dict:
        """Offset, angle and overshoot of the walls ``entries`` against their reflectors ``reflectors`` (W,)."""
        walls = self.scene.walls[self.scene.kind_index[reflectors]]
        ends = entries.segment
        middle = ends.mean(axis=1)
        direction = walls[:, 1] - walls[:, 0]
        length = np.linalg.norm(direction, axis=-1)
        unit = direction / length[:, None]
        normal = np.stack([-unit[:, 1], unit[:, 0]], axis=-1)
        along = np.einsum("wej,wj->we", ends - walls[:, None, 0], unit)
        overshoot = np.maximum(np.maximum(-along, along - length[:, None]), 0.0).max(axis=1)
        segment = ends[:, 1] - ends[:, 0]
        angle = np.abs(np.arctan2(segment[:, 0] * unit[:, 1] - segment[:, 1] * unit[:, 0],
                                  np.einsum("wj,wj->w", segment, unit)))
        return dict(wall_offset=np.abs(np.einsum("wj,wj->w", middle - walls[:, 0], normal)),
                    wall_angle=np.minimum(angle, np.pi - angle), wall_overshoot=overshoot)


def _similarity(mapped, true) -> tuple[np.ndarray, np.ndarray]:
    """The similarity transform carrying ``mapped`` (P, 2) onto ``true`` (P, 2) in least squares, and the residuals.

    ``true ~ scale R(rotation) mapped + shift`` (Umeyama's closed form): ``(scale, rotation, shift_x, shift_y)``
    (4,) and each point's distance after it (P,), m.  Fewer than 3 points fit any transform exactly: NaN.
    """
    if len(mapped) < 3:
        return np.full(4, np.nan), np.full(len(mapped), np.nan)
    mapped_mean, true_mean = mapped.mean(axis=0), true.mean(axis=0)
    a, b = mapped - mapped_mean, true - true_mean
    # In 2-D the best rotation's angle and scale follow from two sums (Umeyama's SVD reduces to them).
    along, across = np.sum(a * b), np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    rotation = np.arctan2(across, along)
    scale = np.hypot(along, across) / np.sum(a * a)
    c, s = np.cos(rotation), np.sin(rotation)
    turned = scale * (mapped @ np.array([[c, s], [-s, c]]))
    shift = true_mean - turned.mean(axis=0)
    return np.array([scale, rotation, *shift]), np.linalg.norm(turned + shift - true, axis=1)


def _points_of(scene: Scene, code: int) -> np.ndarray:
    return scene.corner_point if code == CORNER else scene.edges


def _distance_to_lines(points, segments) -> np.ndarray:
    """Distance of points (P, 2) from the infinite lines through segments (S, 2, 2), (P, S), m."""
    start, along = segments[:, 0], segments[:, 1] - segments[:, 0]
    unit = along / np.linalg.norm(along, axis=-1, keepdims=True)
    offset = points[:, None, :] - start[None, :, :]
    return np.abs(offset[..., 0] * unit[None, :, 1] - offset[..., 1] * unit[None, :, 0])


def _distance_to_segments(points, segments) -> np.ndarray:
    """Distance of points (P, 2) from segments (S, 2, 2), (P, S), m."""
    start, along = segments[:, 0], segments[:, 1] - segments[:, 0]
    offset = points[:, None, :] - start[None, :, :]
    t = np.clip(np.sum(offset * along, axis=-1) / np.maximum(np.sum(along * along, axis=-1), 1e-18), 0.0, 1.0)
    return np.linalg.norm(offset - t[..., None] * along, axis=-1)


def _angle_between(directions, segments) -> np.ndarray:
    """Angle between lines along ``directions`` (E, 2) and along segments' directions (S, 2), in [0, pi/2], (E, S)."""
    a = np.arctan2(directions[:, 1], directions[:, 0])[:, None]
    b = np.arctan2(segments[:, 1], segments[:, 0])[None, :]
    return np.abs(np.remainder(a - b + np.pi / 2, np.pi) - np.pi / 2)


def _overlaps(ends, walls) -> np.ndarray:
    """Whether each entry's extent (E, 2, 2) overlaps each wall's segment (S, 2, 2) along the wall, (E, S)."""
    direction = walls[:, 1] - walls[:, 0]
    length = np.linalg.norm(direction, axis=-1)
    unit = direction / length[:, None]
    along = np.einsum("esij,sj->esi", ends[:, None, :, :] - walls[None, :, None, 0, :], unit)
    low, high = along.min(axis=-1), along.max(axis=-1)
    return (high >= 0.0) & (low <= length[None, :])
