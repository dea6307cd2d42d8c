"""The realistic world: each effect alone changes what it should and nothing else, against its own statistics
or a brute-force reference; ``ideal`` is today's forward model value for value."""

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal, assert_array_max_ulp
from scipy.optimize import minimize

from sonar_ring.geometry import load_layout, speed_of_sound
from sonar_ring.realism import (
    EFFECTS,
    IDEAL,
    REALISTIC,
    Realism,
    WheelOdometry,
    World,
    air_absorption,
    miss_probability,
    multipath_paths,
    profile,
    scene_realism,
    spurious_paths,
)
from sonar_ring.simulate import (
    DIRECT,
    LATE,
    MULTIPATH,
    PING_ROW_FIELDS,
    SPURIOUS,
    Noise,
    SceneError,
    Simulator,
    load_scene,
    stack_pings,
)

FIXTURE = Path(__file__).parent / "data" / "forward_model_pings.npz"
"""Pings of the forward model as it was before the realism effects existed (seed 7; the poses inside)."""
FIXTURE_CASES = {
    "browne_ring": ("room", Noise(tof=1e-6, amplitude=0.02)),
    "kreczmer_triad": ("room", Noise(tof=1e-6, amplitude=0.02, phase=2e-7, timer=0.33e-6)),
    "barshan_kuc_pair": ("barshan_kuc_bench", Noise(tof=1e-6, amplitude=0.02)),
    "barshan_kuc_array": ("barshan_kuc_bench", Noise(tof=1e-6, amplitude=0.02)),
}
NOISY = Noise(tof=1e-6, amplitude=0.02)
ROOM = load_scene("room")
RING = load_layout("browne_ring")


def _run(realism, poses, *, seed=0, noise=NOISY, scene=ROOM, layout=RING, ping_rate=None):
    world = World(scene, layout, realism, noise=noise, seed=seed, ping_rate=ping_rate)
    rate = world.ping_rate
    return [world.ping(pose, k / rate) for k, pose in enumerate(poses)], world


def _lap(step=5):
    return ROOM.trajectory.poses(RING.ping_rate)[1][::step]


def _direct(ping):
    keep = ping.truth_origin == DIRECT
    return {name: getattr(ping, name)[keep] for name in PING_ROW_FIELDS}


@pytest.mark.parametrize("layout_name", sorted(FIXTURE_CASES))
def test_ideal_is_the_forward_model_of_before_value_for_value(layout_name):
    reference = np.load(FIXTURE)
    scene_name, noise = FIXTURE_CASES[layout_name]
    poses, times = reference[f"{layout_name}/pose"], reference[f"{layout_name}/time"]
    world = World(load_scene(scene_name), load_layout(layout_name), IDEAL, noise=noise, seed=7)
    table = stack_pings([world.ping(pose, time) for pose, time in zip(poses, times, strict=True)])
    for key in reference.files:
        layout, name = key.split("/", 1)
        if layout == layout_name and name == "amplitude":
            # numpy's transcendental functions (the beam pattern's exp among them) follow the processor's vector
            # extensions (AVX-512 or not), whose last bits differ: on an AVX-512 machine the amplitudes differ
            # from the fixture's by up to 5 units in the last place; every other field is the same bit for bit.
            assert_array_max_ulp(table[name], reference[key], maxulp=16)
        elif layout == layout_name:
            assert_array_equal(table[name], reference[key], err_msg=name)
    assert np.all(table["truth_origin"] == DIRECT)
    # and the forward model alone, with the same generator, gives the same
    simulator = Simulator(load_scene(scene_name), load_layout(layout_name))
    alone = stack_pings(simulator.run(poses, times, noise=noise, rng=np.random.default_rng(7)))
    for name in PING_ROW_FIELDS:
        assert_array_equal(alone[name], table[name], err_msg=name)


@pytest.mark.parametrize("effect", ["misses", "spurious", "multipath", "odometry"])
def test_an_effect_leaves_the_other_echoes_as_they_were(effect):
    poses = _lap(step=20)
    ideal, _ = _run(IDEAL, poses)
    changed, world = _run(REALISTIC.only(effect), poses)
    assert world.realism.effects() == (effect,)
    for before, after in zip(ideal, changed, strict=True):
        kept, added = _direct(before), _direct(after)
        if effect == "misses":
            # The same rows with some receivers gone: every value heard is the one heard before.
            present = np.isfinite(added["tof"])
            for name in ("tof", "amplitude"):
                before_values = _match_rows(kept, added)[name]
                assert_array_equal(added[name][present], before_values[present])
        else:
            for name in PING_ROW_FIELDS:
                assert_array_equal(added[name], kept[name], err_msg=name)
        assert after.speed_of_sound == before.speed_of_sound


