"""Scene simulator: path lengths against Fermat's principle, Barshan & Kuc's range
and amplitude curves (eqs 6-11, 15-20, Fig. 8), existence rules (finite walls,
corner arms, occlusion, range, acceptance), noise, phase delays, frames and
the scene files."""

import math

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal
from scipy.optimize import minimize, minimize_scalar

from sonar_ring import localise
from sonar_ring.geometry import CONFIG_DIR, load_layout, speed_of_sound
from sonar_ring.simulate import (
    CORNER,
    DEFAULT_THRESHOLD,
    EDGE,
    NOISE_FREE,
    PLANE,
    REFLECTOR_TYPES,
    Noise,
    Ping,
    SceneError,
    Simulator,
    load_scene,
    ping,
    scene_path,
    stack_pings,
    transducer_half_angle,
)

LAYOUTS = ("browne_ring", "barshan_kuc_pair", "barshan_kuc_array", "kreczmer_triad")
SCENES = ("single_wall", "single_corner", "single_pole", "room", "barshan_kuc_bench")
BK = load_layout("barshan_kuc_pair")
D_BK = 0.080  # Barshan & Kuc's separation d
# The same pair with all-seeing receivers, to check path lengths at any inclination.
BK_WIDE = load_layout(dict(yaml.safe_load((CONFIG_DIR / "layouts" / "barshan_kuc_pair.yaml").read_text()),
                           beam_half_angle_deg=89.0))


def wall_scene(x, half_width=3.0, **extra):
    return load_scene({"reflectors": [{"type": "wall", "name": "wall", "from": [x, -half_width],
                                       "to": [x, half_width]}], **extra})


def corner_scene(x, arm=1.0, **extra):
    """A corner at (x, 0) opening toward -x, arms of length ``arm`` at +-45 deg."""
    end = arm / math.sqrt(2)
    return load_scene({"reflectors": [
        {"type": "wall", "name": "left", "from": [x, 0.0], "to": [x - end, end]},
        {"type": "wall", "name": "right", "from": [x, 0.0], "to": [x - end, -end]},
        {"type": "corner", "name": "corner", "walls": ["left", "right"]}], **extra})


def to_world(points, pose):
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.asarray(points) @ np.array([[c, s], [-s, c]]) + pose[:2]


def transducers_3d(layout, pose, p: Ping, n, k):
    """World 3-D positions of the transmitter and receiver k of echo row n."""
    tx = layout.transmitters[p.transmitter[n]]
    rx = layout.receivers[layout.groups[p.group[n], k]]
    return (np.array([*to_world(tx[:2], pose), tx[2]]), np.array([*to_world(rx[:2], pose), rx[2]]))


def fermat_length(points, legs):
    """Shortest T -> (points on vertical planes or lines) -> R path, by numerical minimisation.

    ``legs``: list of (origin (2,), direction (2,) or None) -- a vertical plane through
    origin along direction, or a vertical line at origin (None).  Returns the length and
    the horizontal offsets along each plane.
    """
    t, r = points

    def via(x):
        stops, i = [], 0
        for origin, direction in legs:
            if direction is None:
                stops.append(np.array([*origin, x[i]]))
                i += 1
            else:
                stops.append(np.array([*(origin + x[i] * direction), x[i + 1]]))
                i += 2
        chain = [t, *stops, r]
        return sum(np.linalg.norm(b - a) for a, b in zip(chain[:-1], chain[1:], strict=True))

    start = []
    for _origin, direction in legs:
        # off the corner's vertex, where |X1 - X2| is not differentiable
        start += [0.2, t[2]] if direction is not None else [t[2]]
    result = minimize(via, start, method="BFGS", options={"gtol": 1e-11})
    return result.fun, result.x


def room_poses(rng):
    """Six sensor poses in the room, each facing a wall, a corner or an edge (pairs only see 2 m, +-10 deg)."""
    places = np.column_stack([rng.uniform(0.8, 5.2, 6), rng.uniform(0.8, 3.7, 6)])
    places[0, 1] = rng.uniform(0.8, 1.7)  # within 2 m of the south wall
    places[1, 0] = rng.uniform(4.4, 5.2)  # and of the east wall
    places[2:4] = [[1.0, 1.1], [5.1, 3.4]]  # near two corners
    targets = [[places[0, 0], 0.0], [6.0, places[1, 1]], [0.0, 0.0], [6.0, 4.5], [3.4, 2.0], [1.8, 2.6]]
    yaw = [math.atan2(t[1] - p[1], t[0] - p[0]) for p, t in zip(places, targets, strict=True)]
    return np.column_stack([places, np.array(yaw) + rng.normal(0, 0.03, 6)])


# --------------------------------------------------------------------------- path lengths

