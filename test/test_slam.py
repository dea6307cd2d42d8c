"""The SLAM core on small hand-built cases: the wall factor's Jacobians, a pose offset recovered from two walls
and a corner, a loop closed without duplicates, faults detected, and the mapper's core around it."""

import itertools
import math
from dataclasses import replace
from types import SimpleNamespace

import gtsam
import numpy as np
import pytest
from numpy.testing import assert_allclose

from sonar_ring import pipeline
from sonar_ring.curvature import point_models
from sonar_ring.echoes import screen_ping
from sonar_ring.explain import EchoTests
from sonar_ring.geometry import load_layout
from sonar_ring.landmarks import CORNER, CORNER_OR_EDGE, EDGE, PLANE, UNKNOWN, Landmarks, make_landmarks
from sonar_ring.map_builder import MapBuilder, MapperSettings
from sonar_ring.ping_stage import Counts, PingStage
from sonar_ring.poses import (
    QUATERNION_NORM_TOLERANCE,
    PoseHistory,
    compose,
    pose_covariance_at,
    relative_pose,
    step_covariance,
    yaw_of,
)
from sonar_ring.realism import IDEAL, World, air_speed
from sonar_ring.score import score_map, trajectory_error
from sonar_ring.simulate import DIRECT, Noise, load_scene
from sonar_ring.slam import (
    POSE,
    LandmarkSlam,
    SlamSettings,
    _expected_measurements,
    consistent_sightings,
    wall_error,
)

RING = load_layout("browne_ring")
SETTINGS = pipeline.Settings(sigma_speed=pipeline.ROBOT_SIGMA_SPEED)
STAGE = PingStage(RING, SETTINGS)
CORNER_ROOM = load_scene({
    "name": "corner_room",
    "reflectors": [
        {"type": "wall", "name": "south", "from": [0.0, 0.0], "to": [4.0, 0.0]},
        {"type": "wall", "name": "west", "from": [0.0, 3.0], "to": [0.0, 0.0]},
        {"type": "corner", "name": "sw", "walls": ["south", "west"]},
    ],
})


def labelled_pings(scene, poses, seed=0):
    world = World(scene, RING, IDEAL, noise=Noise(tof=1e-6, amplitude=0.02), seed=seed)
    pings = [world.ping(pose, k / RING.ping_rate) for k, pose in enumerate(poses)]
    echoes = [screen_ping(p.echoes, RING).echoes for p in pings]
    return [STAGE.label(e)[1] if e is not None else Landmarks.empty() for e in echoes], pings


def test_wall_error_jacobians_match_finite_differences():
    pose = gtsam.Pose2(0.3, -0.2, 0.4)
    line = np.array([1.1, 2.5])  # theta, d
    measured = np.array([0.5, 1.0])
    jacobians = [np.zeros((2, 3)), np.zeros((2, 2))]
    base = wall_error(pose, line, measured, jacobians)
    step = 1e-7
    numeric_pose = np.column_stack([(wall_error(pose.retract(step * np.eye(3)[k]), line, measured) - base) / step
                                    for k in range(3)])
    numeric_line = np.column_stack([(wall_error(pose, line + step * np.eye(2)[k], measured) - base) / step
                                    for k in range(2)])
    assert_allclose(jacobians[0], numeric_pose, atol=1e-6)
    assert_allclose(jacobians[1], numeric_line, atol=1e-6)
    # the foot point of the line n . x = d seen from the pose, in its frame
    normal = np.array([math.cos(1.1), math.sin(1.1)])
    foot = (2.5 - normal @ [0.3, -0.2]) * normal
    c, s = math.cos(0.4), math.sin(0.4)
    assert_allclose(base + measured, np.array([[c, s], [-s, c]]) @ foot, atol=1e-12)


def test_expected_measurements_and_their_jacobian_match_finite_differences():
    pose = np.array([0.3, -0.2, 0.4])
    is_wall = np.array([False, True, False, True])
    anchor = np.array([[2.0, 1.0], [1.1, 2.5], [-1.0, 0.5], [-0.7, -2.0]])
    angles = np.array([0.0, 1.2, 0.0, -2.0])
    normal = np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    expected, jacobian = _expected_measurements(pose, is_wall, anchor, normal)
    # a wall's foot point is wall_error's (line (theta, d)), a point's its position in the robot frame
    for row in np.flatnonzero(is_wall):
        line = np.array([angles[row], normal[row] @ anchor[row]])
        assert_allclose(expected[row], wall_error(gtsam.Pose2(*pose), line, np.zeros(2)), atol=1e-12)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    assert_allclose(expected[~is_wall], (anchor[~is_wall] - pose[:2]) @ np.array([[c, -s], [s, c]]), atol=1e-12)
    step = 1e-7
    for k in range(3):
        moved = gtsam.Pose2(*pose).retract(step * np.eye(3)[k])
        numeric = (_expected_measurements(np.array([moved.x(), moved.y(), moved.theta()]), is_wall, anchor,
                                          normal)[0] - expected) / step
        assert_allclose(jacobian[:, :, k], numeric, atol=1e-6)


