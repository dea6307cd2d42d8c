"""Echoes the map explains (sonar_ring.explain): double bounces predicted by the image method from the map's
walls and points, multipath labelled in the realistic world, and landmarks that cannot be where they are."""

import dataclasses
import math

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from scipy.optimize import minimize

from sonar_ring import explain, image_method, pipeline, simulate
from sonar_ring.benchmark import worlds
from sonar_ring.explain import MULTIPATH, NONE, Tolerance, facing, impossible, match, predict, reflection_points
from sonar_ring.geometry import load_layout
from sonar_ring.image_method import KIND_NAMES, POINT, POINT_WALL, WALL, WALL_POINT, WALL_WALL
from sonar_ring.landmarks import CORNER, EDGE, PLANE, make_landmarks
from sonar_ring.mapping import transform_landmarks
from sonar_ring.ping_stage import PingStage
from sonar_ring.realism import REALISTIC, World, multipath_paths
from sonar_ring.simulate import DIRECT, Noise, Simulator, load_scene, place

RING = load_layout("browne_ring")
ROOM = load_scene("room")
SIGMA_PATH = 1e-6 * ROOM.speed_of_sound  # 1 us of TOF noise
EXACT = Tolerance(sigma_path=SIGMA_PATH)
ROWS = np.arange(RING.n_groups)
SLOT = np.zeros(RING.n_groups, dtype=int)

# A hand-built room: 5 x 4 m, a 0.8 m doorway in the north wall, a partition from the south wall, a pole.
HAND_WALLS = np.array([
    [[0.0, 0.0], [5.0, 0.0]], [[5.0, 0.0], [5.0, 4.0]], [[5.0, 4.0], [2.8, 4.0]], [[2.0, 4.0], [0.0, 4.0]],
    [[0.0, 4.0], [0.0, 0.0]], [[3.5, 0.0], [3.5, 1.5]], [[1.0, 5.0], [4.0, 5.0]]])
HAND_POINTS = np.array([[1.6, 2.4], [3.5, 1.5], [2.0, 4.0], [2.8, 4.0]])
UNCERTAIN = Tolerance(sigma_path=SIGMA_PATH, pose_covariance=np.diag([0.02 ** 2, 0.02 ** 2, math.radians(0.5) ** 2]),
                      sigma_map=0.005)


def _room_map():
    """The room as a map: its walls, and its edges and corners as points."""
    return ROOM.walls, np.vstack([ROOM.edges, ROOM.corner_point])


def _inside_hand_room(rng, count):
    poses = []
    while len(poses) < count:
        x, y = rng.uniform(0.5, 4.5), rng.uniform(0.5, 3.5)
        if not (3.0 < x < 4.0 and y < 2.0) and math.hypot(x - 1.6, y - 2.4) > 0.5:
            poses.append([x, y, rng.uniform(-math.pi, math.pi)])
    return np.array(poses)


def _inside_room(rng, count):
    poses = []
    while len(poses) < count:
        x, y = rng.uniform(0.3, 5.7), rng.uniform(0.3, 4.2)
        if not (3.2 < x < 4.0 and 1.8 < y < 2.6):
            poses.append([x, y, rng.uniform(-math.pi, math.pi)])
    return np.array(poses)


# --------------------------------------------------------------------------- the image method


def _fermat(start, end, bounces):
    """Shortest 3-D path from ``start`` to ``end`` (x, y, z) touching each bounce in order: a vertical wall
    ``(2, 2)`` anywhere on its plane, or a vertical line ``(2,)``; minimised over where (along, height)."""

    def through(x):
        stops, i = [start], 0
        for bounce in bounces:
            if bounce.shape == (2, 2):
                stops.append(np.array([*(bounce[0] + x[i] * (bounce[1] - bounce[0])), x[i + 1]]))
                i += 2
            else:
                stops.append(np.array([*bounce, x[i]]))
                i += 1
        stops.append(end)
        return sum(np.linalg.norm(b - a) for a, b in zip(stops[:-1], stops[1:], strict=True)), stops

    best = None
    for along in (0.25, 0.5, 0.75):
        guess = np.concatenate([[along, start[2]] if b.shape == (2, 2) else [start[2]] for b in bounces])
        result = minimize(lambda x: through(x)[0], guess, method="BFGS", options={"gtol": 1e-13, "xrtol": 1e-15})
        if best is None or result.fun < best.fun:
            best = result
    return best.fun, through(best.x)[1], best.x


def _bounces(kind, first, second, walls, points):
    if kind == WALL_WALL:
        return [walls[first], walls[second]]
    return [walls[first], points[second]] if kind == WALL_POINT else [points[first], walls[second]]


def _transducers_3d(layout, placement, group, slot, receiver):
    tx = layout.transmitters[layout.group_transmitters[group, slot]]
    rx = layout.receivers[layout.groups[group, receiver]]
    return (np.array([*placement.tx[group, slot], tx[2]]), np.array([*placement.rx[group, receiver], rx[2]]))


def test_each_predicted_double_bounce_is_the_shortest_path_by_fermat_within_1e_9_m():
    rng = np.random.default_rng(1)
    checked = dict.fromkeys(KIND_NAMES[:3], 0)
    for pose in _inside_hand_room(rng, 6):
        placement = place(RING, pose)
        prediction = predict(HAND_WALLS, HAND_POINTS, placement, RING, ROWS, SLOT, EXACT)
        double = np.flatnonzero(prediction.kind <= POINT_WALL)
        for q in double[::7]:
            for k in np.flatnonzero(np.isfinite(prediction.path[q])):
                start, end = _transducers_3d(RING, placement, prediction.group[q], prediction.slot[q], k)
                bounces = _bounces(prediction.kind[q], prediction.first[q], prediction.second[q], HAND_WALLS,
                                   HAND_POINTS)
                length, stops, _ = _fermat(start, end, bounces)
                assert abs(prediction.path[q, k] - length) < 1e-9, (KIND_NAMES[prediction.kind[q]], length)
                # The bounces lie on the segments, where the prediction put them.
                assert_allclose(prediction.first_point[q, k], stops[1][:2], atol=1e-6)
                assert_allclose(prediction.last_point[q, k], stops[-2][:2], atol=1e-6)
                for bounce, stop in zip(bounces, stops[1:-1], strict=True):
                    if bounce.shape == (2, 2):
                        along = (stop[:2] - bounce[0]) @ (bounce[1] - bounce[0]) / np.sum((bounce[1] - bounce[0]) ** 2)
                        assert -1e-9 <= along <= 1 + 1e-9
                checked[KIND_NAMES[prediction.kind[q]]] += 1
    assert min(checked.values()) >= 5, checked