def _match_rows(before, after):
    """Rows of ``before`` with the (reflector, group, transmitter) of each row of ``after``."""
    key = {(r, g, t): i for i, (r, g, t) in enumerate(zip(before["truth_reflector"], before["group"],
                                                             before["transmitter"], strict=True))}
    index = [key[(r, g, t)] for r, g, t in zip(after["truth_reflector"], after["group"], after["transmitter"],
                                                strict=True)]
    return {name: value[index] for name, value in before.items()}


# --------------------------------------------------------------------------- odometry


def _straight(steps, length):
    x = np.linspace(0.0, length, steps + 1)
    return np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])


def _odometry_end(realism, poses, seeds):
    ends = []
    for seed in seeds:
        odometry = WheelOdometry(realism, np.random.default_rng(seed))
        ends.append([odometry.step(pose) for pose in poses])
    return np.array(ends)  # (seeds, P, 3)


def test_odometry_distance_noise_grows_as_the_square_root_of_distance():
    realism = replace(IDEAL, odometry_distance_noise=0.01)
    poses = _straight(100, 9.0)
    runs = _odometry_end(realism, poses, range(2000))
    along = runs[:, :, 0] - poses[None, :, 0]
    for index in (25, 100):
        expected = 0.01 * math.sqrt(poses[index, 0])
        spread = along[:, index].std()
        # the standard deviation of 2000 samples is within 8 % of the truth (5 sigma)
        assert abs(spread / expected - 1) < 0.08, (index, spread, expected)
    assert np.all(runs[:, :, 1] == 0) and np.all(runs[:, :, 2] == 0)  # no heading error, none sideways


def test_odometry_heading_noise_and_bias_and_scale():
    poses = _straight(100, 4.0)
    heading = _odometry_end(replace(IDEAL, odometry_heading_noise=0.01), poses, range(2000))[:, -1, 2]
    assert abs(heading.std() / (0.01 * 2.0) - 1) < 0.08
    assert abs(heading.mean()) < 5 * 0.02 / math.sqrt(2000)
    biased = _odometry_end(replace(IDEAL, odometry_heading_bias=0.005), poses, [0])[0]
    assert_allclose(biased[:, 2], 0.005 * poses[:, 0], rtol=1e-12, atol=1e-15)
    scaled = _odometry_end(replace(IDEAL, odometry_scale_error=0.01), poses, [0])[0]
    assert_allclose(scaled[:, 0], 1.01 * poses[:, 0], rtol=1e-12)
    # a turn on the spot rolls the wheels track_width / 2 * |turn|: its heading noise
    turn = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, math.pi / 2]])
    turned = _odometry_end(replace(IDEAL, odometry_heading_noise=0.01), turn, range(2000))[:, -1, 2] - math.pi / 2
    assert abs(turned.std() / (0.01 * math.sqrt(0.2 * math.pi / 2)) - 1) < 0.08


def test_exact_odometry_reproduces_the_true_poses():
    poses = ROOM.trajectory.poses(RING.ping_rate)[1]
    odometry = WheelOdometry(IDEAL, np.random.default_rng(0))
    assert_allclose([odometry.step(pose) for pose in poses], np.unwrap(poses, axis=0), atol=1e-9)
    assert odometry.distance == pytest.approx(2 * (3.8 + 2.4), abs=0.02)


def test_realistic_odometry_drifts_several_centimetres_in_a_lap():
    poses = ROOM.trajectory.poses(RING.ping_rate)[1]
    runs = _odometry_end(REALISTIC, poses, range(20))
    final = np.hypot(*(runs[:, -1, :2] - poses[-1, :2]).T)
    assert 0.02 < np.median(final) < 0.3


# --------------------------------------------------------------------------- speed of sound


