"""The map score on hand-built maps: a perfect map scores perfect; a ghost, a duplicate, a wrong class and a
misplaced entry are each counted once; the frame, the heard reflectors and the trajectory error."""

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from sonar_ring.geometry import load_layout
from sonar_ring.landmarks import CORNER, EDGE, PLANE, UNKNOWN, Landmarks, make_landmarks
from sonar_ring.mapping import transform_landmarks
from sonar_ring.realism import IDEAL, World
from sonar_ring.score import heard_reflectors, score_map, trajectory_error
from sonar_ring.simulate import load_scene

ROOM = load_scene("room")


def _perfect(scene=ROOM) -> Landmarks:
    walls = scene.walls
    points = np.concatenate([scene.corner_point, scene.edges])
    classes = np.concatenate([np.full(len(walls), PLANE), np.full(len(scene.corner_point), CORNER),
                              np.full(len(scene.edges), EDGE)])
    segment = np.concatenate([walls, np.repeat(points[:, None, :], 2, axis=1)])
    position = segment.mean(axis=1)
    direction = walls[:, 1] - walls[:, 0]
    normal = np.concatenate([np.stack([-direction[:, 1], direction[:, 0]], -1)
                             / np.linalg.norm(direction, axis=1)[:, None], np.zeros((len(points), 2))])
    return make_landmarks(classes, position, normal=normal, segment=segment)


def _with(base: Landmarks, landmark_class, position, segment=None) -> Landmarks:
    return Landmarks.concatenate([base, make_landmarks([landmark_class], [position], segment=segment)])


def test_a_perfect_map_scores_perfect():
    score = score_map(_perfect(), ROOM)
    assert score.complete
    for name, count in (("plane", 10), ("corner", 4), ("edge", 7)):
        s = score.per_class[name]
        assert (s.heard, s.mapped, s.entries, s.missing) == (count, count, count, 0)
    assert score.ghosts == score.wrong == 0
    assert np.all(score.point_error == 0) and np.all(score.wall_offset < 1e-12)
    assert np.all(score.wall_angle < 1e-12) and np.all(score.wall_overshoot < 1e-12)


def test_an_empty_map_misses_everything():
    score = score_map(Landmarks.empty(), ROOM)
    assert score.total("missing") == ROOM.n_reflectors and score.entries == 0 and not score.complete
    assert score.point_error.size == score.wall_offset.size == score.shape_error.size == 0
    assert np.all(np.isnan(score.similarity))
    assert "nothing mapped" in score.summary()


def test_a_map_right_in_shape_but_scaled_turned_and_shifted():
    """The similarity fit recovers the transform a map was put through, and the shape error is nil.

    A speed of sound 0.35 % off scales every range; the map's anchoring turns and shifts it.
    """
    scale, rotation, shift = 1.0035, math.radians(0.3), np.array([0.01, -0.006])
    c, s = math.cos(rotation), math.sin(rotation)
    perfect = _perfect()

    def moved(points):
        return scale * points @ np.array([[c, s], [-s, c]]) + shift

    entries = make_landmarks(perfect.landmark_class, moved(perfect.position), normal=perfect.normal,
                             segment=moved(perfect.segment.reshape(-1, 2)).reshape(-1, 2, 2))
    score = score_map(entries, ROOM)
    assert score.per_class["corner"].mapped == 4 and score.per_class["edge"].mapped == 7
    assert np.median(score.point_error) > 0.005
    back = np.array([[c, s], [-s, c]]) @ shift / scale  # true = R^T (mapped - shift) / scale
    assert_allclose(score.similarity, [1.0 / scale, -rotation, *(-back)], atol=1e-12)
    assert score.shape_error.shape == score.point_error.shape
    assert np.all(score.shape_error < 1e-12)
    assert "shape 0.0 mm after scaling by 0.9965 and turning by -0.30 deg" in score.summary()
    # Two points fit any similarity: no figure rather than a perfect one.
    two = score_map(entries.select(np.flatnonzero(entries.landmark_class != EDGE)[:12]), ROOM)
    assert two.shape_error.size == 2 and np.all(np.isnan(two.similarity)) and np.all(np.isnan(two.shape_error))


