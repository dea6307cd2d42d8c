"""Tests of the mapper core: frames, fusion, wall segments, PLANE vs CORNER over motion, limits."""

import warnings
from dataclasses import fields, replace

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from sonar_ring.landmarks import CORNER, CORNER_OR_EDGE, EDGE, PLANE, UNKNOWN, Landmarks, make_landmarks
from sonar_ring.mapping import LandmarkMap, MapCounts, transform_landmarks
from sonar_ring.poses import turned_covariances

# Synthetic scene: the robot drives along +x on y = 0 past a wall on y = WALL_Y (seen from
# below, so its normal towards the sensor is -y) and a corner at CORNER_POINT.
WALL_Y = 1.0
CORNER_POINT = np.array([1.5, -1.2])
SIGMA_RANGE = 0.005  # m
SIGMA_BEARING = np.radians(1.0)  # rad
REFLECTION_HALF_SPREAD = 0.02  # m, the two receivers' reflection points either side of G
STEP = 0.03  # m of travel per ping
CHI2_2DOF_3SIGMA = 11.829  # 99.73 % point of chi-square, 2 dof: the 2-D counterpart of 3 sigma


def sighting_covariance(sensor, point):
    """Range/bearing covariance of a fix at ``point`` seen from ``sensor``, shape (2, 2)."""
    offset = point - sensor
    distance = np.hypot(*offset)
    radial = offset / distance
    across = np.array([-radial[1], radial[0]])
    return (SIGMA_RANGE ** 2 * np.outer(radial, radial)
            + (distance * SIGMA_BEARING) ** 2 * np.outer(across, across))


def sightings(rng, sensor, points, classes, confidence=0.9):
    """Noisy landmarks in odom of the true landmark points ``points`` (K, 2) seen from ``sensor``.

    Positions are drawn from their covariance; planes get the normal of the virtual-image
    model (along sensor - G) and the two reflection points either side of G as segment.
    """
    points = np.asarray(points, dtype=float)
    classes = np.asarray(classes)
    covariance = np.array([sighting_covariance(sensor, point) for point in points])
    noisy = points + np.einsum("kij,kj->ki", np.linalg.cholesky(covariance), rng.standard_normal(points.shape))
    towards = sensor - noisy
    normal = towards / np.hypot(towards[:, 0], towards[:, 1])[:, None]
    tangent = np.stack([-normal[:, 1], normal[:, 0]], axis=-1)
    spread = np.where(classes == PLANE, REFLECTION_HALF_SPREAD, 0.0)[:, None] * tangent
    return make_landmarks(classes, noisy, normal=np.where((classes == PLANE)[:, None], normal, 0.0),
                          covariance=covariance, segment=np.stack([noisy - spread, noisy + spread], axis=1),
                          confidence=np.where(classes == UNKNOWN, 0.0, confidence))


def drive(landmark_map, rng, xs, wall_class=PLANE, corner_class=CORNER):
    """Drive along y = 0 through ``xs``, seeing the wall's foot point and the corner each ping."""
    for x in xs:
        landmarks = sightings(rng, np.array([x, 0.0]), [[x, WALL_Y], CORNER_POINT], [wall_class, corner_class])
        landmark_map.update(landmarks, [x, 0.0, 0.0])


def by_class(snapshot, code):
    return snapshot.select(snapshot.landmark_class == code)


def main_entry(snapshot, code):
    """The entry of class ``code`` with the most sightings, as Landmarks of length 1."""
    mine = np.flatnonzero(snapshot.landmark_class == code)
    return snapshot.select(mine[[np.argmax(snapshot.observations[mine])]])


def wall_offset_error(wall):
    """Signed error of a wall's line offset (m) and its standard deviation (m) from the snapshot."""
    normal = wall.normal[0]
    return (wall.position[0, 1] - WALL_Y) * normal[1], np.sqrt(normal @ wall.covariance[0] @ normal)


def mahalanobis2(error, covariance):
    return float(error @ np.linalg.solve(covariance, error))


# --------------------------------------------------------------------------- frames

def test_transform_landmarks_matches_hand_computation():
    landmarks = make_landmarks([PLANE, CORNER], [[3.0, 0.5], [1.0, 0.0]], normal=[[1.0, 0.0], [0.0, 0.0]],
                               covariance=[[[4e-4, 1e-4], [1e-4, 1e-4]], np.diag([4e-4, 1e-4])],
                               segment=[[[3.0, 0.0], [3.0, 1.0]], [[1.0, 0.0], [1.0, 0.0]]],
                               confidence=[0.5, 0.25], group=[7, 8], echo=[3, 4])
    quarter = transform_landmarks(landmarks, [1.0, 2.0, np.pi / 2])
    # Rotating by +90 degrees maps (x, y) to (-y, x); then translate by (1, 2).
    assert_allclose(quarter.position, [[0.5, 5.0], [1.0, 3.0]], atol=1e-12)
    assert_allclose(quarter.normal, [[0.0, 1.0], [0.0, 0.0]], atol=1e-12)
    assert_allclose(quarter.segment[0], [[1.0, 5.0], [0.0, 5.0]], atol=1e-12)
    # R C R^T for 90 degrees swaps the variances and negates the covariance term.
    assert_allclose(quarter.covariance[0], [[1e-4, -1e-4], [-1e-4, 4e-4]], atol=1e-18)
    # 30 degrees, diag(a, b): [[a c^2 + b s^2, (a - b) c s], [(a - b) c s, a s^2 + b c^2]].
    tilted = transform_landmarks(landmarks, [0.0, 0.0, np.radians(30.0)])
    c, s = np.sqrt(3.0) / 2.0, 0.5
    assert_allclose(tilted.position[1], [c, s], atol=1e-12)
    assert_allclose(tilted.covariance[1], [[4e-4 * c * c + 1e-4 * s * s, 3e-4 * c * s],
                                           [3e-4 * c * s, 4e-4 * s * s + 1e-4 * c * c]], rtol=1e-12)
    for name in ("landmark_class", "confidence", "observations", "group", "echo", "valid", "reason"):
        assert_array_equal(getattr(tilted, name), getattr(landmarks, name))