def test_the_speed_of_sound_effect_scales_ranges_as_predicted():
    realism = replace(IDEAL, temperature_offset=2.0, temperature_drift=0.5)
    poses = _lap(step=60)
    ideal, _ = _run(IDEAL, poses, noise=Noise())
    warm, _ = _run(realism, poses, noise=Noise())
    assumed = ROOM.speed_of_sound
    for k, (before, after) in enumerate(zip(ideal, warm, strict=True)):
        assert after.speed_of_sound == before.speed_of_sound == assumed
        time = k / RING.ping_rate
        true = speed_of_sound(ROOM.temperature_c + 2.0 + 0.5 * time / 60.0, ROOM.relative_humidity)
        # what the nodes compute (tof times the assumed speed) is the true path scaled by c_assumed / c_true
        assert_allclose(after.tof, before.tof * assumed / true, rtol=1e-12)
        assert_array_equal(after.truth_reflector, before.truth_reflector)


# --------------------------------------------------------------------------- misses


def test_misses_follow_the_fading_probability():
    realism = replace(IDEAL, fading_db=8.0)  # strong fading: misses enough to count
    poses = _lap(step=4)
    ideal, _ = _run(IDEAL, poses)
    faded, _ = _run(realism, poses)
    expected = missed = heard = 0
    for before, after in zip(ideal, faded, strict=True):
        old, new = _direct(before), _direct(after)
        if len(new["tof"]) < len(old["tof"]):  # whole rows go when every receiver missed
            present = np.zeros(old["tof"].shape, bool)
            matched = _match_rows(old, new)
            present_rows = [np.flatnonzero((old["truth_reflector"] == r) & (old["group"] == g))[0]
                            for r, g in zip(new["truth_reflector"], new["group"], strict=True)]
            present[present_rows] = np.isfinite(matched["tof"]) & np.isfinite(new["tof"])
        else:
            present = np.isfinite(new["tof"])
        amplitude = old["amplitude"][np.isfinite(old["amplitude"])]
        expected += miss_probability(amplitude, 10 ** (-30 / 20), 8.0).sum()
        heard += amplitude.size
        missed += amplitude.size - int(np.count_nonzero(present & np.isfinite(old["tof"])))
    sigma = math.sqrt(expected * (1 - expected / heard))
    assert abs(missed - expected) < 5 * sigma, (missed, expected, sigma)
    assert missed > 50


def test_miss_probability_at_the_threshold_is_a_half():
    threshold = 0.0316
    assert_allclose(miss_probability([threshold, 2 * threshold, threshold / 2], threshold, 3.0),
                    [0.5, 0.5 * math.erfc(20 * math.log10(2) / 3 / math.sqrt(2)),
                     0.5 * math.erfc(-20 * math.log10(2) / 3 / math.sqrt(2))])
    assert_array_equal(miss_probability([threshold * 1.01, threshold * 0.99], threshold, 0.0), [0.0, 1.0])


# --------------------------------------------------------------------------- spurious


def test_spurious_echoes_come_at_the_poisson_rate_within_range():
    simulator = Simulator(ROOM, RING)
    rng = np.random.default_rng(3)
    placement = simulator.place(ROOM.sensor_pose)
    counts = [len(spurious_paths(simulator, placement, 0.05, rng, 100).source) for _ in range(2000)]
    mean = 0.05 * RING.n_groups
    assert abs(np.mean(counts) - mean) < 5 * math.sqrt(mean / 2000)
    assert abs(np.var(counts) / mean - 1) < 0.1  # Poisson: variance = mean
    pings, _ = _run(replace(IDEAL, spurious_rate=0.05), _lap(step=30))
    rows = np.concatenate([p.truth_origin for p in pings])
    spurious = np.concatenate([p.tof[p.truth_origin == SPURIOUS] for p in pings])
    assert np.count_nonzero(rows == SPURIOUS) > 0
    assert np.nanmax(spurious) * ROOM.speed_of_sound <= simulator.max_path
    assert all(np.all(p.truth_reflector[p.truth_origin == SPURIOUS] == -1) for p in pings)


# --------------------------------------------------------------------------- multipath


def _brute_force_path(start, end, bounces):
    """Shortest path from ``start`` to ``end`` touching each ``bounce`` in order: a wall ``(a, b)`` anywhere on its
    line, or a point (an edge); minimised over the reflection points' positions along the walls (Fermat)."""
    walls = [b for b in bounces if b.shape == (2, 2)]

    def through(s):
        points, used = [start], 0
        for b in bounces:
            if b.shape == (2, 2):
                points.append(b[0] + s[used] * (b[1] - b[0]))
                used += 1
            else:
                points.append(b)
        points.append(end)
        return np.sum(np.linalg.norm(np.diff(points, axis=0), axis=1)), points

    best = None
    for guess in np.linspace(0.05, 0.95, 7):
        result = minimize(lambda s: through(s)[0], np.full(len(walls), guess), method="BFGS",
                          options={"gtol": 1e-13, "xrtol": 1e-15})
        if best is None or result.fun < best.fun:
            best = result
    return best.fun, through(best.x)[1], best.x