def test_a_sighting_that_disagrees_with_the_map_is_left_out_but_a_slip_moves_none():
    # Twelve entries around the robot, measured from the true pose with 2 mm of noise; the estimate of the pose
    # is off by a slip (3 cm, 1 deg) and two sightings (a double bounce fused into a point, one into a wall) by
    # 3 cm: the slip is fitted out, the two are left out (and the noise's tail, a few of the others).
    rng = np.random.default_rng(5)
    truth = np.array([1.0, 2.0, 0.3])
    estimate = compose(truth, (0.03, -0.02, math.radians(1.0)))
    is_wall = np.arange(12) % 3 == 0
    bearing = np.linspace(-np.pi, np.pi, 12, endpoint=False)
    anchor = truth[:2] + rng.uniform(1.0, 3.0, 12)[:, None] * np.stack([np.cos(bearing), np.sin(bearing)], -1)
    normal = -np.stack([np.cos(bearing + 0.2), np.sin(bearing + 0.2)], -1)  # facing the robot
    measured, _ = _expected_measurements(truth, is_wall, anchor, normal)
    covariance = np.tile(0.002 ** 2 * np.eye(2), (12, 1, 1))
    measured += rng.normal(0.0, 0.002, measured.shape)
    measured[[1, 3]] += 0.03 * np.array([[0.6, 0.8], [-0.8, 0.6]])
    prior = np.diag([0.02 ** 2, 0.02 ** 2, math.radians(1.0) ** 2])
    agrees = consistent_sightings(estimate, prior, measured, covariance, is_wall, anchor, normal, 4.0)
    outliers = np.isin(np.arange(12), [1, 3])
    assert not agrees[outliers].any() and np.count_nonzero(agrees[~outliers]) >= 8  # chi2 4 keeps 86 % of 2 dof
    # With a prior that does not allow the slip, almost every sighting seems off.
    tight = consistent_sightings(estimate, 1e-12 * np.eye(3), measured, covariance, is_wall, anchor, normal, 4.0)
    assert np.count_nonzero(tight) <= 2


def test_a_pose_offset_is_recovered_from_two_walls_and_a_corner():
    # The robot drives inside the corner; the odometry is exact for a stretch (the map forms), then reports
    # every pose 4 cm and 1.5 deg off: the walls and the corner pull the estimate back to the truth.
    truth = np.array([[1.0 + 0.01 * k, 1.0 + 0.004 * k, math.radians(-100 + 0.3 * k)] for k in range(150)])
    landmarks, _ = labelled_pings(CORNER_ROOM, truth)
    slam = LandmarkSlam()
    offset = np.array([0.04, -0.02, math.radians(1.5)])
    estimates = []
    for k, (found, pose) in enumerate(zip(landmarks, truth, strict=True)):
        odometry = pose if k < 100 else compose(pose, offset * min(1.0, (k - 100) / 10))
        estimates.append(slam.add_ping(found, odometry, k / RING.ping_rate, models=point_models(RING, found)).pose)
    classes = slam.snapshot().landmark_class
    assert np.count_nonzero(classes == PLANE) == 2 and np.count_nonzero(classes == CORNER) == 1
    # While the odometry is exact, the map agrees with it: the walls' first sightings are in the graph.
    before = relative_pose(truth[99], estimates[99])
    assert math.hypot(before[0], before[1]) < 0.001 and abs(before[2]) < math.radians(0.1), before
    final = relative_pose(truth[-1], estimates[-1])
    assert math.hypot(final[0], final[1]) < 0.01 and abs(final[2]) < math.radians(0.3), final
    assert math.hypot(*offset[:2]) > 0.04  # what the odometry alone is off by