def test_single_bounces_are_the_forward_models_echoes():
    """The reflectors' own echoes the prediction holds beside the double bounces are the simulator's."""
    simulator = Simulator(ROOM, RING)
    for pose in ([2.4, 1.3, 0.4], [4.6, 3.0, 2.0]):
        echoes = simulator.ping(pose)
        placement = place(RING, pose)
        prediction = predict(ROOM.walls, ROOM.edges, placement, RING, ROWS, SLOT, EXACT)
        for n in range(echoes.n_echoes):
            reflector = echoes.truth_reflector[n]
            if echoes.truth_class[n] not in (PLANE, EDGE):
                continue
            kind = WALL if echoes.truth_class[n] == PLANE else POINT
            rows = np.flatnonzero((prediction.kind == kind) & (prediction.first == ROOM.kind_index[reflector])
                                  & (prediction.group == echoes.group[n]))
            assert rows.size == 1
            heard = np.isfinite(echoes.tof[n])
            assert_allclose(prediction.path[rows[0], heard], echoes.tof[n, heard] * echoes.speed_of_sound, rtol=1e-13)


def _world_paths(simulator, placement):
    """The realistic world's multipath paths the ring hears, (kind, first, second, group, slot, receiver) -> m."""
    families = multipath_paths(simulator, placement, 0.5, 0)
    scene = simulator.scene
    walls = len(scene.walls)
    corner = np.zeros((walls, walls), dtype=bool)
    corner[scene.corner_walls[:, 0], scene.corner_walls[:, 1]] = True
    corner |= corner.T
    pairs = np.nonzero(~corner & ~np.eye(walls, dtype=bool))
    offsets = np.abs(np.einsum("wej,wj->we", scene.edges[None] - simulator.wall_start[:, None],
                               simulator.wall_normal))
    wall, edge = np.nonzero(offsets > 1e-6)
    members = [(WALL_WALL, *pairs), (WALL_POINT, wall, edge), (POINT_WALL, edge, wall)]
    heard = {}
    for family, (kind, first, second) in zip(families, members, strict=True):
        paths = simulator.hear(family, placement)
        member = paths.source - family.source[0]
        for m, g, s, k, length in zip(member, paths.group, paths.slot, paths.receiver, paths.path, strict=True):
            heard[kind, first[m], second[m], g, s, k] = length
    return heard


def _predicted_paths(prediction, kinds=(WALL_WALL, WALL_POINT, POINT_WALL)):
    paths = {}
    for q in np.flatnonzero(np.isin(prediction.kind, kinds)):
        for k in np.flatnonzero(np.isfinite(prediction.path[q])):
            key = (prediction.kind[q], prediction.first[q], prediction.second[q], prediction.group[q],
                   prediction.slot[q], k)
            paths[key] = prediction.path[q, k]
    return paths


def test_with_the_scene_as_map_the_prediction_is_the_realistic_worlds_multipath():
    simulator = Simulator(ROOM, RING)
    rng = np.random.default_rng(2)
    compared = 0
    for pose in ROOM.trajectory.poses(RING.ping_rate)[1][::97]:
        pose = pose + [0.0, 0.0, rng.uniform(-math.pi, math.pi)]
        world = _world_paths(simulator, simulator.place(pose))
        predicted = _predicted_paths(predict(ROOM.walls, ROOM.edges, place(RING, pose), RING, ROWS, SLOT, EXACT))
        assert set(predicted) == set(world)
        for key, length in world.items():
            assert predicted[key] == length  # the same code: the same number
        compared += len(world)
    assert compared > 1000


def test_a_wall_blocks_where_it_was_seen_if_seen_as_often_as_the_paths_reflectors():
    # A ghost wall seen over half a metre by the east wall, grown across the room to a fixed point it met: it
    # reflects along its grown length, but blocks only where it was seen, and only paths whose reflectors it was
    # seen as often as -- so the room's own double bounces (the ones that explain the ghost) stay predicted.
    ghost = len(ROOM.walls)
    grown, seen = [[0.3, 1.0], [5.7, 1.0]], [[5.2, 1.0], [5.7, 1.0]]
    walls = np.concatenate([ROOM.walls, [grown]])
    points = ROOM.edges

    def by_the_room(prediction):
        return {key: length for key, length in _predicted_paths(prediction).items()
                if ghost not in ((key[1], key[2]) if key[0] == WALL_WALL else (key[1],) if key[0] == WALL_POINT
                                 else (key[2],))}

    def support(ghost_support):
        return {"wall_support": np.r_[np.full(len(ROOM.walls), 1000.0), ghost_support],
                "point_support": np.full(len(points), 1000.0)}

    hidden = {"grown": 0, "seen grown, as often": 0}
    rng = np.random.default_rng(6)
    for x, y in zip(rng.uniform(0.5, 3.0, 12), rng.uniform(2.8, 4.2, 12), strict=True):
        placement = place(RING, [x, y, rng.uniform(-math.pi, math.pi)])
        room = by_the_room(predict(ROOM.walls, points, placement, RING, ROWS, SLOT, EXACT))
        where_seen = by_the_room(predict(walls, points, placement, RING, ROWS, SLOT, EXACT,
                                         seen=np.concatenate([ROOM.walls, [seen]])))
        seen_less = by_the_room(predict(walls, points, placement, RING, ROWS, SLOT, EXACT, **support(999.0)))
        assert where_seen == room and seen_less == room
        for case, prediction in (("grown", predict(walls, points, placement, RING, ROWS, SLOT, EXACT)),
                                 ("seen grown, as often",
                                  predict(walls, points, placement, RING, ROWS, SLOT, EXACT, **support(1000.0)))):
            paths = by_the_room(prediction)
            assert set(paths) <= set(room)
            hidden[case] += len(room) - len(paths)
    assert min(hidden.values()) > 100  # what the ghost wall hides where it blocks