def test_multipath_paths_equal_the_brute_force_image_method():
    simulator = Simulator(ROOM, RING)
    placement = simulator.place([2.4, 1.3, 0.4])
    families = multipath_paths(simulator, placement, 0.5, ROOM.n_reflectors)
    kinds = [("wall", "wall"), ("wall", "edge"), ("edge", "wall")]
    checked = 0
    for family, kind in zip(families, kinds, strict=True):
        exists = np.nonzero(family.exists)
        for index in zip(*(axis[::97] for axis in exists), strict=True):
            member, group, slot, receiver = index
            t = placement.tx[group, slot]
            r = placement.rx[group, receiver]
            bounces = _bounces(simulator, family, member, kind, families, kinds)
            length, points, along = _brute_force_path(t, r, bounces)
            assert np.all((along >= -1e-9) & (along <= 1 + 1e-9))  # the bounces lie on the segments
            assert abs(family.horizontal[index] - length) < 1e-8, (kind, index)
            checked += 1
    assert checked > 30


def _bounces(simulator, family, member, kind, families, kinds):
    """The walls and edges a multipath family member bounces at, in order (families are built in
    :func:`multipath_paths`' order: every non-corner ordered pair of walls, then wall x edge both ways)."""
    scene = simulator.scene
    if kind == ("wall", "wall"):
        pairs = scene.corner_walls.tolist()
        corners = {tuple(p) for p in pairs} | {tuple(p[::-1]) for p in pairs}
        pairs = [(a, b) for a in range(len(scene.walls)) for b in range(len(scene.walls))
                 if a != b and (a, b) not in corners]
        a, b = pairs[member]
        return [scene.walls[a], scene.walls[b]]
    start = families[kinds.index(("wall", "wall"))].source[-1] + 1
    if kind == ("edge", "wall"):
        start += len(families[1].source)
    offsets = np.abs(np.einsum("wej,wj->we", scene.edges[None] - simulator.wall_start[:, None],
                               simulator.wall_normal))
    wall, edge = np.nonzero(offsets > 1e-6)
    k = family.source[member] - start
    return [scene.walls[wall[k]], scene.edges[edge[k]]] if kind == ("wall", "edge") else \
        [scene.edges[edge[k]], scene.walls[wall[k]]]


def test_multipath_rows_are_no_reflector_and_not_corners():
    pings, _ = _run(replace(IDEAL, multipath_gain=0.5), _lap(step=40))
    multipath = [p for p in pings if np.any(p.truth_origin == MULTIPATH)]
    assert multipath
    for p in multipath:
        rows = p.truth_origin == MULTIPATH
        assert np.all(p.truth_reflector[rows] == -1)
        assert np.all(np.isnan(p.truth_position[rows]))
    # A right-angle corner's double bounce is the corner's echo, not multipath: no pair of a corner's walls.
    simulator = Simulator(ROOM, RING)
    families = multipath_paths(simulator, simulator.place(ROOM.sensor_pose), 0.5, 0)
    corner_pairs = len(ROOM.corner_walls) * 2
    walls = len(ROOM.walls)
    assert len(families[0].source) == walls * (walls - 1) - corner_pairs


# --------------------------------------------------------------------------- late echoes