@pytest.mark.parametrize("layout_name", LAYOUTS)
def test_path_lengths_obey_fermat_in_3d_for_every_echo_of_the_room(layout_name):
    """c * tof equals the shortest 3-D path via the true reflector (Fermat), vertical offsets included."""
    layout = load_layout(layout_name)
    scene = load_scene("room")
    simulator = Simulator(scene, layout)
    checked = {PLANE: 0, CORNER: 0, EDGE: 0}
    for pose in room_poses(np.random.default_rng(7)):
        p = simulator.ping(pose)
        d = p.echoes.path_lengths()
        for n in range(p.n_echoes):
            f = p.truth_reflector[n]
            row = scene.kind_index[f]
            for k in np.flatnonzero(np.isfinite(d[n])):
                ends = transducers_3d(layout, pose, p, n, k)
                if p.truth_class[n] == PLANE:
                    a, b = scene.walls[row]
                    length, x = fermat_length(ends, [(a, (b - a) / np.linalg.norm(b - a))])
                    assert -1e-9 <= x[0] <= np.linalg.norm(b - a) + 1e-9  # reflection point on the segment
                elif p.truth_class[n] == CORNER:
                    c = scene.corner_point[row]
                    arm_a, arm_b = scene.corner_arm[row]
                    length = min(fermat_length(ends, [(c, arm_a), (c, arm_b)])[0],
                                 fermat_length(ends, [(c, arm_b), (c, arm_a)])[0])
                else:
                    length, _ = fermat_length(ends, [(scene.edges[row], None)])
                assert_allclose(d[n, k], length, atol=1e-8)
                checked[p.truth_class[n]] += 1
    assert min(checked.values()) > 0, checked


def test_corner_reflection_points_lie_on_both_arms_and_obey_the_law_of_reflection():
    scene = corner_scene(1.2)
    layout = load_layout("browne_ring")
    p = ping(scene, layout, [0.0, 0.1, 0.0])  # sensor axes parallel to the world's
    rows = np.flatnonzero(p.truth_class == CORNER)
    assert rows.size >= 2
    c = p.truth_position[rows[0]]
    assert_allclose(c, [1.2, -0.1], atol=1e-12)
    for n in rows:
        for k in np.flatnonzero(np.isfinite(p.tof[n])):
            rx = layout.receivers[layout.groups[p.group[n], k], :2]
            last = p.truth_reflection_point[n, k]
            # The unfolded path is a straight line from the image 2C - T (T: the emitter at
            # the sensor origin) to the receiver; its last leg points from R to that image.
            image = 2 * c
            direction = (last - rx) / np.linalg.norm(last - rx)
            expected = (image - rx) / np.linalg.norm(image - rx)
            assert_allclose(direction, expected, atol=1e-12)
            # ... and the last reflection point is on one of the two walls, within the arm.
            offset = last - c
            assert np.linalg.norm(offset) <= 1.0
            assert_allclose(abs(offset[0]), abs(offset[1]), atol=1e-12)  # +-45 deg arms


def test_ranges_match_barshan_kuc_eqs_15_to_20():
    """Half the path of each transmitter/receiver pair is the paper's R_aa', R_ab', R_bb'.

    Eq 17 as printed, sqrt(R^2 + d^2/4 - R d sin(theta)), is not even in theta, yet mirror
    symmetry and reciprocity make R_ab'(theta) = R_ba'(-theta) = R_ab'(-theta); the
    exact plane cross range is sqrt(R^2 + d^2 cos^2(theta) / 4), equal to eq 17 at theta = 0.
    """
    half = D_BK / 2
    for radius in (0.2, 0.8, 1.6):
        eq17_at_zero = ping(wall_scene(radius), BK_WIDE, [0, 0, 0], threshold=1e-300).echoes.path_lengths()[0, 1] / 2
        assert_allclose(eq17_at_zero, math.sqrt(radius**2 + half**2), rtol=1e-15)
        for inclination in np.radians([-8.0, -2.0, 0.0, 5.0]):
            pose = [0.0, 0.0, -inclination]  # the sensor turns; the reflector's angle is +inclination
            s = math.sin(inclination)
            cross = math.sqrt(radius**2 + (half * math.cos(inclination)) ** 2)
            plane = ping(wall_scene(radius), BK_WIDE, pose, threshold=1e-300).echoes.path_lengths() / 2
            assert_allclose(plane[0], [radius - half * s, cross], rtol=0, atol=1e-12)  # eq 15
            assert_allclose(plane[1], [cross, radius + half * s], rtol=0, atol=1e-12)  # eq 16
            p = ping(corner_scene(radius), BK_WIDE, pose, threshold=1e-300)
            corner = p.echoes.path_lengths()[p.truth_class == CORNER] / 2
            assert_allclose(corner[0], [math.sqrt(radius**2 + half**2 - radius * D_BK * s), radius],
                            atol=1e-12)  # eqs 18, 20
            assert_allclose(corner[1], [radius, math.sqrt(radius**2 + half**2 + radius * D_BK * s)],
                            atol=1e-12)  # eqs 20, 19


# --------------------------------------------------------------------------- amplitudes (Fig. 8)

def bk_amplitudes(simulator, inclination):
    """A_aa', A_ab', A_ba', A_bb' of the plane or corner reflector at ``inclination`` (0 if not heard)."""
    p = simulator.ping([0.0, 0.0, -inclination])
    out = {}
    for n in np.flatnonzero(p.truth_class == simulator.scene.reflector_class[-1]):
        fired = "ab"[p.transmitter[n]]
        out[fired + "a"], out[fired + "b"] = np.nan_to_num(p.amplitude[n])
    return out


def bk_curves(simulator):
    """Inclinations (-9.5..9.5 deg) and the four amplitude curves there, (20,) and (20, 4); 0 = not heard."""
    inclinations = np.radians(np.linspace(-9.5, 9.5, 20))
    curves = [[bk_amplitudes(simulator, th).get(p, 0.0) for p in ("aa", "ab", "ba", "bb")] for th in inclinations]
    return inclinations, np.array(curves)