def test_a_step_covariance_is_the_growth_of_dead_reckoning():
    # Dead reckoning: a start pose with its covariance and a step with its own, sampled (small noise, so the
    # linear propagation holds), give the end's covariance; the step's is recovered from the two poses' alone.
    rng = np.random.default_rng(7)
    start, step = np.array([1.0, -2.0, 2.5]), np.array([0.3, 0.05, 0.2])
    start_covariance = np.diag([4e-6, 9e-6, 1e-6]) + 1e-6 * np.array([[0, 1, 0], [1, 0, -1], [0, -1, 0]])
    step_noise = np.diag([1e-6, 4e-7, 2e-6]) + 2e-7 * np.array([[0, 1, 1], [1, 0, 0], [1, 0, 0]])
    starts = rng.multivariate_normal(start, start_covariance, 200_000)
    steps = rng.multivariate_normal(step, step_noise, 200_000)
    c, s = np.cos(starts[:, 2]), np.sin(starts[:, 2])
    ends = np.stack([starts[:, 0] + c * steps[:, 0] - s * steps[:, 1], starts[:, 1] + s * steps[:, 0]
                     + c * steps[:, 1], starts[:, 2] + steps[:, 2]], -1)
    end = compose(start, step)
    c, s = math.cos(start[2]), math.sin(start[2])
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    end_covariance = pose_covariance_at(start, start_covariance, step) + turn @ step_noise @ turn.T
    assert_allclose(np.cov(ends.T), end_covariance, rtol=0.03, atol=3e-8)
    assert_allclose(step_covariance(start, start_covariance, end, end_covariance), step_noise, rtol=1e-9,
                    atol=1e-18)
    # A covariance that does not grow so gives none: a fixed one, all zeros (unknown), one not finite.
    for fixed in (start_covariance, np.zeros((3, 3))):
        assert step_covariance(start, fixed, end, fixed) is None
    assert step_covariance(start, start_covariance, end, np.full((3, 3), np.nan)) is None


def test_the_pose_history_interpolates_covariances_where_both_poses_have_one():
    history = PoseHistory(limit=2)
    history.add(100, (0.0, 0.0, 0.0), np.eye(3))
    history.add(200, (1.0, 0.0, 0.0), 3.0 * np.eye(3))
    history.add(300, (2.0, 0.0, 0.0))
    assert_allclose(history.covariance_at(150), 2.0 * np.eye(3))
    assert_allclose(history.covariance_at(200), 3.0 * np.eye(3))
    assert history.covariance_at(250) is None and history.covariance_at(300) is None
    assert history.covariance_at(301) is None and history.at(301) is None
    history.add(400, (3.0, 0.0, 0.0), np.eye(3))  # the limit drops the oldest poses with their covariances
    assert history.too_old(150) and history.covariance_at(400) is not None and history.covariance_at(350) is None


def dead_reckoning(odometry, variance_per_metre):
    """The covariances (3, 3) dead reckoning reports along ``odometry`` (P, 3): each step's noise proportional to
    its length, propagated from an exact start."""
    covariances = [np.zeros((3, 3))]
    for start, end in itertools.pairwise(odometry):
        step = relative_pose(start, end)
        c, s = math.cos(start[2]), math.sin(start[2])
        turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        covariances.append(pose_covariance_at(start, covariances[-1], step)
                           + turn @ (variance_per_metre * math.hypot(*step[:2]) * np.eye(3)) @ turn.T)
    return covariances


def test_the_odometrys_own_covariance_gives_its_noise_where_it_grows():
    # As in the offset test above, the odometry reports every pose 4 cm and 1.5 deg off after a stretch, now
    # with the covariance a dead reckoning reports (a step's noise proportional to its length, propagated).
    # Odometry that claims to be ten thousand times better than the parameters' noise is believed over the
    # walls; one about as good as they say is not (the offset recovered, as with the parameters); a
    # covariance that does not grow (a fixed one) leaves the parameters' noise, bit for bit, and says so.
    truth = np.array([[1.0 + 0.01 * k, 1.0 + 0.004 * k, math.radians(-100 + 0.3 * k)] for k in range(150)])
    landmarks, _ = labelled_pings(CORNER_ROOM, truth)
    offset = np.array([0.04, -0.02, math.radians(1.5)])
    odometry = [pose if k < 100 else compose(pose, offset * min(1.0, (k - 100) / 10)) for k, pose in enumerate(truth)]

    def estimated(covariances):
        slam, estimates, keyframes, assumed = LandmarkSlam(), [], 0, 0
        for k, (found, pose, covariance) in enumerate(zip(landmarks, odometry, covariances, strict=True)):
            report = slam.add_ping(found, pose, k / RING.ping_rate, models=point_models(RING, found),
                                   odometry_covariance=covariance)
            estimates.append(report.pose)
            keyframes += report.keyframe and k > 0
            assumed += report.step_noise_assumed
        final = relative_pose(truth[-1], estimates[-1])
        return np.array(estimates), math.hypot(final[0], final[1]), keyframes, assumed

    parameters, off, keyframes, assumed = estimated([None] * len(truth))
    assert off < 0.01 and keyframes > 10 and assumed == 0
    _, off, _, assumed = estimated(dead_reckoning(odometry, 1e-8))  # 0.1 mm per sqrt(m)
    assert off > 0.04 and assumed == 0
    _, off, _, assumed = estimated(dead_reckoning(odometry, 1e-4))  # 1 cm per sqrt(m), the parameters' 2 cm
    assert off < 0.01 and assumed == 0
    fixed, _, keyframes, assumed = estimated([np.diag([1e-4, 1e-4, 1e-4])] * len(truth))
    np.testing.assert_array_equal(fixed, parameters)
    assert assumed == keyframes