def test_transform_landmarks_round_trip_and_empty():
    rng = np.random.default_rng(4)
    covariance = np.array([sighting_covariance(np.zeros(2), p) for p in [[2.0, 1.0], [0.5, -3.0]]])
    landmarks = make_landmarks([UNKNOWN, EDGE], [[2.0, 1.0], [0.5, -3.0]], covariance=covariance)
    pose = np.array([rng.normal(), rng.normal(), 2.3])
    there = transform_landmarks(landmarks, pose)
    # The inverse pose: rotate by -yaw, translate by -R^T t.
    back = np.array([[np.cos(pose[2]), np.sin(pose[2])], [-np.sin(pose[2]), np.cos(pose[2])]]) @ -pose[:2]
    again = transform_landmarks(there, [back[0], back[1], -pose[2]])
    assert_allclose(again.position, landmarks.position, atol=1e-12)
    assert_allclose(again.covariance, landmarks.covariance, atol=1e-15)
    assert len(transform_landmarks(Landmarks.empty(), pose)) == 0


def test_turned_covariances_are_r_c_rt_bit_for_bit():
    rng = np.random.default_rng(5)
    factor = rng.normal(size=(200, 2, 2))
    covariance = factor @ factor.transpose(0, 2, 1)
    for yaw in rng.uniform(-np.pi, np.pi, 20):
        rotation = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
        assert_array_equal(turned_covariances(covariance, rotation), rotation @ covariance @ rotation.T)
    assert turned_covariances(np.empty((0, 2, 2)), np.eye(2)).shape == (0, 2, 2)


# --------------------------------------------------------------------------- fusion and convergence

def test_corner_fusion_is_information_weighted_and_shrinks_like_one_over_n():
    rng = np.random.default_rng(1)
    # No floors and no gating, so the map must equal the batch information-form estimate.
    landmark_map = LandmarkMap(sighting_sigma=0.0, map_sigma=0.0, gate_chi2=1e6, new_entry_gate_chi2=1e6)
    positions, informations = [], []
    for n, x in enumerate(np.arange(0.0, 1.2, STEP), start=1):
        sensor = np.array([x, 0.0])
        landmarks = sightings(rng, sensor, [CORNER_POINT], [CORNER])
        landmark_map.update(landmarks, [x, 0.0, 0.0])
        positions.append(landmarks.position[0])
        informations.append(np.linalg.inv(landmarks.covariance[0]))
        fused = landmark_map.snapshot()
        total = np.sum(informations, axis=0)
        expected = np.linalg.solve(total, np.einsum("kij,kj->i", np.array(informations), np.array(positions)))
        assert_allclose(fused.covariance[0], np.linalg.inv(total), rtol=1e-9)
        assert_allclose(fused.position[0], expected, rtol=0, atol=1e-12)
        assert fused.observations[0] == n
    assert landmark_map.counts.fused == 39 and len(landmark_map) == 1
    # From one place every sighting has the same covariance C: the fused one is C / n.
    standing = LandmarkMap(sighting_sigma=0.0, map_sigma=0.0, gate_chi2=1e6, new_entry_gate_chi2=1e6)
    single = sighting_covariance(np.zeros(2), CORNER_POINT)
    for n in range(1, 31):
        standing.update(sightings(rng, np.zeros(2), [CORNER_POINT], [CORNER]), [0, 0, 0])
        assert_allclose(standing.snapshot().covariance[0], single / n, rtol=1e-9)


def test_map_is_consistent_positions_within_three_sigma():
    """Acceptance: over independent runs, fused landmarks lie within 3 sigma of the truth in >= 99 %.

    With the default floors (the product) the rate holds; without them the mean squared
    normalised errors stay near their expectations (2 for a point, 1 for a wall offset;
    the second-order bias of a range-bearing fix, ~ r sigma_bearing^2, adds a little),
    so the fused covariances are neither grossly optimistic nor merely padded.
    """
    runs = 120
    results = {"floors": ([], []), "no floors": ([], [])}
    singletons = 0
    for seed in range(runs):
        for name, options in (("floors", {}), ("no floors", {"sighting_sigma": 0.0, "map_sigma": 0.0})):
            rng = np.random.default_rng(1000 + seed)
            landmark_map = LandmarkMap(**options)
            drive(landmark_map, rng, np.arange(0.0, 0.9, STEP))
            snapshot = landmark_map.snapshot()
            corner, wall = main_entry(snapshot, CORNER), main_entry(snapshot, PLANE)
            # A sighting beyond the 99.99 % new-entry gate (a Gaussian tail) starts a new entry.
            assert np.all(np.sort(snapshot.observations)[:-2] == 1)
            singletons += len(snapshot) - 2
            point_d2, wall_z2 = results[name]
            point_d2.append(mahalanobis2(corner.position[0] - CORNER_POINT, corner.covariance[0]))
            error, sigma = wall_offset_error(wall)
            wall_z2.append((error / sigma) ** 2)
            assert abs(np.arctan2(wall.normal[0, 0], -wall.normal[0, 1])) < np.radians(0.5)
    assert singletons <= 2
    point_d2, wall_z2 = (np.array(values) for values in results["floors"])
    assert np.mean(point_d2 <= CHI2_2DOF_3SIGMA) >= 0.99
    assert np.mean(wall_z2 <= 9.0) >= 0.99
    point_d2, wall_z2 = (np.array(values) for values in results["no floors"])
    assert 1.6 <= point_d2.mean() <= 2.6
    assert 0.8 <= wall_z2.mean() <= 1.6


def test_wall_becomes_one_segment_with_right_normal_offset_and_extent():
    rng = np.random.default_rng(2)
    landmark_map = LandmarkMap()
    xs = np.arange(0.0, 3.0, STEP)
    drive(landmark_map, rng, xs)
    walls = by_class(landmark_map.snapshot(), PLANE)
    assert len(walls) == 1
    assert_allclose(walls.normal[0], [0.0, -1.0], atol=np.sin(np.radians(0.2)))
    error, sigma = wall_offset_error(walls)
    assert abs(error) <= 3.0 * sigma
    # The seen extent: foot points from x = 0 to the last x, plus the reflection-point spread.
    ends = np.sort(walls.segment[0, :, 0])
    assert_allclose(ends, [xs[0] - REFLECTION_HALF_SPREAD, xs[-1] + REFLECTION_HALF_SPREAD], atol=0.05)
    assert_allclose(walls.segment[0, :, 1], WALL_Y, atol=0.01)
    # Every sighting is in an entry or counted ambiguous, and the wall holds nearly all of its own.
    assert landmark_map.snapshot().observations.sum() + landmark_map.counts.ambiguous == 2 * xs.size
    assert walls.observations[0] >= 0.97 * xs.size
    assert_allclose(walls.confidence[0], 0.9, rtol=1e-6)