def peak(simulator, pair):
    """Inclination and height of the maximum of one amplitude curve: grid, then Brent."""
    grid = np.radians(np.arange(-14.0, 14.01, 0.5))
    best = grid[np.argmax([bk_amplitudes(simulator, th).get(pair, 0.0) for th in grid])]
    step = math.radians(0.5)
    result = minimize_scalar(lambda th: -bk_amplitudes(simulator, th).get(pair, 0.0),
                             bounds=(best - step, best + step), method="bounded", options={"xatol": 1e-12})
    return result.x, -result.fun


@pytest.mark.parametrize("radius", [0.3, 0.8, 1.6])
def test_fig8a_plane_all_curves_peak_at_zero_cross_pairs_at_amax_exp(radius):
    simulator = Simulator(wall_scene(radius), BK, threshold=1e-300)
    theta0 = simulator.half_angle
    theta_s = math.atan(D_BK / (2 * radius))  # eq 8
    for pair, height in (("aa", 1.0), ("bb", 1.0), ("ab", math.exp(-4 * theta_s**2 / theta0**2)),
                         ("ba", math.exp(-4 * theta_s**2 / theta0**2))):
        position, value = peak(simulator, pair)
        assert_allclose(position, 0.0, atol=1e-7)
        assert_allclose(value, height, rtol=1e-9)
    # The whole curves where heard: eq 6 exactly; eq 7 (a Gaussian fit in the paper) to 0.001 A_max.
    inclinations, curves = bk_curves(simulator)
    heard = curves > 0
    assert_array_equal(heard, heard[::-1])  # symmetric about theta = 0
    assert heard[:, 1].sum() >= 3
    gauss = np.exp(-4 * inclinations**2 / theta0**2)
    for pair, expected, tolerance in ((0, gauss, 1e-12), (3, gauss, 1e-12),
                                      (1, math.exp(-4 * theta_s**2 / theta0**2) * gauss, 1e-3)):
        assert_allclose(curves[heard[:, pair], pair], expected[heard[:, pair]], atol=tolerance)
    assert_allclose(curves[:, 1], curves[:, 2], rtol=1e-12)  # reciprocity: A_ab' = A_ba'


@pytest.mark.parametrize("radius", [0.2, 0.3, 0.8, 1.6])
def test_fig8b_corner_aa_peaks_at_plus_theta_s_bb_at_minus_theta_s(radius):
    simulator = Simulator(corner_scene(radius), BK, threshold=1e-300)
    theta0 = simulator.half_angle
    theta_s = math.atan(D_BK / (2 * radius))  # eq 8
    # Transmitter a faces the corner (a's axis through C) at sin(theta) = d / 2R: the exact
    # peak; eq 9 puts it at atan(d / 2R), 0.23 deg away at 200 mm, 0.004 deg at 800 mm.
    exact = math.asin(D_BK / (2 * radius))
    for pair, where in (("aa", exact), ("bb", -exact), ("ab", 0.0), ("ba", 0.0)):
        position, value = peak(simulator, pair)
        assert_allclose(position, where, atol=1e-7)
        assert_allclose(value, 1.0, rtol=1e-9)  # every corner curve reaches A_max
        assert abs(position - math.copysign(theta_s, where)) < math.radians(0.23) or where == 0.0
    # At zero inclination A_aa' is attenuated by exactly the eq 9 factor exp(-4 theta_s^2 / theta0^2),
    # and not heard at all when theta_s exceeds the +-10 deg beam (R < R_min of eq 28).
    expected = math.exp(-4 * theta_s**2 / theta0**2) if theta_s <= BK.beam_half_angle else 0.0
    assert_allclose(bk_amplitudes(simulator, 0.0)["aa"], expected, rtol=1e-12)
    inclinations, curves = bk_curves(simulator)
    heard = curves > 0
    assert_array_equal(heard[:, 0], heard[::-1, 3])  # A_bb'(theta) mirrors A_aa'(-theta)
    assert_allclose(curves[:, 0], curves[::-1, 3], rtol=1e-12)
    # Eq 9 is the paper's Gaussian fit: within 0.01 A_max from 300 mm, 0.035 at 200 mm (below R_min).
    fit = 0.01 if radius >= 0.3 else 0.04
    for pair, expected, tolerance in ((1, np.exp(-4 * inclinations**2 / theta0**2), 1e-12),  # eq 11, exact
                                      (0, np.exp(-4 * (inclinations - theta_s) ** 2 / theta0**2), fit)):  # eq 9
        assert heard[:, pair].sum() >= 8
        assert_allclose(curves[heard[:, pair], pair], expected[heard[:, pair]], atol=tolerance)


def test_plane_cross_echo_vanishes_below_the_working_range_eq_28():
    """At 200 mm the a -> b' ray arrives 11.3 deg off axis: outside the +-10 deg acceptance (R_min = 227 mm)."""
    p = ping(wall_scene(0.2), BK, [0, 0, 0])
    assert_array_equal(np.isnan(p.amplitude), [[False, True], [True, False]])
    assert_allclose(p.amplitude[[0, 1], [0, 1]], 1.0, rtol=1e-12)


def test_beam_half_angle_eq2_and_the_wide_receiver_fallback():
    c = speed_of_sound(20.0)
    assert_allclose(transducer_half_angle(BK, c), math.asin(0.61 * c / 60e3 / 0.020), rtol=1e-15)
    assert_allclose(math.degrees(transducer_half_angle(BK, c)), 10.05, atol=0.01)
    # Kreczmer's 10 mm receivers: 0.61 lambda > a, no first null -> 90 deg.
    assert transducer_half_angle(load_layout("kreczmer_triad"), c) == pytest.approx(math.pi / 2)