def test_the_mapper_reads_the_odometrys_covariance_unless_told_not_to():
    """A dead reckoning's covariance that claims precise odometry moves the mapper's poses; with
    use_odometry_covariance false they are the parameters' poses, bit for bit, and nothing is counted."""
    truth = np.array([[1.0 + 0.01 * k, 1.0, math.radians(-135)] for k in range(60)])
    landmarks, _ = labelled_pings(CORNER_ROOM, truth)
    odometry = [compose(pose, (0.0, 0.0, math.radians(0.02) * k)) for k, pose in enumerate(truth)]  # drifting

    def poses(covariances, **settings):
        health = Counts()
        builder = MapBuilder(MapperSettings(layout=RING, **settings), health)
        estimates = []
        for k, (found, pose, covariance) in enumerate(zip(landmarks, odometry, covariances, strict=True)):
            stamp = int(1e9 + k * 1e9 / RING.ping_rate)
            builder.add_odometry(stamp, pose, covariance)
            builder.add_ping(stamp, found)
            estimates.append(builder.robot_pose)
        return np.array(estimates), health

    parameters, _ = poses([None] * len(truth))
    precise = dead_reckoning(odometry, 1e-8)
    believed, _ = poses(precise)
    unread, health = poses(precise, use_odometry_covariance=False)
    assert not np.array_equal(believed, parameters)
    np.testing.assert_array_equal(unread, parameters)
    assert not health.problems and "odometry covariance not growing" not in health.notes


def test_the_map_keeps_the_first_keyframes_heading_while_the_odometrys_drifts():
    # The odometry's heading drifts from the start, 1 deg a metre.  The walls are walls only after the sensor
    # has moved, and confirmed some pings later: with only the sightings from then on, the graph placed them
    # with the heading the odometry had then; with the sightings held from the first ping, with the first
    # keyframe's (the map's origin, exact).
    truth = np.array([[1.0 + 0.01 * k, 1.0 + 0.004 * k, math.radians(-100 + 0.3 * k)] for k in range(100)])
    landmarks, _ = labelled_pings(CORNER_ROOM, truth)
    slam = LandmarkSlam()
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(truth[:, :2], axis=0).T))])
    for k, (found, pose) in enumerate(zip(landmarks, truth, strict=True)):
        odometry = pose + [0.0, 0.0, math.radians(1.0) * travelled[k]]
        slam.add_ping(found, odometry, k / RING.ping_rate, models=point_models(RING, found))
    mapped = slam.snapshot()
    walls = mapped.select(mapped.landmark_class == PLANE)
    assert len(walls) == 2
    # the south wall's normal is +y, the west wall's +x
    turn = np.degrees([math.atan2(-normal[0], normal[1]) if abs(normal[1]) > abs(normal[0])
                       else math.atan2(normal[1], normal[0]) for normal in walls.normal])
    assert np.all(np.abs(turn) < 0.2), turn  # without the held sightings 0.34 and 0.53 deg
    assert math.degrees(travelled[-1] * math.radians(1.0)) > 0.9  # what the odometry's heading is off by


def test_a_loop_closes_without_duplicates():
    room = load_scene("room")
    realism = replace(IDEAL, odometry_scale_error=0.01, odometry_heading_bias=0.005, odometry_heading_noise=0.01,
                      odometry_distance_noise=0.01)
    world = World(room, RING, realism, noise=Noise(tof=1e-6, amplitude=0.02), seed=3)
    poses = room.trajectory.poses(RING.ping_rate)[1]
    slam = LandmarkSlam()
    estimates, odometry, truth, heard = [], [], [], set()
    for k in range(2 * len(poses)):  # two laps: the second re-observes the first's landmarks
        pose = poses[k % len(poses)]
        ping = world.ping(pose, k / RING.ping_rate)
        odometry.append(world.odometry_pose(pose))
        truth.append(pose)
        heard.update(ping.truth_reflector[(ping.truth_origin == DIRECT) & np.isfinite(ping.tof).all(axis=1)].tolist())
        echoes = screen_ping(ping.echoes, RING).echoes
        found = STAGE.label(echoes)[1]
        estimates.append(slam.add_ping(found, odometry[-1], k / RING.ping_rate).pose)
    score = score_map(slam.snapshot(min_observations=2), room, sorted(heard))
    assert score.total("duplicates") == 0 and score.ghosts == 0, score.summary()
    assert score.per_class["plane"].mapped == score.per_class["plane"].heard, score.summary()
    rms, final = trajectory_error(estimates, truth)
    odometry_rms, odometry_final = trajectory_error(odometry, truth)
    assert rms < 0.02 and final < 0.02 and odometry_final > 5 * final, (rms, final, odometry_rms, odometry_final)