def test_plane_normal_sign_convention_does_not_matter():
    maps = []
    for flip in (1.0, -1.0):
        rng = np.random.default_rng(3)
        landmark_map = LandmarkMap()
        for x in np.arange(0.0, 1.5, STEP):
            landmarks = sightings(rng, np.array([x, 0.0]), [[x, WALL_Y]], [PLANE])
            landmark_map.update(replace(landmarks, normal=flip * landmarks.normal), [x, 0, 0])
        maps.append(landmark_map.snapshot())
    assert_array_equal(maps[0].normal, maps[1].normal)
    assert_array_equal(maps[0].segment, maps[1].segment)


# --------------------------------------------------------------------------- PLANE vs CORNER over motion

def test_unknown_sightings_resolve_into_a_wall_and_a_corner_over_motion():
    rng = np.random.default_rng(5)
    landmark_map = LandmarkMap()
    xs = np.arange(0.0, 3.0, STEP)
    travelled_when_decided = {}
    for x in xs:
        drive(landmark_map, rng, [x], wall_class=UNKNOWN, corner_class=UNKNOWN)
        counts = landmark_map.counts
        for name in ("resolved_plane", "resolved_fixed"):
            if getattr(counts, name) and name not in travelled_when_decided:
                travelled_when_decided[name] = x - xs[0]
    # Nothing is decided before the sensor has moved min_baseline across the line of sight,
    # and both are decided soon after.
    assert set(travelled_when_decided) == {"resolved_plane", "resolved_fixed"}
    for travelled in travelled_when_decided.values():
        assert landmark_map.min_baseline - 1e-9 <= travelled <= 0.5
    snapshot = landmark_map.snapshot()
    # Motion tells a fixed point from a plane, not a corner from an edge (that is the curvature's).
    assert_array_equal(np.sort(snapshot.landmark_class), [PLANE, CORNER_OR_EDGE])
    wall, corner = by_class(snapshot, PLANE), by_class(snapshot, CORNER_OR_EDGE)
    assert wall.confidence[0] >= 0.99 and corner.confidence[0] >= 0.99
    error, sigma = wall_offset_error(wall)
    assert abs(error) <= 3.0 * sigma
    # The wall covers every foot point seen, from the first ping on (UNKNOWN sightings have no spread).
    assert_allclose(np.sort(wall.segment[0, :, 0]), [xs[0], xs[-1]], atol=0.05)
    assert mahalanobis2(corner.position[0] - CORNER_POINT, corner.covariance[0]) <= CHI2_2DOF_3SIGMA
    assert corner.observations[0] + wall.observations[0] + landmark_map.counts.ambiguous == 2 * xs.size
    # Without curvature evidence (no point models: a triad's sightings) a fixed point is as decided as it gets.
    uids = landmark_map.entries().uid
    assert landmark_map.decided(uids).all() and not landmark_map.decided([uids.max() + 1]).any()


@pytest.mark.parametrize("viewpoint, yaw", [([0.4, 0.0], 0.0), ([0.0, -0.4], np.pi / 2)])
def test_a_wall_is_seen_from_the_transmitter_that_heard_it(viewpoint, yaw):
    """A transmitter 0.4 m ahead of the sensor's origin (a module at the robot's side): the foot points of the
    wall's UNKNOWN sightings lie 0.4 m ahead of the sensor, whatever way the sensor frame is turned."""
    xs = np.arange(0.0, 3.0, STEP)
    maps = {}
    for name, viewpoints in (("transmitter", [viewpoint]), ("origin", None)):
        rng = np.random.default_rng(5)
        maps[name] = LandmarkMap(viewpoints=viewpoints)
        for x in xs:
            transmitter = np.array([x + 0.4, 0.0])
            maps[name].update(sightings(rng, transmitter, [[transmitter[0], WALL_Y]], [UNKNOWN]), [x, 0.0, yaw])
    wall = maps["transmitter"].snapshot()
    assert wall.landmark_class.tolist() == [PLANE]
    assert_allclose(wall.normal[0], [0.0, -1.0], atol=np.sin(np.radians(0.5)))
    error, sigma = wall_offset_error(wall)
    assert abs(error) <= 3.0 * sigma
    assert_allclose(np.sort(wall.segment[0, :, 0]), [xs[0] + 0.4, xs[-1] + 0.4], atol=0.05)
    # Taken from the sensor's origin, every line of sight is turned 22 degrees: the wall falls apart in points.
    assert maps["origin"].counts.resolved_plane == 0
    assert PLANE not in maps["origin"].snapshot().landmark_class


def test_viewpoints_turn_and_move_with_the_sensor_and_an_unknown_group_is_seen_from_the_origin():
    landmark_map = LandmarkMap(viewpoints=[[0.1, 0.2], [0.0, -0.3]])
    assert_allclose(landmark_map.viewpoints_at([0, 1, 7], [1.0, 2.0, np.pi / 2]),
                    [[0.8, 2.1], [1.3, 2.0], [1.0, 2.0]], atol=1e-15)
    assert_array_equal(LandmarkMap().viewpoints_at([0, 3], [1.0, 2.0, 0.5]), [[1.0, 2.0], [1.0, 2.0]])


def test_a_wall_whose_first_sightings_stray_along_it_is_made_once_its_line_wins():
    # The first 40 pings (8 cm of travel, less than min_baseline) see the wall's foot point 4 cm to either side
    # along the wall (its echoes by way of reflectors not yet mapped), then the sensor drives on and sees it
    # right.  The line fits far better than a point but not within the test of consistency (chi-square 330 for
    # 240 dof); it fits within PLANE_SPREAD times its dof, so the wall is made.
    rng = np.random.default_rng(8)
    landmark_map = LandmarkMap()
    xs = np.concatenate([np.linspace(0.0, 0.08, 40), np.arange(0.08 + STEP, 3.0, STEP)])
    for k, x in enumerate(xs):
        along = (0.04 if k % 2 else -0.04) if k < 40 else 0.0
        landmark_map.update(sightings(rng, np.array([x, 0.0]), [[x + along, WALL_Y]], [UNKNOWN]), [x, 0.0, 0.0])
    snapshot = landmark_map.snapshot()
    main = snapshot.select([np.argmax(snapshot.observations)])
    assert main.landmark_class[0] == PLANE and main.observations[0] >= 0.85 * xs.size
    assert_allclose(main.normal[0], [0.0, -1.0], atol=np.sin(np.radians(0.5)))
    assert abs(wall_offset_error(main)[0]) <= 0.005