def test_ring_amplitude_is_the_receiver_gain_times_reflectivity():
    layout = load_layout("browne_ring")
    for scene, cls in ((wall_scene(1.5), PLANE), (load_scene("single_pole"), EDGE)):
        simulator = Simulator(scene, layout)
        p = simulator.ping([0, 0, 0])
        assert p.n_echoes > 0
        for n in range(p.n_echoes):
            rx = layout.receivers[layout.groups[p.group[n]], :2]
            arrival = p.truth_reflection_point[n] - rx
            off_axis = np.arctan2(arrival[:, 1], arrival[:, 0]) - layout.receiver_yaw[layout.groups[p.group[n]]]
            off_axis = np.angle(np.exp(1j * off_axis))
            heard = np.isfinite(p.tof[n])
            assert np.all(np.abs(off_axis[heard]) <= layout.beam_half_angle)
            expected = scene.reflectivity[cls] * np.exp(-2 * off_axis**2 / simulator.half_angle**2)
            assert_allclose(p.amplitude[n][heard], expected[heard], rtol=1e-12)


# --------------------------------------------------------------------------- existence

def test_plane_echo_exists_only_when_the_reflection_point_is_on_the_wall():
    """Monostatic a -> a' reflects at the foot of a's perpendicular: heard iff that foot is on the segment."""
    scene = load_scene({"reflectors": [{"type": "wall", "from": [1.0, 0.0], "to": [1.0, 1.0]}]})
    simulator = Simulator(scene, BK)
    for y in np.linspace(-0.095, -0.005, 10):  # a's foot crosses the wall's end at y = -0.04
        p = simulator.ping([0.0, y, 0.0])
        a_heard = bool(np.any((p.transmitter == 0) & np.isfinite(p.tof[:, 0]))) if p.n_echoes else False
        assert a_heard == (0.0 <= y + D_BK / 2 <= 1.0), y


def test_corner_double_reflection_needs_both_arms_long_enough():
    # a -> corner -> b reflects 0.04 * sqrt(2) = 56.6 mm from the vertex on each arm (d = 80 mm).
    for arm, cross_heard in ((0.05, False), (0.06, True)):
        p = ping(corner_scene(0.5, arm=arm), BK, [0, 0, 0], threshold=1e-9)
        corner = p.truth_class == CORNER
        assert_array_equal(np.isfinite(p.tof[corner]), [[True, cross_heard], [cross_heard, True]])


def test_sensor_outside_the_corner_quadrant_gets_no_corner_echo():
    layout = load_layout("browne_ring")
    inside = ping(corner_scene(1.2), layout, [0, 0, 0])
    behind = ping(corner_scene(1.2), layout, [2.5, 0, math.pi])  # on the convex side
    assert np.any(inside.truth_class == CORNER)
    assert not np.any(behind.truth_class == CORNER)


def test_walls_occlude_reflectors_behind_them():
    layout = load_layout("browne_ring")
    pole = {"type": "edge", "name": "pole", "at": [2.0, 0.0]}
    screen = {"type": "wall", "name": "screen", "from": [1.0, -0.15], "to": [1.0, 0.15]}
    moved = dict(screen, **{"from": [1.0, 0.6], "to": [1.0, 0.9]})
    blocked = ping(load_scene({"reflectors": [pole, screen]}), layout, [0, 0, 0])
    clear = ping(load_scene({"reflectors": [pole, moved]}), layout, [0, 0, 0])
    assert not np.any(blocked.truth_class == EDGE)
    assert np.any(blocked.truth_class == PLANE)  # the screen itself echoes
    assert np.any(clear.truth_class == EDGE)
    # In the room the corridor wall is heard only through the doorway.
    room = load_scene("room")
    corridor = room.reflector_names.index("corridor")
    simulator = Simulator(room, layout)
    assert corridor in simulator.ping([2.45, 3.0, 0.0]).truth_reflector
    assert corridor not in simulator.ping([1.5, 3.0, 0.0]).truth_reflector  # behind north_w


def test_echoes_beyond_the_receive_window_are_dropped():
    # Barshan & Kuc pair: max_range 2 m -> paths up to 4 m; a -> a' at normal incidence is 2 R.
    assert ping(wall_scene(1.999), BK, [0, 0, 0]).n_echoes == 2
    assert ping(wall_scene(2.001), BK, [0, 0, 0]).n_echoes == 0


def test_ring_pairs_hear_a_wall_only_within_their_acceptance_angle():
    layout = load_layout("browne_ring")
    p = ping(load_scene("single_wall"), layout)
    # Pairs face 0, 7.5, 15 deg ...; the wall's normal is at 0 deg: pairs -7.5, 0, 7.5 hear it.
    assert sorted(p.group.tolist()) == [0, 1, 47]
    assert np.all(p.truth_class == PLANE)


def test_threshold_drops_weak_echoes():
    layout = load_layout("browne_ring")
    scene = load_scene("single_pole")  # edges reflect 0.3 of a plane
    assert ping(scene, layout).n_echoes > 0
    assert ping(scene, layout, threshold=0.31).n_echoes == 0
    assert DEFAULT_THRESHOLD == pytest.approx(10 ** (-1.5))


# --------------------------------------------------------------------------- truth and frames