@pytest.mark.parametrize("tolerance", [EXACT, UNCERTAIN], ids=["exact", "uncertain"])
def test_pruning_drops_no_path_that_exists(tolerance):
    """On random poses in the room, with walls seen shorter than they are and extra points, pruned and unpruned
    predictions are the same, path for path (and so are those near the rows of a ping)."""
    rng = np.random.default_rng(3)
    walls, points = _room_map()
    walls = walls.copy()
    walls[:, 0] += rng.uniform(0.0, 0.3, (len(walls), 1)) * (walls[:, 1] - walls[:, 0])  # seen extents
    points = np.vstack([points, np.column_stack([rng.uniform(0.2, 5.8, 10), rng.uniform(0.2, 4.3, 10)])])
    world = World(ROOM, RING, REALISTIC.only("multipath"), noise=Noise(tof=1e-6), seed=3)
    total = 0
    for pose in _inside_room(rng, 12):
        placement = place(RING, pose)
        ping = world.ping(pose, 0.0)
        measured = ping.tof * ping.speed_of_sound
        for paths in (None, measured):
            group = ROWS if paths is None else ping.group
            slot = SLOT if paths is None else ping.transmitter
            pruned = predict(walls, points, placement, RING, group, slot, tolerance, paths=paths)
            everything = predict(walls, points, placement, RING, group, slot, tolerance, paths=paths, prune=False)
            for name in ("group", "slot", "kind", "first", "second", "path", "jacobian", "first_point",
                         "last_point", "channel_start"):
                assert_array_equal(getattr(pruned, name), getattr(everything, name), err_msg=name)
            total += len(pruned)
    assert total > 2000


def test_the_filters_by_the_rows_drop_no_path_a_row_matches():
    """Predicting near the rows (lengths, differences between receivers: pass 1 of ``map_paths``) gives every row the
    same matches as predicting every path, at poses off by 1.5 cm per axis and 0.4 deg (standard deviations; SLAM's
    own uncertainty in the realistic room is 2.1 cm and 0.58 deg)."""
    rng = np.random.default_rng(5)
    walls, points = _room_map()
    world = World(ROOM, RING, REALISTIC.only("multipath"), noise=Noise(tof=1e-6), seed=5)
    gate = UNCERTAIN.gate_sigmas
    matched = 0
    for pose in _inside_room(rng, 12):
        ping = world.ping(pose, 0.0)
        measured = ping.tof * ping.speed_of_sound
        guess = pose + np.concatenate([rng.normal(0.0, 0.015, 2), rng.normal(0.0, math.radians(0.4), 1)])
        placement = place(RING, guess)
        near = predict(walls, points, placement, RING, ping.group, ping.transmitter, UNCERTAIN, paths=measured)
        every = predict(walls, points, placement, RING, ping.group, ping.transmitter, UNCERTAIN)
        found = [match(prediction, RING, ping.group, ping.transmitter, measured, UNCERTAIN)
                 for prediction in (near, every)]
        for name in ("residual", "direct_residual"):
            within = [np.where(getattr(f, name) <= gate, getattr(f, name), np.inf) for f in found]
            assert_array_equal(*within, err_msg=name)
        assert_array_equal(found[0].label, found[1].label)
        assert_array_equal(found[0].double_support, found[1].double_support)
        matched += int(np.count_nonzero(found[0].residual <= gate))
    assert matched > 100


def test_a_corners_double_bounce_and_a_walls_end_are_not_multipath():
    """Walls that meet are a corner, whose double bounce is the corner's own echo; a point on a wall is its end."""
    placement = place(RING, [2.5, 1.5, 0.3])
    prediction = predict(HAND_WALLS, HAND_POINTS, placement, RING, ROWS, SLOT, EXACT)
    pairs = {(a, b) for kind, a, b in zip(prediction.kind, prediction.first, prediction.second, strict=True)
             if kind == WALL_WALL}
    assert (0, 4) not in pairs and (4, 0) not in pairs and (0, 1) not in pairs  # the room's corners
    assert (5, 0) not in pairs and (0, 5) not in pairs  # the partition meets the south wall
    assert pairs  # but other pairs bounce
    on_wall = {(a, p) for kind, a, p in zip(prediction.kind, prediction.first, prediction.second, strict=True)
               if kind == WALL_POINT}
    assert (5, 1) not in on_wall and (3, 2) not in on_wall  # the partition's end, the door jamb on its wall


# --------------------------------------------------------------------------- multipath in the realistic world


def _labels(pose_error, tolerance, step=6):
    """Labels of a lap of the realistic world with multipath (1 us TOF noise), the room as the map, the pose
    given with an error drawn by ``pose_error(rng)``.  Returns the counts of (origin, label)."""
    walls, points = _room_map()
    world = World(ROOM, RING, REALISTIC.only("multipath"), noise=Noise(tof=1e-6, amplitude=0.02), seed=4)
    times, poses = ROOM.trajectory.poses(RING.ping_rate)
    rng = np.random.default_rng(4)
    counts = {"multipath": 0, "labelled": 0, "direct_also": 0, "direct": 0, "false": 0}
    for k, (time, pose) in enumerate(zip(times, poses, strict=True)):
        ping = world.ping(pose, time)
        if k % step:
            continue
        placement = place(RING, pose + pose_error(rng))
        measured = ping.tof * ping.speed_of_sound
        prediction = predict(walls, points, placement, RING, ping.group, ping.transmitter, tolerance, paths=measured)
        explained = match(prediction, RING, ping.group, ping.transmitter, measured, tolerance)
        multipath = ping.truth_origin == simulate.MULTIPATH
        labelled = explained.label == MULTIPATH
        counts["multipath"] += np.count_nonzero(multipath)
        counts["labelled"] += np.count_nonzero(multipath & labelled)
        counts["direct_also"] += np.count_nonzero(multipath & ~labelled
                                                  & (explained.direct_residual <= tolerance.gate_sigmas))
        counts["direct"] += np.count_nonzero(ping.truth_origin == DIRECT)
        counts["false"] += np.count_nonzero((ping.truth_origin == DIRECT) & labelled)
    return counts


def test_multipath_echoes_are_labelled_and_real_echoes_are_not_with_an_exact_pose():
    counts = _labels(lambda rng: np.zeros(3), EXACT)
    # Measured: recall 99.5 %, no false positive (the rest of the multipath echoes are as long as a mapped
    # reflector's own echo -- a pole on the line of sight to a wall -- and are left to the mapper).
    assert counts["labelled"] / counts["multipath"] >= 0.99, counts
    assert (counts["labelled"] + counts["direct_also"]) / counts["multipath"] >= 0.999, counts
    assert counts["false"] / counts["direct"] <= 0.001, counts
    assert counts["multipath"] > 5000 and counts["direct"] > 1500