def test_classes_of_looks_uids_up_as_the_entries_list_them():
    rng = np.random.default_rng(5)
    landmark_map = LandmarkMap()
    for x in np.arange(0.0, 1.0, STEP):
        drive(landmark_map, rng, [x])
    entries = landmark_map.entries()
    assert entries.is_wall.any() and not entries.is_wall.all()
    missing = entries.uid.max() + 1
    uids = np.concatenate([entries.uid[::-1], [missing], entries.uid[:1]])
    is_wall, entry_class = landmark_map.classes_of(uids)
    assert_array_equal(is_wall, np.concatenate([entries.is_wall[::-1], [False], entries.is_wall[:1]]))
    assert_array_equal(entry_class, np.concatenate([entries.landmark_class[::-1], [UNKNOWN],
                                                    entries.landmark_class[:1]]))
    assert entry_class.dtype == np.uint8 and landmark_map.classes_of(np.empty(0, np.int64))[0].shape == (0,)


@pytest.mark.parametrize("motion", ["standing", "towards the wall"])
def test_unknown_stays_unknown_without_motion_across_the_line_of_sight(motion):
    rng = np.random.default_rng(6)
    landmark_map = LandmarkMap()
    for k in range(60):
        # Driving straight at a wall keeps its foot point in place, just like a corner's.
        sensor = np.array([0.5, 0.0 if motion == "standing" else 0.005 * k])
        landmarks = sightings(rng, sensor, [[sensor[0], WALL_Y]], [UNKNOWN])
        landmark_map.update(landmarks, [sensor[0], sensor[1], np.pi / 2])
    snapshot = landmark_map.snapshot()
    assert_array_equal(snapshot.landmark_class, [UNKNOWN])
    assert snapshot.observations[0] + landmark_map.counts.ambiguous == 60
    assert landmark_map.counts.resolved_plane == landmark_map.counts.resolved_fixed == 0
    assert_allclose(snapshot.confidence, 0.0)


def test_sightings_of_one_reflector_in_one_ping_start_one_entry():
    rng = np.random.default_rng(13)
    landmark_map = LandmarkMap()
    sensor = np.zeros(2)
    # Overlapping receiver groups: three sightings of the corner (one UNKNOWN) and two of the wall.
    landmark_map.update(sightings(rng, sensor, [CORNER_POINT] * 3 + [[0.0, WALL_Y]] * 2,
                                  [UNKNOWN, CORNER, CORNER, PLANE, UNKNOWN]), [0, 0, 0])
    snapshot = landmark_map.snapshot()
    assert_array_equal(snapshot.landmark_class, [PLANE, CORNER])
    assert_array_equal(snapshot.observations, [2, 3])
    counts = landmark_map.counts
    assert (counts.created, counts.fused) == (2, 3)


GHOST_POINT = np.array([2.5, 2.0])  # behind the wall: where a double bounce would put a reflector


def test_an_explained_sighting_never_starts_an_entry():
    rng = np.random.default_rng(21)
    landmark_map = LandmarkMap()
    for x in np.arange(0.0, 1.5, STEP):
        landmarks = sightings(rng, np.array([x, 0.0]), [CORNER_POINT, GHOST_POINT], [CORNER, UNKNOWN])
        placed = landmark_map.update(landmarks, [x, 0.0, 0.0], explained=[False, True])
        assert placed.uid[1] == -1
    snapshot = landmark_map.snapshot()
    assert_array_equal(snapshot.landmark_class, [CORNER])
    counts = landmark_map.counts
    assert counts.explained == len(np.arange(0.0, 1.5, STEP)) and counts.explained_away == 0
    assert counts.sightings == (counts.invalid + counts.not_finite + counts.degenerate + counts.explained
                                + counts.ambiguous + counts.fused + counts.created + counts.dropped)