def test_truth_is_the_localiser_landmark_in_the_sensor_frame():
    # BK pair at (0.3, 0.2) facing 6 deg, a wall along x = 1.5 and a pole.
    scene = load_scene({"reflectors": [{"type": "wall", "from": [1.5, -3], "to": [1.5, 3]},
                                       {"type": "edge", "at": [1.4, 0.35]}]})
    pose = np.array([0.3, 0.2, math.radians(6)])
    p = ping(scene, BK, pose, threshold=1e-6)
    assert set(p.truth_class.tolist()) == {PLANE, EDGE}
    for n in range(p.n_echoes):
        tx = BK.transmitters[p.transmitter[n], :2]
        if p.truth_class[n] == PLANE:
            world_tx = to_world(tx, pose)
            foot = np.array([1.5, world_tx[1]])  # foot of the perpendicular from the transmitter that fired
            assert_allclose(to_world(p.truth_position[n], pose), foot, atol=1e-12)
            # normal from the wall toward the transmitter, in the sensor frame
            assert_allclose(p.truth_normal[n], [-math.cos(pose[2]), math.sin(pose[2])], atol=1e-12)
        else:
            assert_allclose(to_world(p.truth_position[n], pose), [1.4, 0.35], atol=1e-12)
            assert np.all(np.isnan(p.truth_normal[n]))


def test_moving_scene_and_sensor_together_changes_nothing():
    layout = load_layout("browne_ring")
    base = load_scene("room")
    shift, turn = np.array([3.0, -1.0]), 0.7
    rotation = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])

    def move(point):
        return (rotation @ np.asarray(point, dtype=float) + shift).tolist()

    wall_names = [base.reflector_names[f] for f in np.flatnonzero(base.reflector_class == PLANE)]
    mapping = {"reflectors": []}
    for f, name in enumerate(base.reflector_names):
        row = base.kind_index[f]
        if base.reflector_class[f] == PLANE:
            item = {"type": "wall", "from": move(base.walls[row, 0]), "to": move(base.walls[row, 1])}
        elif base.reflector_class[f] == EDGE:
            item = {"type": "edge", "at": move(base.edges[row])}
        else:
            item = {"type": "corner", "walls": [wall_names[w] for w in base.corner_walls[row]]}
        mapping["reflectors"].append(dict(item, name=name))
    moved = load_scene(dict(mapping, temperature_c=base.temperature_c, relative_humidity=base.relative_humidity))
    pose = base.sensor_pose
    a = ping(base, layout, pose)
    b = ping(moved, layout, [*move(pose[:2]), pose[2] + turn])
    assert a.n_echoes == b.n_echoes > 20
    for field in ("group", "transmitter", "truth_reflector", "truth_class"):
        assert_array_equal(getattr(a, field), getattr(b, field))
    for field in ("tof", "amplitude", "truth_position", "truth_normal", "truth_reflection_point"):
        assert_allclose(getattr(a, field), getattr(b, field), atol=1e-9, equal_nan=True)


def test_ping_arrays_have_the_documented_shapes_and_order():
    for name in LAYOUTS:
        layout = load_layout(name)
        p = ping(load_scene("room"), layout, [2.0, 1.2, 0.4])
        n, k = p.n_echoes, layout.receivers_per_group
        assert p.tof.shape == p.amplitude.shape == (n, k) and p.tof.dtype == np.float64
        assert p.phase_delay.shape == (n, k - 1 if layout.kind == "triad" else 0)
        assert p.truth_position.shape == p.truth_normal.shape == (n, 2)
        assert p.truth_reflection_point.shape == (n, k, 2)
        assert_array_equal(np.isnan(p.tof), np.isnan(p.amplitude))
        assert np.all(np.isfinite(p.tof).any(axis=1))  # every row was heard by someone
        keys = np.column_stack([p.group, p.transmitter, np.nanmin(p.tof, axis=1)])
        assert all(tuple(keys[i]) <= tuple(keys[i + 1]) for i in range(n - 1))
        assert set(p.transmitter.tolist()) <= set(layout.group_transmitters.ravel().tolist())
        assert np.all(p.amplitude[np.isfinite(p.amplitude)] >= DEFAULT_THRESHOLD)


def test_speed_of_sound_follows_the_scene_temperature():
    layout = load_layout("browne_ring")
    cold = ping(wall_scene(1.5, temperature_c=0.0), layout)
    warm = ping(wall_scene(1.5, temperature_c=30.0, relative_humidity=60.0), layout)
    assert cold.speed_of_sound == pytest.approx(float(speed_of_sound(0.0)))
    assert warm.speed_of_sound == pytest.approx(float(speed_of_sound(30.0, 60.0)))
    assert_allclose(cold.tof * cold.speed_of_sound, warm.tof * warm.speed_of_sound, rtol=1e-14)
    assert_allclose(cold.tof / warm.tof, warm.speed_of_sound / cold.speed_of_sound, rtol=1e-14)


# --------------------------------------------------------------------------- noise

def test_noise_has_the_requested_statistics_and_comes_only_from_the_generator():
    simulator = Simulator(wall_scene(0.8), BK)
    exact = simulator.ping([0, 0, 0])
    noise = Noise(tof=2e-6, amplitude=0.02)
    poses = np.zeros((3000, 3))
    np.random.seed(1)  # global state must not matter
    first = stack_pings(simulator.run(poses, noise=noise, rng=np.random.default_rng(5)))
    np.random.seed(2)
    again = stack_pings(simulator.run(poses, noise=noise, rng=np.random.default_rng(5)))
    other = stack_pings(simulator.run(poses[:10], noise=noise, rng=np.random.default_rng(6)))
    assert_array_equal(first["tof"], again["tof"])
    assert not np.allclose(first["tof"][:20], other["tof"])
    # A_aa' (row of transmitter a, column a) at normal incidence: mean A_max, sigma 0.02.
    aa = first["amplitude"][first["transmitter"] == 0, 0]
    assert aa.size == 3000
    assert_allclose(aa.mean(), 1.0, atol=4 * 0.02 / math.sqrt(3000))
    assert_allclose(aa.std(), 0.02, rtol=0.05)
    error = first["tof"][first["transmitter"] == 0, 0] - exact.tof[0, 0]
    assert_allclose(error.mean(), 0.0, atol=4 * 2e-6 / math.sqrt(3000))
    assert_allclose(error.std(), 2e-6, rtol=0.05)