def test_multipath_echoes_are_labelled_with_a_pose_error_of_1_to_2_cm_and_half_a_degree_given_as_uncertainty():
    def pose_error(rng):
        angle = rng.uniform(-math.pi, math.pi)
        return np.array([*(rng.uniform(0.01, 0.02) * np.array([math.cos(angle), math.sin(angle)])),
                         rng.choice([-1, 1]) * math.radians(0.5)])

    tolerance = Tolerance(sigma_path=SIGMA_PATH, pose_covariance=np.diag([0.015 ** 2, 0.015 ** 2,
                                                                          math.radians(0.5) ** 2]))
    counts = _labels(pose_error, tolerance)
    # Measured: recall 97 %; 3 % more as long as a mapped reflector's own echo within the wider gate; no false
    # positive.
    assert counts["labelled"] / counts["multipath"] >= 0.95, counts
    assert (counts["labelled"] + counts["direct_also"]) / counts["multipath"] >= 0.995, counts
    assert counts["false"] / counts["direct"] <= 0.001, counts


def test_the_match_is_the_mahalanobis_distance_of_the_documented_covariance():
    rng = np.random.default_rng(6)
    tolerance = Tolerance(sigma_path=SIGMA_PATH, pose_covariance=np.array([[4e-4, 1e-5, 2e-5], [1e-5, 1e-4, 0.0],
                                                                          [2e-5, 0.0, 1e-4]]),
                          sigma_speed=0.003, sigma_map=0.004)
    placement = place(RING, [2.0, 2.0, 0.5])
    prediction = predict(HAND_WALLS, HAND_POINTS, placement, RING, ROWS, SLOT, tolerance)
    double = np.flatnonzero((prediction.kind <= POINT_WALL) & np.isfinite(prediction.path).all(axis=1))[:20]
    measured = prediction.path[double] + rng.normal(0.0, 0.005, (double.size, 2))
    explained = match(prediction, RING, prediction.group[double], prediction.slot[double], measured, tolerance)
    for n, q in enumerate(double):
        if explained.best[n] != q:
            continue  # another path of the channel is closer
        d, jacobian = prediction.path[q], prediction.jacobian[q]
        covariance = (SIGMA_PATH ** 2 * np.eye(2) + jacobian @ tolerance.pose_covariance @ jacobian.T
                      + 0.003 ** 2 * np.outer(d, d) + 8 * 0.004 ** 2)
        error = measured[n] - d
        assert explained.residual[n] == pytest.approx(math.sqrt(error @ np.linalg.solve(covariance, error)), rel=1e-9)


def test_the_pose_derivative_is_the_paths_change_with_the_pose():
    pose = np.array([2.2, 1.7, 0.8])
    prediction = predict(HAND_WALLS, HAND_POINTS, place(RING, pose), RING, ROWS, SLOT, EXACT)
    double = np.flatnonzero((prediction.kind <= POINT_WALL) & np.isfinite(prediction.path).all(axis=1))
    for axis, step in enumerate((1e-6, 1e-6, 1e-7)):
        moved = predict(HAND_WALLS, HAND_POINTS, place(RING, pose + np.eye(3)[axis] * step), RING, ROWS, SLOT, EXACT)
        after = _predicted_paths(moved)
        for q in double:
            for k in range(2):
                key = (prediction.kind[q], prediction.first[q], prediction.second[q], prediction.group[q], 0, k)
                if key in after:
                    assert (after[key] - prediction.path[q, k]) / step == pytest.approx(
                        prediction.jacobian[q, k, axis], abs=1e-5)


def _one_channel_prediction(kinds, firsts, seconds, supports, paths):
    """A hand-built prediction: paths of group 0, transmitter 0 only, the same length to every receiver."""
    count, receivers = len(kinds), RING.receivers_per_group
    channel_start = np.full(RING.n_groups * RING.group_transmitters.shape[1] + 1, count)
    channel_start[0] = 0
    return explain.Prediction(
        group=np.zeros(count, np.int64), slot=np.zeros(count, np.int64), kind=np.array(kinds, np.int64),
        first=np.array(firsts, np.int64), second=np.array(seconds, np.int64), support=np.array(supports, float),
        path=np.repeat(np.array(paths, float)[:, None], receivers, axis=1), jacobian=np.zeros((count, receivers, 3)),
        first_point=np.zeros((count, receivers, 2)), last_point=np.zeros((count, receivers, 2)),
        channel_start=channel_start)


def _multipath_rows(prediction, explanation, gate_sigmas, echo, paths):
    """image_method.multipath_rows (the rule explain_landmarks applies) of a prediction and its match."""
    return image_method.multipath_rows(prediction.kind, prediction.first, prediction.second, prediction.support,
                                       explanation.best, explanation.residual, explanation.direct,
                                       explanation.direct_residual, explanation.double_support, echo, paths,
                                       gate_sigmas)


def test_an_entrys_own_echo_is_multipath_where_a_double_bounce_of_better_seen_entries_within_the_gate_explains_it():
    # Entry X (wall 0, seen 150 times) explains the echo; so do a double bounce off X itself (the closest) and one
    # off walls 1 and 2, 1 mm longer: still within the gate of 3 mm of path noise.
    tolerance = Tolerance(sigma_path=3e-3)
    echo = np.full((1, RING.receivers_per_group), 4.0)

    def multipath(second_support, rival_path):
        prediction = _one_channel_prediction(
            [WALL, WALL_WALL, WALL_WALL], [0, 0, 1], [0, 1, 2], [150, 150, second_support],
            [4.0, 4.0, rival_path])
        explanation = match(prediction, RING, [0], [0], echo, tolerance, direct_wins=False)
        return explanation, _multipath_rows(prediction, explanation, tolerance.gate_sigmas, np.zeros(1, np.int64),
                                            echo)[0]

    explanation, is_multipath = multipath(200, 4.001)
    assert explanation.best[0] == 1 and explanation.direct[0] == 0  # the closest double bounce is off X
    assert explanation.double_support[0] == 200 and is_multipath  # the better seen one explains it
    assert not multipath(100, 4.001)[1]  # seen less than X: X's own echo
    explanation, is_multipath = multipath(200, 4.1)  # beyond the gate: only the double bounce off X
    assert explanation.double_support[0] == 150 and not is_multipath
    # No double bounce within the gate: -inf.
    far = _one_channel_prediction([WALL, WALL_WALL], [0, 1], [0, 2], [150, 500], [4.0, 4.5])
    assert match(far, RING, [0], [0], echo, tolerance).double_support[0] == -np.inf