def test_the_airs_speed_is_found_and_the_published_map_scaled_by_it():
    # One lap of the room in air 2 K warmer than the nodes assume (every path 0.37 % short): the graph holds the
    # map 0.37 % small; the pairs' disagreement on each reflector's bearing gives the air's speed, and the map
    # is published at the true scale.
    room = load_scene("room")
    world = World(room, RING, replace(IDEAL, temperature_offset=2.0), noise=Noise(tof=1e-6, amplitude=0.02), seed=1)
    poses = room.trajectory.poses(RING.ping_rate)[1]
    slam = LandmarkSlam(layout=RING)
    heard = set()
    for k, pose in enumerate(poses):
        ping = world.ping(pose, k / RING.ping_rate)
        heard.update(ping.truth_reflector[(ping.truth_origin == DIRECT) & np.isfinite(ping.tof).all(axis=1)].tolist())
        found = STAGE.label(screen_ping(ping.echoes, RING).echoes)[1]
        slam.add_ping(found, world.odometry_pose(pose), k / RING.ping_rate, models=point_models(RING, found))
    true_error = air_speed(room, world.realism, 0.0) / room.speed_of_sound - 1.0
    error, sigma = slam.air_estimate
    assert abs(error - true_error) < 3 * sigma and sigma < 0.001, (error, sigma, true_error)
    published = score_map(slam.snapshot(min_observations=2), room, sorted(heard))
    held = score_map(slam.snapshot_and_uids(min_observations=2)[0], room, sorted(heard))
    assert abs(held.similarity[0] - 1.0 - true_error) < 0.0005, held.similarity  # the graph's map: small
    assert abs(published.similarity[0] - 1.0) < 3 * sigma, published.similarity
    assert np.median(published.point_error) < 0.6 * np.median(held.point_error)


def test_a_fixed_point_enters_the_graph_once_its_curvature_tells_edge_from_corner():
    # Passing a pole 2 m away, the motion names it a fixed point within half a metre; the wavefront's curvature
    # tells it an edge a few decimetres later.  Until then it is CORNER_OR_EDGE, as the multipath that no model
    # fits stays: it must not pull the pose (nor cost the smoother) until it is decided.
    scene = load_scene({"name": "pole_room", "reflectors": [
        {"type": "wall", "name": "south", "from": [0.0, 0.0], "to": [4.0, 0.0]},
        {"type": "wall", "name": "west", "from": [0.0, 3.0], "to": [0.0, 0.0]},
        {"type": "corner", "name": "sw", "walls": ["south", "west"]},
        {"type": "edge", "name": "pole", "at": [2.5, 2.2]}]})
    truth = np.array([[1.0 + 0.01 * k, 0.2, math.radians(45)] for k in range(150)])
    landmarks, _ = labelled_pings(scene, truth)
    slam = LandmarkSlam()
    keyframes_awaiting = 0
    for k, (found, pose) in enumerate(zip(landmarks, truth, strict=True)):
        report = slam.add_ping(found, pose, k / RING.ping_rate, models=point_models(RING, found))
        entries = slam.front.entries()
        awaiting = (entries.landmark_class == CORNER_OR_EDGE) & slam.front.persistent(entries.uid)
        keyframes_awaiting += bool(report.keyframe and awaiting.any())
        assert slam.front.decided(slam.confirmed).all()
        assert not np.isin(entries.uid[awaiting], slam.confirmed).any()
    assert keyframes_awaiting >= 2
    mapped = slam.snapshot()
    pole = np.flatnonzero(np.hypot(*(mapped.position - [2.5, 2.2]).T) < 0.05)
    assert mapped.landmark_class[pole].tolist() == [EDGE]


def test_between_two_marginals_a_keyframe_holds_the_last_one_turned_into_its_frame():
    truth = np.array([[1.0 + 0.01 * k, 1.0, math.radians(-135)] for k in range(130)])
    landmarks, _ = labelled_pings(CORNER_ROOM, truth)
    slam = LandmarkSlam(SlamSettings(covariance_every=5))
    kept = {}
    for k, (found, pose) in enumerate(zip(landmarks, truth, strict=True)):
        if slam.add_ping(found, pose, k / RING.ping_rate).keyframe and slam._keyframe > 0:
            key = gtsam.symbol("x", slam._keyframe)
            kept[slam._keyframe] = (slam._keyframe_covariance.copy(), slam._keyframe_odometry.copy(),
                                    slam._smoother.marginalCovariance(key))
    assert len(kept) >= 10
    for index, (covariance, odometry, marginal) in kept.items():
        if index % 5 == 0:
            assert_allclose(covariance, marginal, rtol=1e-9)
        elif index - 1 in kept:
            adjoint = gtsam.Pose2(*relative_pose(kept[index - 1][1], odometry)).inverse().AdjointMap()
            assert_allclose(covariance, adjoint @ kept[index - 1][0] @ adjoint.T, rtol=1e-9, atol=1e-15)
            assert np.all(np.linalg.eigvalsh(covariance) > 0)