def test_noisy_ping_needs_a_generator():
    with pytest.raises(ValueError, match="rng"):
        ping(wall_scene(1.0), BK, noise=Noise(amplitude=0.02))


def test_timer_counts_whole_ticks_without_bias():
    tick = 0.33e-6
    layout = load_layout("kreczmer_triad")
    scene = load_scene("room")
    exact = ping(scene, layout, [2.0, 1.0, 0.3])
    simulator = Simulator(scene, layout)
    rng = np.random.default_rng(5)
    counted = [simulator.ping([2.0, 1.0, 0.3], noise=Noise(timer=tick), rng=rng) for _ in range(400)]
    for field in ("tof", "phase_delay"):
        t0 = getattr(exact, field)
        t = np.stack([getattr(c, field) for c in counted])
        heard = np.isfinite(t0)
        assert heard.any()
        assert_allclose(t[:, heard] / tick, np.round(t[:, heard] / tick), atol=1e-6)  # whole ticks
        assert np.all(np.abs(t[:, heard] - t0[heard]) < tick)
        # A uniform clock phase makes the mean reading the true time (truncation would be -tick/2).
        assert_allclose(t[:, heard].mean(axis=0), t0[heard], atol=0.1 * tick)


def test_kreczmer_phase_delays_are_arrival_differences_modulo_one_period():
    layout = load_layout("kreczmer_triad")
    period = 1 / layout.frequency
    simulator = Simulator(load_scene("room"), layout)
    p = simulator.ping([2.0, 1.0, 0.3])
    assert p.n_echoes > 0
    delay = p.tof[:, 1:] - p.tof[:, :1]
    assert_allclose(p.phase_delay, np.mod(delay, period), atol=1e-15)
    assert np.all((p.phase_delay >= 0) & (p.phase_delay < period))


@pytest.mark.parametrize("azimuth_deg", [-20.0, 20.0, 35.0])
def test_kreczmer_eq3_holds_for_a_distant_source(azimuth_deg):
    """v t01 = n1 lambda + b1 sin(phi) for an integer n1, up to the plane-wave error b^2 / 2d (eq 7)."""
    layout = load_layout("kreczmer_triad")
    distance, phi = 2.5, math.radians(azimuth_deg)
    receivers = layout.receivers[layout.groups[0]]
    pole = receivers[0, :2] + distance * np.array([math.cos(phi), math.sin(phi)])  # phi seen from R0
    p = ping(load_scene({"reflectors": [{"type": "edge", "at": pole.tolist()}]}), layout, [0, 0, 0])
    assert p.n_echoes == 1
    wavelength = layout.wavelength(p.speed_of_sound)
    baselines = np.abs(receivers[1:, 1] - receivers[0, 1])  # b1, b1 + b2
    residual = p.speed_of_sound * p.phase_delay[0] - baselines * math.sin(phi)
    wrapped = residual - wavelength * np.round(residual / wavelength)
    assert np.all(np.abs(wrapped) < baselines**2 / distance)  # twice eq 7's b^2 / 2d


# --------------------------------------------------------------------------- scene files

@pytest.mark.parametrize("name", SCENES)
def test_shipped_scenes_load_and_echo_for_every_layout(name):
    scene = load_scene(name)
    assert scene_path(name) == CONFIG_DIR / "scenes" / f"{name}.yaml"
    assert scene.name == name
    heard = 0
    for layout_name in LAYOUTS:
        heard += ping(scene, load_layout(layout_name)).n_echoes
    assert heard > 0


def test_room_has_every_class_and_a_loop_at_the_ping_rate():
    room = load_scene("room")
    assert {PLANE, CORNER, EDGE} <= set(room.reflector_class.tolist())
    layout = load_layout("browne_ring")
    times, poses = room.trajectory.poses(layout.ping_rate)
    steps = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    assert_allclose(np.diff(times), 1 / layout.ping_rate, rtol=1e-12)
    assert_allclose(steps[steps > 0.0099], room.trajectory.speed / layout.ping_rate, rtol=1e-9)  # off the bends
    assert np.linalg.norm(poses[-1, :2] - poses[0, :2]) <= 0.0100001  # one lap
    assert_allclose(poses[0, 2], 0.0)  # facing along the first leg (+x)
    pings = Simulator(room, layout).run(poses[::100], times[::100])
    classes = np.concatenate([p.truth_class for p in pings])
    assert {PLANE, CORNER, EDGE} <= set(classes.tolist())


def test_barshan_kuc_bench_covers_200_to_1600_mm():
    bench = load_scene("barshan_kuc_bench")
    times, poses = bench.trajectory.poses(BK.ping_rate)
    assert_allclose(poses[:, 2], 0.0)
    pings = Simulator(bench, BK).run(poses, times)
    ranges = {PLANE: [], CORNER: []}
    for p in pings:
        for n in range(p.n_echoes):
            if p.truth_class[n] in ranges:
                ranges[p.truth_class[n]].append(np.hypot(*p.truth_position[n]))
    for cls in ranges:
        assert min(ranges[cls]) <= 0.2 + 0.041 and max(ranges[cls]) >= 1.6 - 0.001, cls