def test_an_echo_later_than_an_entrys_own_by_a_double_bounce_off_the_entry_is_that_double_bounce():
    # Wall X (entry 0, seen 150 times) and its echo by way of an edge seen less (100), 20 mm longer: with 10 mm of
    # path noise (a pose known to about 2 cm) each of the ping's two echoes is within the gate of both paths.
    # X sends one echo to the channel, the closer; the later one is the double bounce off X.
    tolerance = Tolerance(sigma_path=1e-2)
    echoes = np.repeat(np.array([[4.0], [4.02]]), RING.receivers_per_group, axis=1)

    def multipath(kinds, firsts, seconds, predicted, rows=(0, 1)):
        prediction = _one_channel_prediction(kinds, firsts, seconds, [150, 100], predicted)
        paths = echoes[list(rows)]
        explanation = match(prediction, RING, [0] * len(rows), [0] * len(rows), paths, tolerance, direct_wins=False)
        assert (explanation.direct_residual <= tolerance.gate_sigmas).all()
        assert (explanation.residual <= tolerance.gate_sigmas).all()
        return _multipath_rows(prediction, explanation, tolerance.gate_sigmas, np.array(rows) + 7, paths)

    by_the_edge = ([WALL, WALL_POINT], [0, 0], [0, 1])
    assert_array_equal(multipath(*by_the_edge, [4.0, 4.02]), [False, True])
    assert_array_equal(multipath(*by_the_edge, [4.0, 4.02], rows=(1, 0)), [True, False])  # in any order
    assert_array_equal(multipath(*by_the_edge, [4.0, 4.02], rows=(1,)), [False])  # alone: X's, seen more
    # The closer echo is the later one: the earlier cannot be a double bounce off X.
    assert_array_equal(multipath(*by_the_edge, [4.015, 4.025]), [False, False])
    # A double bounce of other entries (walls 1 and 2) is not X's echo by way of something: X's own echo wins.
    assert_array_equal(multipath([WALL, WALL_WALL], [0, 1], [0, 2], [4.0, 4.02]), [False, False])


# --------------------------------------------------------------------------- impossible


def _one_group_facing(pose, target):
    """The ring's group facing ``target`` from ``pose``."""
    bearing = math.atan2(target[1] - pose[1], target[0] - pose[0]) - pose[2]
    return int(round(bearing / (2 * math.pi / RING.n_groups))) % RING.n_groups


def test_a_point_behind_a_wall_is_impossible_and_one_seen_through_a_doorway_is_not():
    pose = np.array([2.4, 2.0, 0.0])
    placement = place(RING, pose)
    walls, _ = _room_map()
    normals = facing(walls, pose[:2])  # a map of the room seen from here
    cases = {  # point: impossible?
        (1.0, 5.0): True,  # behind the north wall's west part
        (2.45, 5.7): False,  # on the corridor wall, through the doorway
        (5.0, 2.2): True,  # behind the pillar
        (0.0, 1.0): False,  # on the west wall: the wall it lies on is no crossing
        (6.0, 4.5): False,  # the north-east corner, where two walls end
        (2.0, 4.5): False,  # the west door jamb, a wall's end
    }
    for point, expected in cases.items():
        group = _one_group_facing(pose, point)
        points = np.full((1, 2, 2), point)
        assert impossible(points, placement, RING, [group], [0], walls, normals, 0.005)[0] == expected, point


def test_a_plane_seen_through_a_doorway_and_one_on_its_own_wall_are_possible():
    pose = np.array([2.45, 3.0, math.pi / 2])
    placement = place(RING, pose)
    walls, _ = _room_map()
    group = 0  # facing north, through the doorway to the corridor wall at y = 5.7
    corridor = make_landmarks([PLANE], [[2.45, 5.7]], normal=[[0.0, -1.0]], group=[group])
    points = reflection_points(corridor, placement, RING, [0])
    assert np.all(np.abs(points[..., 1] - 5.7) < 1e-12) and np.all((2.0 < points[..., 0]) & (points[..., 0] < 2.9))
    assert not impossible(points, placement, RING, [group], [0], walls, facing(walls, pose[:2]), 0.005)[0]
    # The same plane seen where the north wall stands in the way is impossible.
    beside = place(RING, [1.0, 3.0, math.pi / 2])
    shifted = make_landmarks([PLANE], [[1.0, 5.7]], normal=[[0.0, -1.0]], group=[group])
    assert impossible(reflection_points(shifted, beside, RING, [0]), beside, RING, [group], [0], walls,
                      facing(walls, [1.0, 3.0]), 0.005)[0]
    # A plane on its own mapped wall, 1 mm behind it (noise): possible within the margin, not without it.
    east = make_landmarks([PLANE], [[6.001, 3.0]], normal=[[-1.0, 0.0]], group=[_one_group_facing(pose, (6, 3))])
    points = reflection_points(east, placement, RING, [0])
    assert not impossible(points, placement, RING, east.group, [0], walls, facing(walls, pose[:2]), 0.005)[0]
    assert impossible(points, placement, RING, east.group, [0], walls, facing(walls, pose[:2]), 0.0)[0]


def test_a_point_heard_through_a_wall_from_behind_it_is_not_impossible():
    # A plane mapped at y = 3.0 seen from the south (a double bounce between the pillar's south face and the
    # south wall looks like one from y = 1): from y = 3.4 the pillar's north face at y = 2.4 lies behind it.
    wall = np.array([[[3.35, 3.0], [3.85, 3.0]]])
    pose = np.array([3.6, 3.4, 0.0])
    placement = place(RING, pose)
    face = make_landmarks([PLANE], [[3.6, 2.4]], normal=[[0.0, 1.0]], group=[_one_group_facing(pose, (3.6, 2.4))])
    points = reflection_points(face, placement, RING, [0])
    seen_from_south, seen_from_north = [[0.0, -1.0]], [[0.0, 1.0]]
    assert not impossible(points, placement, RING, face.group, [0], wall, seen_from_south, 0.005)[0]
    assert impossible(points, placement, RING, face.group, [0], wall, seen_from_north, 0.005)[0]
    # Any length of normal is its direction.
    assert impossible(points, placement, RING, face.group, [0], wall, [[0.0, 7.0]], 0.005)[0]