def test_a_ghost_mapped_before_the_map_could_explain_it_is_explained_away():
    rng = np.random.default_rng(22)
    landmark_map = LandmarkMap()
    xs = np.arange(0.0, 3.0, STEP)
    for k, x in enumerate(xs):
        landmarks = sightings(rng, np.array([x, 0.0]), [CORNER_POINT, GHOST_POINT], [CORNER, UNKNOWN])
        # the first half of the drive the map cannot explain the ghost's echo; then it can
        ghost_explained = k >= xs.size // 2
        placed = landmark_map.update(landmarks, [x, 0.0, 0.0], explained=[False, ghost_explained])
        if k == xs.size // 2 - 1:
            ghost = placed.uid[1]
            assert landmark_map.persistent([ghost])[0]
        # gone once explained in min_support_pings pings and a third as many as it was fused in (50)
        needed = max(landmark_map.min_support_pings, -(-(xs.size // 2) // 3))
        if k == xs.size // 2 + needed - 2:
            assert landmark_map.persistent([ghost])[0]
        if k == xs.size // 2 + needed - 1:
            assert ghost in placed.removed.tolist()
    assert landmark_map.counts.explained_away == 1
    snapshot = landmark_map.snapshot()
    assert_array_equal(snapshot.landmark_class, [CORNER])


def test_a_reflector_whose_echo_is_sometimes_explained_stays():
    rng = np.random.default_rng(23)
    landmark_map = LandmarkMap()
    for k, x in enumerate(np.arange(0.0, 3.0, STEP)):
        landmarks = sightings(rng, np.array([x, 0.0]), [CORNER_POINT], [CORNER])
        landmark_map.update(landmarks, [x, 0.0, 0.0], explained=[k % 3 == 2])  # one ping in three
    assert_array_equal(landmark_map.snapshot().landmark_class, [CORNER])
    assert landmark_map.counts.explained_away == 0


def test_only_an_echo_that_persists_over_pings_and_poses_is_persistent():
    rng = np.random.default_rng(24)
    landmark_map = LandmarkMap(min_support_pings=5, min_support_travel=0.05)
    sensor = np.zeros(2)
    # once: never persistent; standing still, however often: not either
    landmark_map.update(sightings(rng, sensor, [GHOST_POINT], [UNKNOWN]), [0.0, 0.0, 0.0])
    for _ in range(20):
        landmark_map.update(sightings(rng, sensor, [CORNER_POINT], [CORNER]), [0.0, 0.0, 0.0])
    uids = landmark_map.entries().uid
    assert not landmark_map.persistent(uids).any()
    assert len(landmark_map.snapshot(persistent=True)) == 0
    # a reflector seen in five pings while the robot drives 12 cm (a rare one: 0.4 s at 0.3 m/s): persistent
    for x in (0.03, 0.06, 0.09, 0.12):
        landmark_map.update(sightings(rng, np.array([x, 0.0]), [CORNER_POINT], [CORNER]), [x, 0.0, 0.0])
    persistent = landmark_map.snapshot(persistent=True)
    assert_array_equal(persistent.landmark_class, [CORNER])
    assert_allclose(persistent.position[0], CORNER_POINT, atol=0.02)
    assert len(landmark_map.snapshot()) == 2  # the one-off echo is still held, not published


def test_classified_sightings_name_unknown_points():
    rng = np.random.default_rng(7)
    landmark_map = LandmarkMap()
    sensor = np.array([0.0, 0.0])
    for _ in range(5):
        landmark_map.update(sightings(rng, sensor, [CORNER_POINT, [0.0, WALL_Y]], [UNKNOWN, UNKNOWN]), [0, 0, 0])
    assert_array_equal(landmark_map.snapshot().landmark_class, [UNKNOWN, UNKNOWN])
    assert not landmark_map.decided(landmark_map.entries().uid).any()
    landmark_map.update(sightings(rng, sensor, [CORNER_POINT, [0.0, WALL_Y]], [EDGE, PLANE], confidence=0.7),
                        [0, 0, 0])
    snapshot = landmark_map.snapshot()
    assert_array_equal(snapshot.landmark_class, [PLANE, EDGE])  # walls first
    assert_array_equal(snapshot.observations, [6, 6])
    assert_allclose(snapshot.confidence, [0.7, 0.7], rtol=1e-6)
    assert_allclose(snapshot.normal[0], [0.0, -1.0], atol=0.05)


def test_edge_sightings_rename_a_fixed_point_named_by_motion_alone():
    rng = np.random.default_rng(8)
    landmark_map = LandmarkMap()
    xs = np.arange(0.0, 1.0, STEP)
    for x in xs:
        landmark_map.update(sightings(rng, np.array([x, 0.0]), [CORNER_POINT], [UNKNOWN]), [x, 0, 0])
    assert_array_equal(landmark_map.snapshot().landmark_class, [CORNER_OR_EDGE])
    landmark_map.update(sightings(rng, np.array([xs[-1], 0.0]), [CORNER_POINT], [EDGE], confidence=0.6),
                        [xs[-1], 0, 0])
    snapshot = landmark_map.snapshot()
    assert_array_equal(snapshot.landmark_class, [EDGE])
    assert_allclose(snapshot.confidence, [0.6], rtol=1e-6)


# --------------------------------------------------------------------------- wall merging

def test_two_pieces_of_one_wall_merge_when_the_gap_closes():
    rng = np.random.default_rng(9)
    landmark_map = LandmarkMap()
    for xs in (np.arange(0.0, 1.0, STEP), np.arange(2.0, 3.0, STEP)):
        for x in xs:
            landmark_map.update(sightings(rng, np.array([x, 0.0]), [[x, WALL_Y]], [PLANE]), [x, 0, 0])
    assert len(by_class(landmark_map.snapshot(), PLANE)) == 2
    for x in np.arange(1.0, 2.0, STEP):
        landmark_map.update(sightings(rng, np.array([x, 0.0]), [[x, WALL_Y]], [PLANE]), [x, 0, 0])
    walls = by_class(landmark_map.snapshot(), PLANE)
    assert len(walls) == 1 and landmark_map.counts.merged_walls == 1
    assert_allclose(np.sort(walls.segment[0, :, 0]), [-REFLECTION_HALF_SPREAD, 2.97 + REFLECTION_HALF_SPREAD],
                    atol=0.05)
    error, sigma = wall_offset_error(walls)
    assert abs(error) <= 3.0 * sigma


def test_walls_on_one_line_do_not_merge_across_an_edge_between_them():
    # the two sides of a doorway, grown towards each other until their gap is below the search radius: one wall,
    # unless an edge (the door's jamb) lies on their line between them
    for jamb in (False, True):
        rng = np.random.default_rng(10)
        landmark_map = LandmarkMap()
        if jamb:
            for x in np.arange(1.2, 1.8, STEP):
                landmark_map.update(sightings(rng, np.array([x, 0.0]), [[1.5, WALL_Y]], [EDGE]), [x, 0, 0])
        for xs in (np.arange(0.0, 1.3, STEP), np.arange(3.0, 1.7, -STEP)):  # each side grows towards the other
            for x in xs:
                landmark_map.update(sightings(rng, np.array([x, 0.0]), [[x, WALL_Y]], [PLANE]), [x, 0, 0])
        walls = by_class(landmark_map.snapshot(), PLANE)
        if jamb:
            assert len(walls) == 2 and landmark_map.counts.merged_walls == 0
            assert len(by_class(landmark_map.snapshot(), EDGE)) == 1
        else:
            assert len(walls) == 1 and landmark_map.counts.merged_walls == 1


def test_a_wall_does_not_grow_past_an_edge_on_its_line():
    # a wall seen up to the jamb at x = 1.5; sightings on its line beyond the jamb start the wall on the other
    # side of the doorway instead of growing this one across it; sightings within reach before it still join
    rng = np.random.default_rng(12)
    landmark_map = LandmarkMap()
    for x in np.arange(1.2, 1.8, STEP):
        landmark_map.update(sightings(rng, np.array([x, 0.0]), [[1.5, WALL_Y]], [EDGE]), [x, 0, 0])
    for x in np.arange(0.0, 1.4, STEP):
        landmark_map.update(sightings(rng, np.array([x, 0.0]), [[x, WALL_Y]], [PLANE]), [x, 0, 0])
    for x in np.arange(1.6, 2.2, STEP):  # beyond the jamb, within the search radius of the wall's end
        landmark_map.update(sightings(rng, np.array([x, 0.0]), [[x, WALL_Y]], [PLANE]), [x, 0, 0])
    walls = by_class(landmark_map.snapshot(), PLANE)
    assert len(walls) == 2
    ends = np.sort(np.sort(walls.segment[:, :, 0], axis=1), axis=0)
    assert ends[0, 1] < 1.5 < ends[1, 0], ends  # one wall each side of the jamb


def _wall_seen_up_to(stop):
    """A map of the wall at y = WALL_Y seen from x = 0 to ``stop`` (m) along y = 0, and its walls' uids."""
    rng = np.random.default_rng(11)
    landmark_map = LandmarkMap()
    for x in np.arange(0.0, stop, STEP):
        landmark_map.update(sightings(rng, np.array([x, 0.0]), [[x, WALL_Y]], [PLANE]), [x, 0, 0])
    entries = landmark_map.entries()
    return landmark_map, entries.uid[entries.is_wall]


def test_a_published_wall_ends_at_the_edge_its_seen_extent_ran_past():
    # a seen extent runs up to about 0.25 m past a wall's end where an echo on its line continues it (the
    # realistic room's pillar faces); SLAM publishes the wall ended at the edge there, not past it
    from sonar_ring.slam import SlamSettings

    settings = SlamSettings()
    landmark_map, uid = _wall_seen_up_to(1.25)
    assert np.sort(by_class(landmark_map.snapshot(), PLANE).segment[0, :, 0])[1] > 1.2
    edge = np.array([[0.97, WALL_Y]])
    ended = landmark_map.walls_ended_at(uid, edge, settings.wall_end_reach, settings.wall_end_tolerance)
    assert_allclose(np.sort(by_class(ended.snapshot(), PLANE).segment[0, :, 0])[1], 0.97, atol=1e-3)
    # an edge farther than the reach from the end is another reflector's, not this wall's end
    far = landmark_map.walls_ended_at(uid, edge - [settings.wall_end_reach + 0.3, 0.0], settings.wall_end_reach,
                                      settings.wall_end_tolerance)
    assert np.sort(by_class(far.snapshot(), PLANE).segment[0, :, 0])[1] > 1.2


def test_a_wall_whose_two_ends_end_at_one_point_is_not_published():
    # A jamb's echoes placed a degree off while the sensor passes can line up into a short wall piece; ended at
    # the jamb at both ends it is the jamb seen along a line, not a wall.  The map itself keeps it.
    from sonar_ring.slam import SlamSettings

    settings = SlamSettings()
    landmark_map, uid = _wall_seen_up_to(0.2)
    extent = np.sort(by_class(landmark_map.snapshot(), PLANE).segment[0, :, 0])
    assert len(uid) == 1 and extent[1] - extent[0] < settings.wall_end_reach
    jamb = np.array([[extent.mean(), WALL_Y]])
    ended = landmark_map.walls_ended_at(uid, jamb, settings.wall_end_reach, settings.wall_end_tolerance)
    assert len(by_class(ended.snapshot(), PLANE)) == 0 and len(ended.snapshot_uids()) == len(ended.snapshot()) == 0
    assert len(by_class(landmark_map.snapshot(), PLANE)) == 1
    # ended at two points, one each end, it is a wall between them
    ends = np.array([[extent[0] - 0.05, WALL_Y], [extent[1] + 0.05, WALL_Y]])
    between = landmark_map.walls_ended_at(uid, ends, settings.wall_end_reach, settings.wall_end_tolerance)
    assert_allclose(np.sort(by_class(between.snapshot(), PLANE).segment[0, :, 0]), ends[:, 0], atol=1e-3)


# --------------------------------------------------------------------------- memory

def test_eviction_keeps_the_most_recently_seen_entries_within_the_bound():
    landmark_map = LandmarkMap(max_points=10, max_walls=2)
    covariance = np.diag([1e-4, 1e-4])
    for k in range(30):
        # One distinct corner per ping, 10 m apart, never seen again.
        landmark_map.update(make_landmarks([CORNER], [[10.0 * k, 1.0]], covariance=covariance), [10.0 * k, 0, 0])
        assert len(landmark_map) == min(k + 1, 10)
    assert landmark_map.counts.evicted == 20
    assert_allclose(np.sort(landmark_map.snapshot().position[:, 0]), 10.0 * np.arange(20, 30))
    for k in range(5):
        wall = make_landmarks([PLANE], [[10.0 * k, 1.0]], normal=[[0.0, -1.0]], covariance=covariance,
                              segment=[[[10.0 * k - 0.1, 1.0], [10.0 * k + 0.1, 1.0]]])
        landmark_map.update(wall, [10.0 * k, 0, 0])
    assert len(by_class(landmark_map.snapshot(), PLANE)) == 2


def test_eviction_prefers_the_least_recently_seen_then_the_least_seen():
    landmark_map = LandmarkMap(max_points=2)
    covariance = np.diag([1e-4, 1e-4])
    a, b, c = [0.0, 1.0], [5.0, 1.0], [10.0, 1.0]
    # A is seen twice in the first ping (two groups), B once: on a tie in age B goes first.
    landmark_map.update(make_landmarks([CORNER] * 3, [a, a, b], covariance=covariance), [0, 0, 0])
    landmark_map.update(make_landmarks([CORNER], [c], covariance=covariance), [0, 0, 0])
    assert_allclose(landmark_map.snapshot().position, [a, c])
    # Now C was seen more recently than A: A goes.
    landmark_map.update(make_landmarks([CORNER], [b], covariance=covariance), [0, 0, 0])
    assert_allclose(np.sort(landmark_map.snapshot().position[:, 0]), [5.0, 10.0])


def test_eviction_keeps_a_persistent_entry_over_echoes_that_never_repeat():
    landmark_map = LandmarkMap(max_points=5, min_support_pings=5, min_support_travel=0.05)
    covariance = np.diag([1e-4, 1e-4])
    for x in np.arange(0.0, 0.3, 0.03):  # a corner seen from 10 poses: persistent
        landmark_map.update(make_landmarks([CORNER], [[1.0, 1.0]], covariance=covariance), [x, 0, 0])
    for k in range(20):  # then 20 one-off echoes, each seen once, all seen more recently than the corner
        landmark_map.update(make_landmarks([UNKNOWN], [[10.0 * k + 5.0, 3.0]], covariance=covariance), [0.3, 0, 0])
    assert_allclose(landmark_map.snapshot(persistent=True).position, [[1.0, 1.0]], atol=1e-3)
    assert landmark_map.counts.evicted == 16


def test_a_ping_larger_than_the_map_drops_what_does_not_fit():
    landmark_map = LandmarkMap(max_points=10)
    points = np.column_stack([np.arange(15.0), np.ones(15)])
    landmark_map.update(make_landmarks([CORNER] * 15, points, covariance=np.diag([1e-4, 1e-4])), [0, 0, 0])
    assert len(landmark_map) == 10
    assert landmark_map.counts.dropped == 5 and landmark_map.counts.evicted == 0


# --------------------------------------------------------------------------- costmap points, determinism

def test_points_sample_walls_at_the_spacing_and_list_the_points():
    rng = np.random.default_rng(10)
    landmark_map = LandmarkMap(wall_point_spacing=0.05)
    drive(landmark_map, rng, np.arange(0.0, 1.0, STEP))
    snapshot = landmark_map.snapshot()
    wall = by_class(snapshot, PLANE)
    ends = wall.segment[0]
    length = np.hypot(*(ends[1] - ends[0]))
    points = landmark_map.points()
    samples = int(np.ceil(length / 0.05)) + 1
    assert points.shape == (samples + 1, 2)
    assert_allclose(points[0], ends[0], atol=1e-12)
    assert_allclose(points[samples - 1], ends[1], atol=1e-12)
    steps = np.hypot(*np.diff(points[:samples], axis=0).T)
    assert np.all(steps <= 0.05 + 1e-12)
    assert_allclose(steps, length / (samples - 1), rtol=1e-9)
    assert_allclose(points[samples], by_class(snapshot, CORNER).position[0], atol=0)
    assert landmark_map.points(min_observations=10 ** 6).shape == (0, 2)


def test_update_is_deterministic():
    snapshots = []
    for _ in range(2):
        landmark_map = LandmarkMap()
        drive(landmark_map, np.random.default_rng(11), np.arange(0.0, 2.0, STEP), UNKNOWN, UNKNOWN)
        snapshots.append(landmark_map.snapshot())
    for name in (field.name for field in fields(Landmarks)):
        assert_array_equal(getattr(snapshots[0], name), getattr(snapshots[1], name))


def test_usable_sightings_need_the_settings_not_the_entries():
    """Any map of the same settings gives the same usable sightings, whatever its entries."""
    rng = np.random.default_rng(12)
    mapped, fresh, whole = LandmarkMap(), LandmarkMap(), LandmarkMap()
    drive(mapped, np.random.default_rng(11), np.arange(0.0, 1.0, STEP), UNKNOWN, UNKNOWN)
    drive(whole, np.random.default_rng(11), np.arange(0.0, 1.0, STEP), UNKNOWN, UNKNOWN)
    landmarks = sightings(rng, np.array([1.0, 0.0]), [[1.0, WALL_Y], CORNER_POINT, [2.0, 0.5]], [PLANE, CORNER, EDGE])
    landmarks = replace(landmarks, valid=np.array([True, True, False]))
    pose = [1.0, 0.0, 0.0]
    usable = mapped.usable_sightings(landmarks, pose)
    for name in (field.name for field in fields(usable)):
        assert_array_equal(getattr(usable, name), getattr(fresh.usable_sightings(landmarks, pose), name))
    assert (usable.offered, usable.invalid, usable.landmark_class.size) == (3, 1, 2)
    assert mapped.usable_sightings(landmarks, [np.nan, 0.0, 0.0]) is None
    mapped.add(usable)
    whole.update(landmarks, pose)
    assert mapped.counts == whole.counts
    for name in (field.name for field in fields(Landmarks)):
        assert_array_equal(getattr(mapped.snapshot(), name), getattr(whole.snapshot(), name))


# --------------------------------------------------------------------------- bad input

def test_error_handling():
    landmark_map = LandmarkMap()
    good = make_landmarks([CORNER], [[1.0, 1.0]], covariance=np.diag([1e-4, 1e-4]))
    for pose in ([0.0, 0.0], [[0.0, 0.0, 0.0]], "pose", [0.0, 0.0, 0.0, 0.0]):
        with pytest.raises(ValueError, match="pose"):
            landmark_map.update(good, pose)
        with pytest.raises(ValueError, match="pose"):
            transform_landmarks(good, pose)
    with pytest.raises(ValueError, match="Landmarks"):
        landmark_map.update({"position": [[1.0, 1.0]]}, [0, 0, 0])
    broken = replace(good, covariance=np.eye(2))
    with pytest.raises(ValueError, match="covariance"):
        landmark_map.update(broken, [0, 0, 0])
    with pytest.raises(ValueError, match="explained"):
        landmark_map.update(good, [0, 0, 0], explained=[True, False])
    with pytest.raises(ValueError, match="max_points"):
        LandmarkMap(max_points=0)
    with pytest.raises(ValueError, match="min_support_pings"):
        LandmarkMap(min_support_pings=0)
    with pytest.raises(ValueError, match="min_support_travel"):
        LandmarkMap(min_support_travel=-0.1)
    with pytest.raises(ValueError, match="gate_chi2"):
        LandmarkMap(gate_chi2=-1.0)
    with pytest.raises(ValueError, match="new_entry_gate_chi2"):
        LandmarkMap(gate_chi2=20.0, new_entry_gate_chi2=10.0)
    with pytest.raises(ValueError, match="sighting_sigma"):
        LandmarkMap(sighting_sigma=float("nan"))
    for viewpoints in ([0.0, 0.1], [[0.0, 0.1, 0.0]], [[np.nan, 0.0]]):
        with pytest.raises(ValueError, match="viewpoints"):
            LandmarkMap(viewpoints=viewpoints)
    assert landmark_map.counts == MapCounts()

    # Empty input: counted as a ping, nothing stored.
    landmark_map.update(Landmarks.empty(), [0, 0, 0])
    assert len(landmark_map) == 0 and landmark_map.counts.pings == 1

    # Bad sightings are skipped and counted by kind; the good one is stored.
    nan, inf = float("nan"), float("inf")
    unit = np.diag([1e-4, 1e-4])
    bad = make_landmarks(
        [CORNER, CORNER, CORNER, EDGE, CORNER, 9, PLANE, UNKNOWN, PLANE, CORNER, EDGE, UNKNOWN],
        [[1.0, 1.0], [nan, 1.0], [2.0, 2.0], [3.0, 3.0], [4.0, 4.0], [5.0, 5.0], [6.0, 6.0], [0.0, 0.0],
         [7.0, 7.0], [8.0, 8.0], [inf, 9.0], [10.0, 10.0]],
        covariance=[unit, unit, np.full((2, 2), nan), np.zeros((2, 2)), -unit, unit, unit, unit, unit, unit, unit,
                    np.full((2, 2), inf)],
        normal=[[0, 0]] * 6 + [[0.0, 0.0], [0, 0], [nan, 1.0]] + [[0, 0]] * 3,
        valid=[True] * 9 + [False, True, True])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # bad data is counted quietly
        landmark_map.update(bad, [0, 0, 0])
    counts = landmark_map.counts
    assert (counts.not_finite, counts.degenerate, counts.invalid, counts.created) == (5, 5, 1, 1)
    snapshot = landmark_map.snapshot()
    assert len(snapshot) == 1 and np.all(np.isfinite(snapshot.covariance))
    assert_allclose(snapshot.position, [[1.0, 1.0]])

    # A non-finite pose skips the whole ping.
    landmark_map.update(good, [nan, 0.0, 0.0])
    counts = landmark_map.counts
    assert counts.rejected_pings == 1 and counts.pings == 2 and len(landmark_map) == 1
    assert counts.sightings == (counts.invalid + counts.not_finite + counts.degenerate + counts.ambiguous
                                + counts.fused + counts.created + counts.dropped)


# --------------------------------------------------------------------------- end to end

E2E_PINGS = 150  # 1.5 m of the room's first leg, along the south wall


@pytest.fixture(scope="module")
def room_run():
    """The room scene along its trajectory: Browne ring pings, localised with every model."""
    from sonar_ring import pipeline, simulate
    from sonar_ring.geometry import load_layout

    scene = simulate.load_scene("room")
    layout = load_layout("browne_ring")
    simulator = simulate.Simulator(scene, layout)
    _, poses = scene.trajectory.poses(layout.ping_rate)
    settings = pipeline.Settings(sigma_tof=1e-6)
    rng = np.random.default_rng(12)
    pings = []
    for pose in poses[:E2E_PINGS]:
        ping = simulator.ping(pose, noise=simulate.Noise(tof=1e-6), rng=rng)
        echoes = ping.echoes
        pings.append((pose, ping, pipeline.localise_ping(layout, echoes, settings)))
    return scene, pings


def map_room(pings, unclassified):
    """Map the room with each echo localised by its true class's model.

    ``unclassified``: planes and corners are placed with the corner model and labelled
    UNKNOWN (Browne s7), so the map must tell them apart by motion; edges stay EDGE.
    """
    landmark_map = LandmarkMap()
    for pose, ping, hypotheses in pings:
        truth = ping.truth_class[hypotheses.echo]
        model = np.where(unclassified & (truth != EDGE), CORNER, truth)
        landmarks = hypotheses.select((hypotheses.landmark_class == model) & hypotheses.valid)
        if unclassified:
            landmarks = landmarks.with_class(np.where(landmarks.landmark_class == EDGE, EDGE, UNKNOWN),
                                             np.zeros(len(landmarks)))
        landmark_map.update(transform_landmarks(landmarks, pose), pose)
    return landmark_map


def labelled_entries_match_truth(scene, snapshot):
    """Check every labelled entry against the scene; return the reflector (scene index) each matched."""
    points = np.vstack([scene.corner_point, scene.edges])
    point_class = np.r_[np.full(len(scene.corner_point), CORNER), np.full(len(scene.edges), EDGE)]
    matched = []
    for k in np.flatnonzero(snapshot.landmark_class != UNKNOWN):
        if snapshot.landmark_class[k] == PLANE:
            start, end = scene.walls[:, 0], scene.walls[:, 1]
            along = (end - start) / np.hypot(*(end - start).T)[:, None]
            normal = snapshot.normal[k]
            offset = np.einsum("wi,wi->w", snapshot.position[k] - start, np.stack([-along[:, 1], along[:, 0]], 1))
            # Parallel walls whose segment holds the entry's middle (collinear walls share a line).
            middle = np.einsum("wi,wi->w", snapshot.position[k] - start, along)
            length = np.hypot(*(end - start).T)
            candidates = np.flatnonzero((np.abs(along @ normal) < np.sin(np.radians(1.0)))
                                        & (middle > -0.1) & (middle < length + 0.1))
            wall = candidates[np.argmin(np.abs(offset[candidates]))]
            sigma = np.sqrt(normal @ snapshot.covariance[k] @ normal)
            assert abs(offset[wall]) <= 3.0 * sigma
            matched.append(int(np.flatnonzero((scene.reflector_class == PLANE) & (scene.kind_index == wall))[0]))
        else:
            error = points - snapshot.position[k]
            nearest = np.argmin(np.hypot(*error.T))
            assert snapshot.landmark_class[k] in (point_class[nearest], CORNER_OR_EDGE)
            assert mahalanobis2(error[nearest], snapshot.covariance[k]) <= CHI2_2DOF_3SIGMA
            row = nearest - (len(scene.corner_point) if point_class[nearest] == EDGE else 0)
            matched.append(int(np.flatnonzero((scene.reflector_class == point_class[nearest])
                                              & (scene.kind_index == row))[0]))
    return matched


@pytest.mark.parametrize("unclassified", [False, True], ids=["classified", "unclassified"])
def test_room_end_to_end(room_run, unclassified):
    scene, pings = room_run
    landmark_map = map_room(pings, unclassified)
    snapshot = landmark_map.snapshot(min_observations=5)
    matched = labelled_entries_match_truth(scene, snapshot)
    heard = np.unique(np.concatenate([ping.truth_reflector for _, ping, _ in pings]))
    if unclassified:
        # Driving straight at the west and east walls keeps their foot points still: UNKNOWN.
        heard = [f for f in heard if scene.reflector_names[f] not in ("west", "east")]
        unknown = snapshot.select(snapshot.landmark_class == UNKNOWN)
        assert_allclose(np.sort(unknown.position[:, 0]), [0.0, 6.0], atol=0.01)
        assert landmark_map.counts.resolved_fixed == 4
    # Exactly one labelled entry, of the right class and within 3 sigma, for every reflector heard.
    assert sorted(matched) == list(heard)
    # The south wall, driven along, is one segment covering the travel (x 1.2 .. 2.69).
    south = snapshot.select((snapshot.landmark_class == PLANE) & (np.abs(snapshot.position[:, 1]) < 0.05))
    assert len(south) == 1
    assert_allclose(south.normal[0], [0.0, 1.0], atol=np.sin(np.radians(0.5)))
    travel = [pings[0][0][0], pings[-1][0][0]]
    assert_allclose(np.sort(south.segment[0, :, 0]), travel, atol=0.1)


def test_a_plane_normal_that_overflows_is_not_finite():
    """Huge components pass one by one but their sum overflows: corrupt, like NaN."""
    landmark_map = LandmarkMap()
    plane = make_landmarks([PLANE], [[1.0, 1.0]], normal=[[1e308, 1e308]], covariance=np.diag([1e-4, 1e-4]))
    landmark_map.update(plane, [0.0, 0.0, 0.0])
    assert landmark_map.counts.not_finite == 1 and len(landmark_map) == 0