def test_error_handling(tmp_path):
    def error_for(text):
        path = tmp_path / "bad.yaml"
        path.write_text(text)
        with pytest.raises(SceneError) as info:
            load_scene(path)
        message = str(info.value)
        assert str(path) in message
        return message

    assert "field 'reflectors'" in error_for("name: x\n")
    assert "field 'type'" in error_for("reflectors: [{type: window, at: [1, 2]}]\n")
    assert "field 'from'" in error_for("reflectors: [{type: wall, from: [1], to: [1, 2]}]\n")
    assert "field 'at'" in error_for("reflectors: [{type: edge, at: [1, x]}]\n")
    assert "unknown field 'colour'" in error_for("reflectors: [{type: edge, at: [1, 2], colour: red}]\n")
    assert "unknown field 'walls'" in error_for("walls: []\nreflectors: [{type: edge, at: [1, 2]}]\n")
    assert "must be unique" in error_for("reflectors: [{type: edge, name: p, at: [1, 2]}, "
                                         "{type: edge, name: p, at: [2, 2]}]\n")
    assert "must differ" in error_for("reflectors: [{type: wall, from: [1, 1], to: [1, 1]}]\n")
    assert "must name two walls" in error_for("reflectors: [{type: corner, walls: [a, b]}]\n")
    assert "share an end point" in error_for(
        "reflectors: [{type: wall, name: a, from: [0, 0], to: [1, 0]}, {type: wall, name: b, from: [0, 0.5], "
        "to: [0, 2]}, {type: corner, walls: [a, b]}]\n")
    assert "90 deg" in error_for(
        "reflectors: [{type: wall, name: a, from: [0, 0], to: [1, 0]}, {type: wall, name: b, from: [0, 0], "
        "to: [1, 1]}, {type: corner, walls: [a, b]}]\n")
    assert "field 'temperature_c'" in error_for("temperature_c: -300\nreflectors: [{type: edge, at: [1, 2]}]\n")
    assert "field 'relative_humidity'" in error_for(
        "relative_humidity: 120\nreflectors: [{type: edge, at: [1, 2]}]\n")
    assert "field 'reflectivity.edge'" in error_for(
        "reflectivity: {edge: 0}\nreflectors: [{type: edge, at: [1, 2]}]\n")
    assert "field 'reflectivity'" in error_for("reflectivity: {glass: 1}\nreflectors: [{type: edge, at: [1, 2]}]\n")
    assert "field 'sensor_pose'" in error_for("sensor_pose: [0, 0]\nreflectors: [{type: edge, at: [1, 2]}]\n")
    assert "field 'speed'" in error_for(
        "reflectors: [{type: edge, at: [1, 2]}]\ntrajectory: {speed: 0, waypoints: [[0, 0], [1, 0]]}\n")
    assert "field 'waypoints'" in error_for(
        "reflectors: [{type: edge, at: [1, 2]}]\ntrajectory: {speed: 1, waypoints: [[0, 0]]}\n")
    assert "field 'loop'" in error_for(
        "reflectors: [{type: edge, at: [1, 2]}]\ntrajectory: {speed: 1, loop: 2, waypoints: [[0, 0], [1, 0]]}\n")
    assert "not valid YAML" in error_for("reflectors: [\n")
    assert "top level" in error_for("- 1\n")
    with pytest.raises(SceneError, match="cannot read"):
        load_scene(tmp_path / "missing.yaml")
    with pytest.raises(SceneError, match="no_such_scene"):
        load_scene("no_such_scene")
    with pytest.raises(ValueError, match="'tof'"):
        Noise(tof=-1.0)
    with pytest.raises(ValueError, match="threshold"):
        Simulator(wall_scene(1.0), BK, threshold=0.0)
    with pytest.raises(ValueError, match="pose"):
        ping(wall_scene(1.0), BK, [0.0, 0.0])
    with pytest.raises(ValueError, match="at least one"):
        stack_pings([])
    # A valid ping has a noise-free counterpart: NOISE_FREE needs no generator.
    assert ping(wall_scene(1.0), BK, noise=NOISE_FREE).n_echoes == 2


# --------------------------------------------------------------------------- round trip through the localiser

ROUND_TRIP_LAYOUTS = ("browne_ring", "barshan_kuc_pair", "kreczmer_triad")
ROUND_TRIP = {name: load_layout(name) for name in ROUND_TRIP_LAYOUTS}
REFLECTOR_CLASS = REFLECTOR_TYPES  # scene-file type -> class code


def localise_rows(layout, p: Ping, columns):
    """Localise every echo row heard by both receiver ``columns`` with the model of its true class.

    Returns the row indices, the localised positions (n, 2), normals (n, 2; NaN but planes)
    and the valid flags, all in the sensor frame.
    """
    first, second = columns
    d = p.echoes.path_lengths()
    rows = np.flatnonzero(np.isfinite(d[:, first]) & np.isfinite(d[:, second]))
    g, cls = p.group[rows], p.truth_class[rows]
    slot = np.argmax(layout.group_transmitters[g] == p.transmitter[rows][:, None], axis=1)
    dz = layout.height_offset()[g, slot]  # (n, K)
    h1 = localise.horizontal_path(d[rows, first], dz[:, first]).value
    h2 = localise.horizontal_path(d[rows, second], dz[:, second]).value
    tx = layout.transmitters[p.transmitter[rows], :2]
    rx1 = layout.receivers[layout.groups[g, first], :2]
    rx2 = layout.receivers[layout.groups[g, second], :2]
    position = np.full((rows.size, 2), np.nan)
    normal = np.full((rows.size, 2), np.nan)
    valid = np.zeros(rows.size, dtype=bool)
    for code, model in ((PLANE, localise.plane), (CORNER, localise.corner), (EDGE, localise.edge)):
        mine = cls == code
        estimate = model(tx[mine], rx1[mine], rx2[mine], h1[mine], h2[mine])
        position[mine], valid[mine] = estimate.position, estimate.valid
        if code == PLANE:
            normal[mine] = estimate.normal
    return rows, position, normal, valid