def test_reflection_points_of_planes_are_where_the_forward_model_reflects():
    simulator = Simulator(ROOM, RING)
    pose = np.array([2.4, 1.3, 0.4])
    echoes = simulator.ping(pose)
    planes = np.flatnonzero(echoes.truth_class == PLANE)
    rotation = np.array([[math.cos(pose[2]), -math.sin(pose[2])], [math.sin(pose[2]), math.cos(pose[2])]])
    landmarks = make_landmarks(np.full(planes.size, PLANE), echoes.truth_position[planes] @ rotation.T + pose[:2],
                               normal=echoes.truth_normal[planes] @ rotation.T, group=echoes.group[planes])
    points = reflection_points(landmarks, place(RING, pose), RING, echoes.transmitter[planes])
    truth = echoes.truth_reflection_point[planes] @ rotation.T + pose[:2]
    heard = np.isfinite(truth)
    assert_allclose(points[heard], truth[heard], atol=1e-12)
    corners = make_landmarks([CORNER], [[6.0, 0.0]], group=[3])
    assert_array_equal(reflection_points(corners, place(RING, pose), RING, [0]), [[[6.0, 0.0], [6.0, 0.0]]])


# --------------------------------------------------------------------------- errors


def test_error_handling():
    placement = place(RING, [2.0, 2.0, 0.0])
    walls, points = _room_map()
    normals = facing(walls, [2.0, 2.0])
    one = np.zeros(1, dtype=int)
    with pytest.raises(ValueError, match="walls must have shape"):
        predict(walls[:, 0], points, placement, RING, one, one, EXACT)
    with pytest.raises(ValueError, match="points must have shape"):
        predict(walls, points.T, placement, RING, one, one, EXACT)
    with pytest.raises(ValueError, match="seen must have shape"):
        predict(walls, points, placement, RING, one, one, EXACT, seen=walls[:, 0])
    with pytest.raises(ValueError, match="seen must have the shape of walls"):
        predict(walls, points, placement, RING, one, one, EXACT, seen=walls[:2])
    with pytest.raises(ValueError, match=r"point_support must have shape \(11,\)"):
        predict(walls, points, placement, RING, one, one, EXACT, point_support=np.ones(3))
    with pytest.raises(ValueError, match="group must be in 0..47"):
        predict(walls, points, placement, RING, [48], [0], EXACT)
    with pytest.raises(ValueError, match="transmitter 1 is not one of group 0"):
        predict(walls, points, placement, RING, [0], [1], EXACT)
    with pytest.raises(ValueError, match="1-D and of one length"):
        predict(walls, points, placement, RING, [0, 1], [0], EXACT)
    with pytest.raises(ValueError, match="must be integers"):
        predict(walls, points, placement, RING, [0.0], [0], EXACT)
    with pytest.raises(ValueError, match="paths must have shape"):
        predict(walls, points, placement, RING, one, one, EXACT, paths=np.ones((2, 2)))
    with pytest.raises(ValueError, match="placement is of another layout"):
        predict(walls, points, place(load_layout("kreczmer_triad"), [2.0, 2.0, 0.0]), RING, one, one, EXACT)
    prediction = predict(walls, points, placement, RING, one, one, EXACT)
    with pytest.raises(ValueError, match="paths must have shape"):
        match(prediction, RING, one, one, np.ones(2), EXACT)
    with pytest.raises(ValueError, match="prediction is of another layout"):
        match(prediction, load_layout("barshan_kuc_pair"), one, one, np.ones((1, 2)), EXACT)
    with pytest.raises(ValueError, match="points must have shape"):
        impossible(np.ones((1, 2)), placement, RING, one, one, walls, normals, 0.0)
    with pytest.raises(ValueError, match="margin must be"):
        impossible(np.ones((1, 2, 2)), placement, RING, one, one, walls, normals, -1.0)
    with pytest.raises(ValueError, match="normals must have shape"):
        impossible(np.ones((1, 2, 2)), placement, RING, one, one, walls, normals[1:], 0.0)
    with pytest.raises(ValueError, match="normals must be finite and not zero"):
        impossible(np.ones((1, 2, 2)), placement, RING, one, one, walls, 0.0 * normals, 0.0)
    support = np.ones(len(walls)), np.ones(len(points))
    with pytest.raises(ValueError, match="KnownMap: seen must have the shape of walls"):
        explain.KnownMap(walls[:2], normals[:2], walls, points, *support)
    with pytest.raises(ValueError, match=r"KnownMap: point_support must have shape \(11,\)"):
        explain.KnownMap(walls, normals, walls, points, support[0], np.ones(3))
    with pytest.raises(ValueError, match="KnownMap: normals must be finite and not zero"):
        explain.KnownMap(walls, 0.0 * normals, walls, points, *support)
    known = explain.KnownMap(walls, normals, walls, points, *support)
    torn = make_landmarks([CORNER, EDGE], [[6.0, 0.0], [5.0, 1.0]], group=[3, 4]).select([0])
    torn = dataclasses.replace(torn, position=np.ones((2, 2)))
    with pytest.raises(ValueError, match=r"explain_landmarks: Landmarks.position must have shape \(1, 2\)"):
        explain.explain_landmarks(torn, RING, [2.0, 2.0, 0.0], np.zeros((3, 3)), known, explain.EchoTests())
    short_echo = dataclasses.replace(make_landmarks([CORNER], [[6.0, 0.0]]),
                                     echo=np.zeros(0, dtype=np.uint32))
    with pytest.raises(ValueError, match=r"explain_landmarks: Landmarks.echo must have shape \(1,\)"):
        explain.explain_landmarks(short_echo, RING, [2.0, 2.0, 0.0], np.zeros((3, 3)), known, explain.EchoTests())
    with pytest.raises(ValueError, match=r"landmark_paths: Landmarks.echo must have shape \(1,\)"):
        explain.landmark_paths(short_echo, placement, RING)
    outside = RING.n_groups
    stray = make_landmarks([CORNER, EDGE], [[6.0, 0.0], [5.0, 1.0]], group=[3, outside])
    with pytest.raises(ValueError, match=f"explain_landmarks: group must be in 0..{outside - 1}, got {outside}"):
        explain.explain_landmarks(stray, RING, [2.0, 2.0, 0.0], np.zeros((3, 3)), known, explain.EchoTests())
    with pytest.raises(ValueError, match=f"landmark_paths: group must be in 0..{outside - 1}, got {outside}"):
        explain.landmark_paths(stray, placement, RING)
    with pytest.raises(ValueError, match="landmark_paths: the placement is of another layout"):
        explain.landmark_paths(stray.select([0]), place(load_layout("kreczmer_triad"), [0.0, 0.0, 0.0]), RING)
    # A landmark the tests do not take (not valid) may name any group: it is not tested, nothing raises.
    left_out = dataclasses.replace(stray, valid=np.array([True, False]))
    explained = explain.explain_landmarks(left_out, RING, [2.0, 2.0, 0.0], np.zeros((3, 3)), known,
                                          explain.EchoTests())
    assert not explained.any[1] and np.isfinite(explained.position).all()
    none_taken = dataclasses.replace(stray, valid=np.zeros(2, dtype=bool))
    explained = explain.explain_landmarks(none_taken, RING, [2.0, 2.0, 0.0], np.zeros((3, 3)), known,
                                          explain.EchoTests())
    assert not explained.any.any() and np.isnan(explained.position).all()  # none tested: none placed
    with pytest.raises(ValueError, match="walls must have shape"):
        facing(walls[0], [2.0, 2.0])
    with pytest.raises(ValueError, match="point must have shape"):
        facing(walls, [2.0, 2.0, 0.0])
    with pytest.raises(ValueError, match="pose_covariance must have shape"):
        Tolerance(sigma_path=1e-3, pose_covariance=np.eye(2))
    for field, value in (("sigma_path", 0.0), ("gate_sigmas", math.nan), ("sigma_map", -1.0),
                         ("sigma_speed", math.inf)):
        with pytest.raises(ValueError, match=f"field '{field}'"):
            Tolerance(**{"sigma_path": 1e-3, field: value})