def test_an_odometry_jump_starts_a_new_session_and_a_stretch_without_landmarks_is_reported():
    truth = np.array([[1.0 + 0.01 * k, 1.0, math.radians(-135)] for k in range(80)])
    landmarks, _ = labelled_pings(CORNER_ROOM, truth)
    health = Counts()
    builder = MapBuilder(MapperSettings(), health)
    for k, (found, pose) in enumerate(zip(landmarks, truth, strict=True)):
        odometry = pose if k < 60 else compose(pose, (0.5, 0.0, math.radians(20)))  # slipped wheels
        stamp = int(1e9 + k * 1e9 / RING.ping_rate)
        builder.add_odometry(stamp, odometry)
        assert builder.add_ping(stamp, found)
    assert health.problems["odometry_jump"] == 1 and builder.slam.sessions == 2
    assert len(builder.snapshot()) < 3  # the new session does not hold the old map's landmarks
    # now nothing to see for a while: the SLAM says so once
    later = int(1e9 + 80 * 1e9 / RING.ping_rate)
    for k in range(1, 300):
        stamp = later + int(k * 1e9 / RING.ping_rate)
        builder.add_odometry(stamp, compose(truth[-1], (0.005 * k, 0.0, 0.0)))
        builder.add_ping(stamp, Landmarks.empty())
    assert health.problems["no_landmarks"] == 1


def test_an_entry_the_poses_that_should_hear_it_do_not_hear_leaves_the_map():
    """A point seen in a burst of pings and never again, where the ring would hear it, is removed; the room stays.

    The ghost is a CORNER sighting at (2, 2), in the room and in the ring's reach from every pose, added
    to the first 20 pings' landmarks; the room's entries are heard in nearly every ping and stay as
    mapped without the ghost.
    """
    truth = np.array([[1.0 + 0.01 * k, 1.0, math.radians(-135)] for k in range(160)])
    landmarks, _ = labelled_pings(CORNER_ROOM, truth)
    ghost = np.array([2.0, 2.0])
    tests = EchoTests(unheard_after=50, unheard_fraction=0.25, hearing_every=1)

    def mapped(with_ghost):
        health = Counts()
        builder = MapBuilder(MapperSettings(layout=RING, echo_tests=tests), health)
        ghost_mapped = False
        for k, (found, pose) in enumerate(zip(landmarks, truth, strict=True)):
            if with_ghost and k < 20:
                c, s = math.cos(pose[2]), math.sin(pose[2])
                local = np.array([[c, s], [-s, c]]) @ (ghost - pose[:2])
                group = int(np.argmax(RING.plan.facing @ local))
                found = Landmarks.concatenate([found, make_landmarks(
                    [CORNER], local, covariance=np.diag([2.5e-5, 2.5e-5]), confidence=0.99, group=group)])
            stamp = int(1e9 + k * 1e9 / RING.ping_rate)
            builder.add_odometry(stamp, pose)
            builder.add_ping(stamp, found)
            ghost_mapped |= bool(np.any(np.hypot(*(builder.snapshot().position - ghost).T) < 0.05))
        return builder.snapshot(), health, ghost_mapped

    room, health, _ = mapped(False)
    assert "not heard where expected" not in health.notes and score_map(room, CORNER_ROOM).total("mapped") >= 2
    with_ghost, health, ghost_mapped = mapped(True)
    assert ghost_mapped  # confirmed and decided before it left
    assert health.notes["not heard where expected"] == 1
    assert_allclose(with_ghost.position, room.position, atol=1e-3)
    assert np.array_equal(with_ghost.landmark_class, room.landmark_class)


def test_the_builder_waits_for_odometry_and_counts_what_it_cannot_place():
    health = Counts()
    builder = MapBuilder(MapperSettings(slam=False), health)
    empty = Landmarks.empty()
    builder.add_odometry(100, (0.0, 0.0, 0.0))
    assert not builder.add_ping(50, empty) and health.problems["pose_too_old"] == 1
    assert not builder.add_ping(200, empty) and builder.pending == 1  # waits for a later odometry
    assert builder.add_odometry(300, (0.3, 0.0, 0.0)) == 1 and builder.pending == 0
    assert_allclose(builder.robot_pose, (0.15, 0.0, 0.0))  # interpolated at its stamp
    for k in range(40):
        builder.add_ping(400 + k, empty)
    assert health.problems["no_odometry"] == 40 - 32
    builder.give_up_waiting()
    assert health.problems["no_odometry"] == 40 and builder.frame == "odom"