def test_late_echoes_are_the_previous_pings_far_echoes_a_period_early():
    rate = 100.0  # 3.4 m of path per period: the room's far walls answer after the next ping fired
    realism = replace(IDEAL, late_echoes=1.0)
    poses = np.repeat(ROOM.sensor_pose[None, :], 3, axis=0)
    pings, world = _run(realism, poses, noise=Noise(), ping_rate=rate)
    ideal = Simulator(ROOM, RING).ping(ROOM.sensor_pose)
    listened = ROOM.speed_of_sound / rate
    assert not np.any(pings[0].truth_origin == LATE)  # nothing came before the first ping
    own = pings[1].truth_origin == DIRECT
    assert np.nanmax(pings[1].tof[own]) * ROOM.speed_of_sound <= listened + 1e-9  # the rest is heard later
    late = pings[1].truth_origin == LATE
    assert np.any(late)
    # Each phantom is a far echo of the ping before, its path shortened by one period's travel.
    far = np.nanmin(ideal.tof, axis=1) * ROOM.speed_of_sound > listened
    expected = np.sort((ideal.tof[far] - 1.0 / rate)[np.isfinite(ideal.tof[far])])
    found = np.sort(pings[1].tof[late][np.isfinite(pings[1].tof[late])])
    assert np.all(np.isin(np.round(found, 12), np.round(expected, 12)))
    absorption = air_absorption(RING.frequency, ROOM.temperature_c, ROOM.relative_humidity)
    assert 1.5 < absorption < 2.0  # ISO 9613-1 at 50 kHz, 22 degC, 45 % RH
    assert np.all(pings[1].amplitude[late][np.isfinite(pings[1].amplitude[late])] < 10 ** (-absorption * listened / 20))


def test_iso_9613_absorption_reference_values():
    # ISO 9613-1 Table 1, tabulated to three digits (dB/km): 6.3 kHz at 20 degC, 15 % RH; 50 Hz at -20 degC, 10 % RH
    assert 1e3 * air_absorption(6300.0, 20.0, 15.0) == pytest.approx(175, rel=0.005)
    assert 1e3 * air_absorption(50.0, -20.0, 10.0) == pytest.approx(0.589, rel=0.005)


@pytest.mark.parametrize("scene_name", ["single_wall", "single_corner", "single_pole", "room", "barshan_kuc_bench"])
@pytest.mark.parametrize("layout_name", sorted(FIXTURE_CASES))
def test_the_realistic_world_runs_in_every_scene_with_every_layout(scene_name, layout_name):
    scene, layout = load_scene(scene_name), load_layout(layout_name)
    pose = scene.sensor_pose
    pings, _ = _run(REALISTIC, [pose, pose + [0.05, 0.0, 0.1], pose + [0.1, 0.0, 0.2]], scene=scene, layout=layout,
                    noise=FIXTURE_CASES[layout_name][1])
    for ping in pings:
        assert ping.tof.shape == (ping.n_echoes, layout.receivers_per_group)
        assert np.all(np.isfinite(ping.tof).any(axis=1))  # every row heard by some receiver
        assert np.all(np.nan_to_num(ping.tof, nan=1.0) > 0)


# --------------------------------------------------------------------------- profiles


def test_profiles_and_effects():
    assert IDEAL.effects() == ()
    assert REALISTIC.effects() == tuple(EFFECTS)
    for effect in EFFECTS:
        assert REALISTIC.only(effect).effects() == (effect,)
    assert profile("realistic", {"multipath_gain": 0}).effects() == tuple(e for e in EFFECTS if e != "multipath")
    scene = replace(ROOM, realism={"spurious_rate": 0.1})
    assert scene_realism(scene, "ideal").spurious_rate == 0.1
    assert scene_realism(scene, "ideal", {"spurious_rate": 0.0}).effects() == ()


def test_error_handling():
    with pytest.raises(SceneError, match="profile must be one of ideal, realistic"):
        profile("real")
    with pytest.raises(SceneError, match="here: unknown field 'multipath'"):
        profile("ideal", {"multipath": 1}, where="here")
    with pytest.raises(SceneError, match="field 'fading_db' must be a number in"):
        profile("ideal", {"fading_db": -1})
    with pytest.raises(SceneError, match="field 'late_echoes' must be 0 or 1"):
        profile("ideal", {"late_echoes": 0.5})
    with pytest.raises(SceneError, match="scene 'room': realism: unknown field 'x'"):
        scene_realism(replace(ROOM, realism={"x": 1.0}), "ideal")
    with pytest.raises(ValueError, match="field 'spurious_rate'"):
        Realism(spurious_rate=True)
    with pytest.raises(ValueError, match="effect must be one of"):
        REALISTIC.only("rain")
    with pytest.raises(SceneError, match="field 'realism' must map"):
        load_scene({"reflectors": [{"type": "edge", "at": [1, 2]}], "realism": [1]})
    with pytest.raises(SceneError, match="field 'realism.fading_db'"):
        load_scene({"reflectors": [{"type": "edge", "at": [1, 2]}], "realism": {"fading_db": "x"}})
    with pytest.raises(ValueError, match="pose must be finite"):
        World(ROOM, RING).ping([0.0, math.nan, 0.0], 0.0)