def test_nan_data_never_raises_and_explains_nothing():
    pose = np.array([2.4, 1.3, 0.4])
    placement = place(RING, pose)
    walls, points = _room_map()
    world = World(ROOM, RING, REALISTIC.only("multipath"), noise=Noise(tof=1e-6), seed=5)
    ping = world.ping(pose, 0.0)
    measured = ping.tof * ping.speed_of_sound
    baseline = predict(walls, points, placement, RING, ping.group, ping.transmitter, EXACT, paths=measured)
    # Map entries with NaN (and a wall of no length) give no path; the others are unchanged.
    broken_walls = np.concatenate([walls, [[[np.nan, 0.0], [1.0, 1.0]], [[1.0, 1.0], [1.0, 1.0]]]])
    broken_points = np.concatenate([points, [[np.nan, np.nan]]])
    with_nan = predict(broken_walls, broken_points, placement, RING, ping.group, ping.transmitter, EXACT,
                       paths=measured)
    for name in ("kind", "first", "second", "path"):
        assert_array_equal(getattr(with_nan, name), getattr(baseline, name), err_msg=name)
    # Rows heard by no receiver, or with NaN paths, are not explained.
    measured[:3] = np.nan
    explained = match(baseline, RING, ping.group, ping.transmitter, measured, EXACT)
    assert np.all(explained.label[:3] == NONE) and np.all(np.isnan(explained.residual[:3]))
    assert np.any(explained.label == MULTIPATH)
    # A NaN pose covariance explains nothing.
    unknown_pose = Tolerance(sigma_path=SIGMA_PATH, pose_covariance=np.full((3, 3), np.nan))
    prediction = predict(walls, points, placement, RING, ping.group, ping.transmitter, unknown_pose, paths=measured)
    assert np.all(match(prediction, RING, ping.group, ping.transmitter, measured, unknown_pose).label == NONE)
    # NaN reflection points are never impossible.
    normals = facing(walls, pose[:2])
    assert not impossible(np.full((1, 2, 2), np.nan), placement, RING, [0], [0], walls, normals, 0.0)[0]
    assert_array_equal(impossible(np.empty((0, 2, 2)), placement, RING, [], [], walls, normals, 0.0), [])
    # A wall left out (NaN) may have any normal.
    assert not impossible(np.full((1, 2, 2), 1.0), placement, RING, [0], [0], [[[np.nan, 0.0], [1.0, 0.0]]],
                          [[0.0, 0.0]], 0.0)[0]


def test_the_kernels_load_with_their_production_types():
    image_method.load_kernels()
    explain.load_kernels()


def test_explain_landmarks_flags_a_pings_multipath_landmarks_and_places_them_in_the_map():
    stage = PingStage(RING, pipeline.Settings(sigma_speed=pipeline.ROBOT_SIGMA_SPEED))
    walls, points = _room_map()
    tests = explain.EchoTests()
    flagged = from_multipath = 0
    for pose, ping, _, usable in worlds.simulated("multipath alone", 0, 60):
        if usable is None or usable.n_echoes != ping.echoes.n_echoes:  # rows dropped: their origins would not line up
            continue
        landmarks = stage.label(usable)[1]
        seen_once = np.ones(len(walls)), np.ones(len(points))
        known = explain.KnownMap(walls, facing(walls, pose[:2]), walls, points, *seen_once)
        explained = explain.explain_landmarks(landmarks, RING, pose, np.zeros((3, 3)), known, tests)
        # Where each landmark lies in the map, for the markers: the landmarks moved to the sensor's pose.
        assert_array_equal(explained.position, transform_landmarks(landmarks, pose).position)
        origin = ping.truth_origin[landmarks.echo[explained.multipath]]
        flagged += origin.size
        from_multipath += np.count_nonzero(origin == simulate.MULTIPATH)
    # Measured: all 5293 landmarks flagged in 60 pings came from double bounces.
    assert flagged > 100 and from_multipath / flagged >= 0.99, (flagged, from_multipath)