class _Indeterminate:
    """A session's smoother whose updates bring a point that only a bearing fixes (its range free): GTSAM raises."""

    def __init__(self, smoother):
        self.smoother, self.points = smoother, itertools.count()

    def update(self, graph, values, timestamps):
        key = gtsam.symbol("z", next(self.points))
        pose = max(k for k in timestamps if gtsam.Symbol(k).chr() == ord(POSE))
        graph.add(gtsam.BearingFactor2D(pose, key, gtsam.Rot2(0.0), gtsam.noiseModel.Isotropic.Sigma(1, 0.01)))
        values.insert(key, gtsam.Point2(1.0, 0.0))
        timestamps[key] = max(timestamps.values())
        return self.smoother.update(graph, values, timestamps)

    def __getattr__(self, name):
        return getattr(self.smoother, name)


def test_an_estimator_that_raises_starts_a_new_session_and_the_mapper_goes_on():
    """GTSAM raises on an indeterminate system (damaged landmarks gave one in a fuzzed run): the mapper said
    nothing and died; now the session's graph is dropped, the fault counted, and the next pings are mapped."""
    health = Counts()
    builder = MapBuilder(MapperSettings(), health)
    for k in range(60):
        if k == 10:
            builder.slam._smoother = _Indeterminate(builder.slam._smoother)
        stamp = 10**9 + k * 10**8
        builder.add_odometry(stamp, (0.05 * k, 0.0, 0.0))
        assert builder.add_ping(stamp, Landmarks.empty())
    assert health.problems["estimator_failed"] == 1 and builder.slam.sessions == 2
    assert_allclose(builder.robot_pose, (0.05 * 59, 0.0, 0.0), atol=1e-9)  # the new session follows the odometry


def test_landmarks_of_a_group_the_layout_lacks_are_dropped_and_counted_the_rest_mapped():
    """A landmarks/pairs message is any node's: a group beyond the layout's raised IndexError in the point models
    (or ValueError in the echo tests), which killed the mapper."""
    health = Counts()
    builder = MapBuilder(MapperSettings(layout=load_layout("browne_ring"), echo_tests=EchoTests()), health)
    covariance = np.tile(1e-4 * np.eye(2), (2, 1, 1))
    for k in range(3):
        stamp = 10**9 + k * 10**8
        builder.add_odometry(stamp, (0.01 * k, 0.0, 0.0))
        assert builder.add_ping(stamp, make_landmarks([UNKNOWN, UNKNOWN], [[1.0, 0.2], [1.5, -0.3]],
                                                      covariance=covariance, group=[0, 5000 if k == 1 else 1]))
    assert dict(health.problems) == {"unknown_group": 1}
    assert builder.landmark_map.counts.sightings == 5


def test_an_odometry_pose_beyond_a_million_metres_is_refused_not_raised():
    """Its odometry noise, squared in Python floats for the echo tests' pose, raised OverflowError."""
    health = Counts()
    builder = MapBuilder(MapperSettings(layout=load_layout("browne_ring"), echo_tests=EchoTests()), health)
    landmarks = make_landmarks([UNKNOWN], [[1.0, 0.2]], covariance=1e-4 * np.eye(2)[None])
    for k, x in enumerate([0.0, 0.01, 1e300, 0.03]):
        builder.add_odometry(10**9 + k * 10**8, (x, 0.0, 0.0))
        builder.add_ping(10**9 + k * 10**8, landmarks)
    assert dict(health.problems) == {"not_finite_pose": 1}


def test_an_odometry_covariance_the_map_does_not_take_is_counted_and_its_pose_kept():
    """Not finite, not symmetric, a negative variance, or beyond (10^6 m)^2 (whose squares raised OverflowError in
    the echo tests' tolerance, found by fuzzing): counted, the pose mapped with the parameters' noise.  Given
    to the SLAM core directly, such a covariance is left out alike (its docstring: nothing raises)."""
    truth = np.array([[1.0 + 0.01 * k, 1.0, math.radians(-135)] for k in range(80)])
    landmarks, _ = labelled_pings(CORNER_ROOM, truth)
    huge = np.diag([1e200, 1e200, 1.0])
    bad = {50: huge, 55: np.full((3, 3), np.nan), 60: np.array([[1e-4, 1e-5, 0.0], [0.0, 1e-4, 0.0], [0.0, 0.0, 1e-4]]),
           65: np.diag([-1e-6, 1e-6, 1e-6])}
    health = Counts()
    builder = MapBuilder(MapperSettings(layout=RING, echo_tests=EchoTests(refresh_pings=1)), health)
    for k, (found, pose) in enumerate(zip(landmarks, truth, strict=True)):
        stamp = int(1e9 + k * 1e9 / RING.ping_rate)
        builder.add_odometry(stamp, pose, bad.get(k, 1e-6 * (k + 1) * np.eye(3)))
        assert builder.add_ping(stamp, found)
    assert dict(health.problems) == {"bad_odometry_covariance": 4}
    assert health.notes["multipath explained"] + health.notes["impossible"] > 0 or len(builder.snapshot()) > 0
    slam = LandmarkSlam()
    for k, (found, pose) in enumerate(zip(landmarks, truth, strict=True)):
        slam.add_ping(found, pose, k / RING.ping_rate, odometry_covariance=huge if k >= 40 else np.eye(3) * 1e-6 * k)
        assert np.all(np.isfinite(slam.pose_at(pose, huge)[1]))