def round_trip_errors(layout, p: Ping):
    """Largest landmark position and plane normal errors over all receiver pairs of the groups."""
    K = layout.receivers_per_group
    worst, count = [0.0, 0.0], 0
    for columns in [(i, j) for i in range(K) for j in range(i + 1, K)]:
        rows, position, normal, valid = localise_rows(layout, p, columns)
        assert np.all(valid), p.truth_class[rows][~valid]
        worst[0] = max(worst[0], float(np.max(np.abs(position - p.truth_position[rows]), initial=0.0)))
        planes = p.truth_class[rows] == PLANE
        # The localiser's normal points away from the sensor (T' - T); the truth's, like
        # Landmark.msg's, from the wall toward the sensor.
        worst[1] = max(worst[1], float(np.max(np.abs(normal[planes] + p.truth_normal[rows][planes]), initial=0.0)))
        count += rows.size
    return worst, count


def reflector_at(kind, distance, bearing, turn, pose):
    """A one-reflector scene mapping, placed relative to the sensor at ``pose`` (world frame)."""
    def world(local):
        return to_world(np.asarray(local, dtype=float), pose).tolist()

    direction = np.array([math.cos(bearing), math.sin(bearing)])
    point = distance * direction
    if kind == "wall":
        # foot point at ``point``, the wall turned by ``turn`` about it
        along = np.array([-math.sin(bearing + turn), math.cos(bearing + turn)])
        return {"reflectors": [{"type": "wall", "from": world(point - 3 * along), "to": world(point + 3 * along)}]}
    if kind == "corner":
        # vertex at ``point``, opening toward the sensor, its bisector turned by ``turn``
        back = bearing + math.pi + turn
        arms = [point + 1.5 * np.array([math.cos(back + s * math.pi / 4), math.sin(back + s * math.pi / 4)])
                for s in (1, -1)]
        return {"reflectors": [{"type": "wall", "name": "a", "from": world(point), "to": world(arms[0])},
                               {"type": "wall", "name": "b", "from": world(point), "to": world(arms[1])},
                               {"type": "corner", "walls": ["a", "b"]}]}
    return {"reflectors": [{"type": "edge", "at": world(point)}]}


@settings(max_examples=80, deadline=None)
@given(layout_name=st.sampled_from(ROUND_TRIP_LAYOUTS),
       kind=st.sampled_from(["wall", "corner", "edge"]),
       distance=st.floats(0.8, 1.8),
       pair=st.integers(0, 47),
       bearing_fraction=st.floats(-1.0, 1.0),
       turn_fraction=st.floats(-1.0, 1.0),
       x=st.floats(-5.0, 5.0), y=st.floats(-5.0, 5.0), yaw=st.floats(-math.pi, math.pi))
def test_simulated_paths_localise_back_to_the_true_landmark(layout_name, kind, distance, pair, bearing_fraction,
                                                            turn_fraction, x, y, yaw):
    """Noise-free path lengths, vertically corrected, give the true plane / corner / edge within 1e-9 m."""
    layout = ROUND_TRIP[layout_name]
    # Ring: within 3 deg of any pair's axis; the narrow pair +-4 deg; the wide triad +-30 deg.
    if layout_name == "browne_ring":
        bearing = math.radians(7.5 * pair + 3 * bearing_fraction)
    else:
        bearing = bearing_fraction * math.radians(4 if layout_name == "barshan_kuc_pair" else 30)
    turn = turn_fraction * (math.radians(20) if kind == "corner" else 0.0)
    pose = np.array([x, y, yaw])
    scene = load_scene(reflector_at(kind, distance, bearing, turn, pose))
    p = Simulator(scene, layout, threshold=1e-9).ping(pose)
    assert np.any(p.truth_class == REFLECTOR_CLASS[kind])
    (position_error, normal_error), count = round_trip_errors(layout, p)
    assert count > 0
    assert position_error <= 1e-9
    assert normal_error <= 1e-9


@pytest.mark.parametrize("layout_name", ROUND_TRIP_LAYOUTS)
def test_every_echo_of_the_room_localises_back_to_its_landmark(layout_name):
    layout = ROUND_TRIP[layout_name]
    room = load_scene("room")
    total, worst = 0, [0.0, 0.0]
    classes = set()
    _, lap = room.trajectory.poses(layout.ping_rate)
    poses = np.vstack([room_poses(np.random.default_rng(3)), lap[:: len(lap) // 24]])
    for p in Simulator(room, layout, threshold=1e-9).run(poses):
        errors, count = round_trip_errors(layout, p)
        worst = np.maximum(worst, errors)
        total += count
        classes |= set(p.truth_class.tolist())
    assert classes == {PLANE, CORNER, EDGE}
    assert total >= 20
    assert_allclose(worst, 0.0, atol=1e-9)