def test_explain_landmarks_is_predict_match_the_rule_and_impossible_in_one_call():
    """Its compiled call (image_method.explain_rows) decides as the public steps do, on pings with multipath.

    With the room's map, and with its walls alone: the echoes by way of corners and edges are then not
    explained, and their landmarks, beyond the walls, are impossible.
    """
    stage = PingStage(RING, pipeline.Settings(sigma_speed=pipeline.ROBOT_SIGMA_SPEED))
    walls, points = _room_map()
    tests = explain.EchoTests()
    covariance = np.diag([0.02 ** 2, 0.02 ** 2, math.radians(0.5) ** 2])  # SLAM's pose uncertainty, about
    tolerance = Tolerance(tests.sigma_path, covariance, tests.sigma_speed, tests.sigma_map, tests.gate_sigmas)
    # Walls seen more often than points, one of them less than the rest: the rule's supports differ.
    wall_support = np.full(len(walls), 200.0)
    wall_support[0] = 20.0
    decided = np.zeros(2, int)
    for pose, _, _, usable in worlds.simulated("multipath alone", 1, 30):
        landmarks = stage.label(usable)[1]
        placement = place(RING, pose)
        moved = transform_landmarks(landmarks, pose)
        rows = np.flatnonzero(moved.valid & np.isfinite(moved.position).all(axis=1))
        moved = moved.select(rows)
        group, transmitter = moved.group.astype(np.int64), np.zeros(rows.size, np.int64)
        paths = explain.landmark_paths(moved, placement, RING)
        margin = tests.gate_sigmas * np.hypot(np.sqrt(np.linalg.eigvalsh(moved.covariance)[:, -1]), tests.sigma_map)
        for mapped in (points, points[:0]):
            point_support = np.full(len(mapped), 50.0)
            known = explain.KnownMap(walls, facing(walls, pose[:2]), walls, mapped, wall_support, point_support)
            explained = explain.explain_landmarks(landmarks, RING, pose, covariance, known, tests)
            prediction = predict(known.walls, known.points, placement, RING, group, transmitter, tolerance,
                                 paths=paths, seen=known.seen, wall_support=wall_support, point_support=point_support)
            explanation = match(prediction, RING, group, transmitter, paths, tolerance, direct_wins=False)
            multipath = _multipath_rows(prediction, explanation, tests.gate_sigmas, moved.echo.astype(np.int64),
                                        paths)
            blocked = impossible(reflection_points(moved, placement, RING, transmitter), placement, RING, group,
                                 transmitter, known.seen, known.normals, margin) & ~multipath
            assert_array_equal(explained.multipath[rows], multipath)
            assert_array_equal(explained.impossible[rows], blocked)
            closest = explanation.direct[(explanation.direct_residual <= tests.gate_sigmas) & ~multipath]
            heard = np.zeros(len(known), bool)
            heard[np.where(prediction.kind[closest] == WALL, 0, len(walls)) + prediction.first[closest]] = True
            assert_array_equal(explained.heard, heard)
            decided += np.count_nonzero(multipath), np.count_nonzero(blocked)
    assert np.all(decided > 20), decided  # multipath and impossible both


def test_an_entry_is_not_heard_by_echoes_the_map_explains_as_double_bounces():
    """A point mapped inside the room where double bounces put their landmarks (a clutter point beside them).

    Their echoes are within its own echo's gate, but the map explains them as multipath: they do not hear
    it, and the test of entries not heard where expected can remove it.  (Behind a wall its own echo would
    be blocked: not heard either way.)
    """
    stage = PingStage(RING, pipeline.Settings(sigma_speed=pipeline.ROBOT_SIGMA_SPEED))
    walls, points = _room_map()
    tests = explain.EchoTests()
    wall_support, point_support = np.full(len(walls), 100.0), np.full(len(points), 100.0)
    tried = heard = 0
    for pose, _, _, usable in worlds.simulated("multipath alone", 0, 40):
        landmarks = stage.label(usable)[1]
        known = explain.KnownMap(walls, facing(walls, pose[:2]), walls, points, wall_support, point_support)
        explained = explain.explain_landmarks(landmarks, RING, pose, np.zeros((3, 3)), known, tests)
        inside = np.all((explained.position > 0.2) & (explained.position < [5.8, 4.3]), axis=1)
        for row in np.flatnonzero(explained.multipath & inside)[:3]:
            ghost = np.vstack([points, explained.position[row]])
            with_ghost = explain.KnownMap(walls, facing(walls, pose[:2]), walls, ghost, wall_support,
                                          np.append(point_support, 1.0))
            again = explain.explain_landmarks(landmarks, RING, pose, np.zeros((3, 3)), with_ghost, tests)
            assert again.multipath[row]  # seen once, less than the double bounce's walls
            tried += 1
            heard += again.heard[-1]
    assert tried >= 30 and heard == 0, (tried, heard)


def test_audible_entries_are_heard_where_real_and_a_ghost_never_is():
    """The map's own echoes a ping should hear (:func:`explain.audible`) against those its landmarks matched.

    A point where nothing reflects (a ghost) is audible from most poses and never heard; the room's
    walls, corners and edges are heard in most pings that should hear them.
    """
    stage = PingStage(RING, pipeline.Settings(sigma_speed=pipeline.ROBOT_SIGMA_SPEED))
    walls, points = _room_map()
    ghost = len(walls) + len(points)
    points = np.vstack([points, [[2.5, 3.2]]])  # in the room, clear of every reflector
    tests = explain.EchoTests()
    audible_count = np.zeros(ghost + 1)
    heard_count = np.zeros(ghost + 1)
    for pose, _, _, usable in worlds.simulated("ideal", 0, 120):
        landmarks = stage.label(usable)[1]
        seen = np.full(len(walls), 100.0), np.full(len(points), 100.0)
        known = explain.KnownMap(walls, facing(walls, pose[:2]), walls, points, *seen)
        audible = explain.audible(known, RING, pose, np.zeros((3, 3)), tests)
        heard = explain.explain_landmarks(landmarks, RING, pose, np.zeros((3, 3)), known, tests).heard
        audible_count += audible
        heard_count += heard & audible
    assert audible_count[ghost] > 60 and heard_count[ghost] == 0, (audible_count[ghost], heard_count[ghost])
    real = audible_count[:ghost] >= 20
    assert real.sum() >= 10, audible_count
    # Measured: every real entry audible in 20 or more of the 120 pings was heard in 85 % or more of them.
    assert np.all(heard_count[:ghost][real] >= 0.5 * audible_count[:ghost][real]), (audible_count, heard_count)