def test_each_fault_is_counted_once():
    perfect = _perfect()
    ghost = score_map(_with(perfect, CORNER, [3.0, 3.5]), ROOM)
    assert (ghost.ghosts, ghost.wrong, ghost.per_class["corner"].ghosts) == (1, 1, 1)
    assert ghost.total("missing") == 0
    duplicate = score_map(_with(perfect, CORNER, ROOM.corner_point[0] + [0.02, 0.01]), ROOM)
    assert (duplicate.per_class["corner"].duplicates, duplicate.wrong, duplicate.ghosts) == (1, 1, 0)
    # An edge named a corner: wrong class, and the edge is missing.
    edges = np.flatnonzero(perfect.landmark_class == EDGE)
    renamed = perfect.with_class(np.where(np.arange(len(perfect)) == edges[0], CORNER, perfect.landmark_class),
                                 perfect.confidence)
    wrong = score_map(renamed, ROOM)
    assert (wrong.per_class["corner"].wrong_class, wrong.per_class["edge"].missing, wrong.wrong) == (1, 1, 1)
    misplaced = score_map(_with(perfect.select(perfect.landmark_class != EDGE), EDGE, ROOM.edges[-1] + [0.07, 0.0]),
                          ROOM)
    assert misplaced.per_class["edge"].misplaced == 1 and misplaced.per_class["edge"].missing == 7
    ghost_wall = score_map(_with(perfect, PLANE, [3.0, 5.0], segment=[[2.0, 5.0], [4.0, 5.0]]), ROOM)
    assert (ghost_wall.per_class["plane"].ghosts, ghost_wall.wrong) == (1, 1)
    undecided = score_map(_with(_with(perfect, UNKNOWN, ROOM.edges[0] + 0.03), UNKNOWN, [3.0, 3.5]), ROOM)
    assert (undecided.undecided, undecided.unknown_ghosts, undecided.ghosts) == (1, 1, 1)


def test_one_wall_right_for_two_reflectors_maps_both_and_duplicates_neither():
    """A wall entry across the doorway lies on both north walls' line and overlaps both."""
    perfect = _perfect()
    north = [k for k, wall in enumerate(ROOM.walls) if np.allclose(wall[:, 1], 4.5)]
    assert len(north) == 2
    across = make_landmarks([PLANE], [[3.0, 4.5]], normal=[[0.0, -1.0]], segment=[[[0.0, 4.5], [6.0, 4.5]]])
    keep = np.setdiff1d(np.arange(len(perfect)), north)
    score = score_map(Landmarks.concatenate([perfect.select(keep), across]), ROOM)
    plane = score.per_class["plane"]
    assert (plane.mapped, plane.duplicates, plane.entries) == (10, 0, 9)
    assert score.total("duplicates") == 0


def test_a_wall_past_its_end_or_tilted():
    perfect = _perfect()
    south = 0
    longer = perfect.segment.copy()
    longer[south, 1, 0] += 0.03  # 3 cm past the east end
    score = score_map(Landmarks(*(longer if name == "segment" else getattr(perfect, name)
                                  for name in Landmarks.__dataclass_fields__)), ROOM)
    assert score.complete
    assert score.wall_overshoot.max() == pytest.approx(0.03)
    tilted = perfect.segment.copy()
    tilted[south, 1, 1] += 6.0 * math.tan(math.radians(3.0))  # 3 deg off, the far end 31 cm away
    off = score_map(Landmarks(*(tilted if name == "segment" else getattr(perfect, name)
                                for name in Landmarks.__dataclass_fields__)), ROOM)
    assert off.per_class["plane"].missing == 1


def test_the_map_frame_and_the_heard_reflectors():
    pose = np.array([0.7, -1.2, 0.4])
    inverse = np.array([*(-np.array([[math.cos(pose[2]), math.sin(pose[2])],
                                     [-math.sin(pose[2]), math.cos(pose[2])]]) @ pose[:2]), -pose[2]])
    in_map = transform_landmarks(_perfect(), inverse)
    assert score_map(in_map, ROOM, map_pose=pose).complete
    assert not score_map(in_map, ROOM).complete
    # The truth of simulated pings names the reflectors the sensor heard.
    layout = load_layout("browne_ring")
    world = World(ROOM, layout, IDEAL)
    positions, normals, classes, reflectors = [], [], [], []
    for k, sensor in enumerate(ROOM.trajectory.poses(layout.ping_rate)[1][::50]):
        ping = world.ping(sensor, k)
        c, s = math.cos(sensor[2]), math.sin(sensor[2])
        positions.append(ping.truth_position @ np.array([[c, s], [-s, c]]) + sensor[:2])
        normals.append(np.nan_to_num(ping.truth_normal) @ np.array([[c, s], [-s, c]]))
        classes.append(ping.truth_class)
        reflectors.append(ping.truth_reflector)
    found = heard_reflectors(ROOM, np.concatenate(classes), np.concatenate(positions), np.concatenate(normals))
    assert found.tolist() == np.unique(np.concatenate(reflectors)).tolist()
    partly = score_map(_perfect(), ROOM, heard=[0, 5])
    assert partly.per_class["plane"].heard == 1 and partly.per_class["corner"].heard == 1


def test_trajectory_error():
    truth = np.column_stack([np.linspace(0, 1, 5), np.zeros(5), np.zeros(5)])
    estimate = truth + [0.0, 0.03, 0.0]
    estimate[-1, 0] += 0.04
    rms, final = trajectory_error(estimate, truth)
    assert_allclose([rms, final], [math.sqrt((4 * 0.03 ** 2 + 0.05 ** 2) / 5), 0.05])
    with pytest.raises(ValueError, match="same number"):
        trajectory_error(estimate[:3], truth)