def test_the_yaw_of_a_quaternion_that_is_not_a_rotation_is_nan():
    """An odometry orientation left unset (all zeros), garbled or not finite gives no yaw, where it gave a wrong
    one (or, a component near 1e200, raised OverflowError in the mapper's odometry callback)."""
    def quaternion(x, y, z, w):
        return SimpleNamespace(x=x, y=y, z=z, w=w)

    for yaw in (-3.0, -0.4, 0.0, 1.2, math.pi):
        assert yaw_of(quaternion(0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))) == pytest.approx(yaw, abs=1e-12)
    for yaw in np.linspace(-3.1, 3.1, 21):  # within the tolerance, the yaw is off by about as much
        scale = math.sqrt(1.0 + 0.9 * QUATERNION_NORM_TOLERANCE)
        assert yaw_of(quaternion(0.0, 0.0, scale * math.sin(yaw / 2), scale * math.cos(yaw / 2))) \
            == pytest.approx(yaw, abs=QUATERNION_NORM_TOLERANCE)
    for bad in [(0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 1e200, 1.0), (0.0, 0.0, math.inf, 1.0), (math.nan, 0.0, 0.0, 1.0),
                (0.0, 0.0, 0.0, 1.001), (1e-200, 1e-200, 1e-200, 1e-200)]:
        assert math.isnan(yaw_of(quaternion(*bad))), bad


def test_error_handling():
    slam = LandmarkSlam()
    report = slam.add_ping(Landmarks.empty(), (0.0, 0.0, 0.0), 0.0)
    assert report.keyframe and not report.fault
    with pytest.raises(TypeError):
        SlamSettings(keyframe_distance=0.1, unknown=1)
    health = Counts()
    builder = MapBuilder(MapperSettings(), health)
    builder.add_odometry(10, (math.nan, 0.0, 0.0))
    builder.add_ping(10, Landmarks.empty())
    assert health.problems["not_finite_pose"] == 1
    sightings = (np.zeros(3), np.eye(3), np.ones((2, 2)), np.tile(np.eye(2), (2, 1, 1)), np.zeros(2, bool),
                 np.ones((2, 2)), np.ones((2, 2)))
    assert consistent_sightings(*sightings, 4.0).all()
    with pytest.raises(ValueError, match="covariance must have shape"):
        consistent_sightings(*sightings[:3], np.eye(2), *sightings[4:], 4.0)
    with pytest.raises(ValueError, match="chi2 must be a positive number"):
        consistent_sightings(*sightings, float("nan"))


def test_a_landmark_unseen_for_longer_than_the_lag_is_still_there_when_seen_again():
    # A short lag: the keyframes of the first sightings are marginalised while nothing is seen.
    truth = np.array([[1.0 + 0.01 * k, 1.0, math.radians(-135)] for k in range(60)])
    landmarks, _ = labelled_pings(CORNER_ROOM, truth)
    slam = LandmarkSlam(SlamSettings(smoother_lag=1.0))
    time = 0.0
    for found, pose in zip(landmarks[:40], truth[:40], strict=True):
        slam.add_ping(found, pose, time)
        time += 1 / RING.ping_rate
    confirmed = set(slam.confirmed.tolist())
    for k in range(90):  # 3 s of travel with nothing heard, 13.5 cm on and back
        slam.add_ping(Landmarks.empty(), compose(truth[40], (0.003 * min(k, 90 - k), 0.0, 0.0)), time)
        time += 1 / RING.ping_rate
    for k, found in enumerate(landmarks[40:]):  # back where it was, seeing the corner again
        report = slam.add_ping(found, truth[40 + k], time)
        time += 1 / RING.ping_rate
    assert confirmed <= set(slam.confirmed.tolist()) and report.associated > 0
    assert len(confirmed) >= 2 and len(slam.snapshot()) >= len(confirmed)
