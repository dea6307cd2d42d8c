"""One ping from echoes to labelled landmarks (sonar_ring.pipeline), without ROS."""

import dataclasses

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from sonar_ring import localise, pipeline, ring_consistency
from sonar_ring.echoes import EchoArrays
from sonar_ring.geometry import load_layout
from sonar_ring.landmarks import CORNER, EDGE, PLANE, UNKNOWN, Landmarks
from sonar_ring.ping_stage import PingStage
from sonar_ring.simulate import Noise, Simulator, load_scene

CHI2_2DOF_3SIGMA = 11.83  # P(chi2_2 <= 11.83) = 99.73 %
RING = load_layout("browne_ring")


def room_pings(count, sigma_tof, seed=0):
    scene = load_scene("room")
    times, poses = scene.trajectory.poses(RING.ping_rate)
    step = len(times) // count
    return Simulator(scene, RING).run(poses[::step][:count], times[::step][:count], noise=Noise(tof=sigma_tof),
                                      rng=np.random.default_rng(seed))


def hypothesis_of_true_class(ping, hypotheses):
    """Index (N,) of each echo's hypothesis of its true class."""
    index = np.full(ping.n_echoes, -1)
    for row in range(len(hypotheses)):
        if hypotheses.landmark_class[row] == ping.truth_class[hypotheses.echo[row]]:
            index[hypotheses.echo[row]] = row
    return index


def test_noise_free_hypotheses_of_the_true_class_are_exact():
    compared = 0
    for ping in room_pings(40, 0.0):
        hypotheses = pipeline.localise_ping(RING, ping.echoes)
        assert len(hypotheses) == 3 * ping.n_echoes
        heard = np.isfinite(ping.tof).all(axis=1)  # an echo one receiver missed gives no landmark
        index = hypothesis_of_true_class(ping, hypotheses)[heard]
        assert_array_equal(hypotheses.valid[index], True)
        assert np.all(hypotheses.reason[~heard[hypotheses.echo]] == localise.NOT_FINITE)
        assert_allclose(hypotheses.position[index], ping.truth_position[heard], atol=1e-9)
        planes = ping.truth_class[heard] == PLANE
        # messages carry the plane normal towards the sensor, as the simulator's truth does
        assert_allclose(hypotheses.normal[index[planes]], ping.truth_normal[heard][planes], atol=1e-9)
        compared += np.count_nonzero(heard)
    assert compared > 1000


def test_covariances_hold_99_percent_of_errors_within_3_sigma():
    inside = total = 0
    for ping in room_pings(150, 1e-6, seed=3):
        hypotheses = pipeline.localise_ping(RING, ping.echoes, pipeline.Settings(sigma_tof=1e-6))
        index = hypothesis_of_true_class(ping, hypotheses)
        usable = (index >= 0) & hypotheses.valid[np.maximum(index, 0)]
        error = hypotheses.position[index[usable]] - ping.truth_position[usable]
        mahalanobis = np.einsum("ni,nij,nj->n", error, np.linalg.inv(hypotheses.covariance[index[usable]]), error)
        inside += np.count_nonzero(mahalanobis <= CHI2_2DOF_3SIGMA)
        total += error.shape[0]
    assert total > 3000
    assert inside / total >= 0.99


def test_a_valid_estimate_next_to_the_tangent_keeps_a_finite_covariance():
    """One sigma point beyond |d2 - d1| = D has no solution; the covariance falls back to first order."""
    group = np.array([0])
    tx = RING.transmitters[RING.group_transmitters[0, 0], :2]
    rx1, rx2 = RING.receivers[RING.groups[0], :2]
    separation = np.linalg.norm(rx2 - rx1)
    d1 = 2.0
    d2 = d1 + separation * (1 - 1e-7)
    assert localise.plane(tx, rx1, rx2, d1, d2).valid
    echoes = EchoArrays(RING.name, 343.0, group, np.array([0]), np.array([[d1, d2]]) / 343.0,
                        np.empty((1, 0)), np.empty((1, 0)))
    hypotheses = pipeline.localise_ping(RING, echoes, pipeline.Settings(models=("plane",),
                                                                         vertical_correction=False))
    assert hypotheses.valid[0]
    assert np.isfinite(hypotheses.covariance).all()
    assert np.all(np.linalg.eigvalsh(hypotheses.covariance[0]) > 0)


def test_classified_landmarks_are_right_where_decided_and_placed_as_corners_otherwise():
    settings = pipeline.Settings(sigma_tof=1e-6)
    decided = wrong = 0
    for ping in room_pings(150, 1e-6, seed=5):
        echoes = ping.echoes
        hypotheses = pipeline.localise_ping(RING, echoes, settings)
        labelled = pipeline.classify_ping(RING, echoes, hypotheses, settings)
        assert len(labelled) == len(np.unique(labelled.echo))  # one landmark per echo
        assert set(np.unique(labelled.landmark_class)) <= {UNKNOWN, EDGE}  # a ring alone tells no plane from corner
        known = labelled.landmark_class != UNKNOWN
        decided += np.count_nonzero(known)
        wrong += np.count_nonzero(labelled.landmark_class[known] != ping.truth_class[labelled.echo[known]])
        assert_array_equal(labelled.confidence[~known], 0.0)
        corners = {e: row for row, e in enumerate(hypotheses.echo) if hypotheses.landmark_class[row] == CORNER}
        for row in np.flatnonzero(~known):
            assert_array_equal(labelled.position[row], hypotheses.position[corners[labelled.echo[row]]])
    assert decided > 0 and wrong / decided < 0.01


def test_barshan_kuc_pair_is_decided_by_amplitudes():
    pair = load_layout("barshan_kuc_pair")
    scene = load_scene("barshan_kuc_bench")
    ping = Simulator(scene, pair).run(scene.sensor_pose[None, :], np.zeros(1), noise=Noise(amplitude=0.0))[0]
    labelled = pipeline.classify_ping(pair, ping.echoes, pipeline.localise_ping(pair, ping.echoes))
    assert len(labelled) > 0
    known = labelled.landmark_class != UNKNOWN
    assert known.any()
    assert_array_equal(labelled.landmark_class[known], ping.truth_class[labelled.echo[known]])


def assert_same_landmarks(found, expected):
    for name in expected.__dataclass_fields__:
        assert_array_equal(getattr(found, name), getattr(expected, name), err_msg=name)
        assert getattr(found, name).dtype == getattr(expected, name).dtype, name


@pytest.mark.parametrize("layout_name, scene_name", [
    ("browne_ring", "single_pole"), ("browne_ring", "room"), ("barshan_kuc_pair", "barshan_kuc_bench"),
    ("barshan_kuc_array", "barshan_kuc_bench"), ("kreczmer_triad", "room")])
def test_batched_pings_give_each_ping_its_own_result_exactly(layout_name, scene_name):
    layout, scene = load_layout(layout_name), load_scene(scene_name)
    poses = scene.sensor_pose[None, :] + np.linspace(0, 0.3, 9)[:, None] * np.array([1.0, 0.5, 0.2])
    pings = [p.echoes for p in Simulator(scene, layout).run(poses, np.arange(9) / 30.0, noise=Noise(tof=1e-7),
                                                               rng=np.random.default_rng(4))]
    # an empty ping as a message decodes: no amplitude and no phase-delay columns (a triad's too)
    pings[3] = EchoArrays(layout.name, pings[3].speed_of_sound, pings[3].group[:0], pings[3].transmitter[:0],
                          pings[3].tof[:0], np.empty((0, 0), np.float32), np.empty((0, 0)))
    for index in (6, 7):  # a warmer stretch: stacked apart from the rest
        pings[index] = EchoArrays(**{**pings[index].__dict__, "speed_of_sound": 349.0})
    settings = pipeline.Settings(models=("plane", "edge", "corner"), sigma_tof=3e-7)
    batched = pipeline.label_pings(layout, pings, settings)
    assert len(batched) == len(pings)
    decided = invalid = joint = 0
    for echoes, (hypotheses, labelled, published) in zip(pings, batched, strict=True):
        everything = pipeline.localise_ping(layout, echoes, settings)
        alone = everything.select(everything.valid)
        assert_same_landmarks(hypotheses, alone)
        assert_same_landmarks(labelled, pipeline.classify_ping(layout, echoes, alone, settings))
        # Invalid hypotheses change nothing: the composed localiser hands them all on.
        assert_same_landmarks(labelled, pipeline.classify_ping(layout, echoes, everything, settings))
        assert_same_landmarks(published, pipeline.joint_landmarks(layout, echoes, labelled, settings))
        decided += np.count_nonzero(labelled.landmark_class != UNKNOWN)
        invalid += np.count_nonzero(~everything.valid)
        joint += len(labelled) - len(published)
    assert sum(len(h) for h, _, _ in batched) > 0
    if (layout_name, scene_name) == ("browne_ring", "room"):
        assert invalid > 0, "the comparison must cover invalid hypotheses too"
        assert joint > 0, "the comparison must cover echoes several pairs heard (joint landmarks) too"
    if scene_name != "room":
        assert decided > 0, "the comparison must cover decided landmarks too"


def test_an_echo_several_pairs_heard_is_one_landmark_at_its_joint_fit():
    settings = pipeline.Settings(sigma_tof=1e-6)
    pair_error, joint_error, inside, joint = [], [], 0, 0
    for ping in room_pings(150, 1e-6, seed=11):
        echoes = ping.echoes
        labelled = pipeline.classify_ping(RING, echoes, pipeline.localise_ping(RING, echoes, settings), settings)
        published = pipeline.joint_landmarks(RING, echoes, labelled, settings)
        fits = ring_consistency.ring_consistency(RING, echoes.group, echoes.path_lengths(),
                                                 echoes.speed_of_sound * 1e-6, covariances=True)
        assert len(np.unique(published.echo)) == len(published)
        moved = np.any(published.position != labelled.position[np.searchsorted(labelled.echo, published.echo)],
                       axis=1)
        # a joint landmark is at the fit of its class's model, and no row's paths are in two landmarks
        row = published.echo[moved]
        taken = np.concatenate([fits.joined[row].ravel(), published.echo[~moved]])
        taken = taken[taken >= 0]
        assert len(np.unique(taken)) == len(taken)
        edge = published.landmark_class[moved] == EDGE
        transmitter = RING.plan.transmitters[echoes.group[row], 0]
        assert_allclose(published.position[moved], np.where(edge[:, None], fits.edge_position[row],
                                                             0.5 * (transmitter + fits.virtual_image[row])))
        assert np.all((fits.joined[row] >= 0).sum(axis=1) >= 2)
        # accuracy on the plane and corner echoes (UNKNOWN landmarks, placed at the virtual image's G)
        specular = np.isin(ping.truth_class, (PLANE, CORNER))
        for landmarks, errors in ((labelled, pair_error), (published, joint_error)):
            chosen = landmarks.select(specular[landmarks.echo] & (landmarks.landmark_class == UNKNOWN))
            errors.extend(np.hypot(*(chosen.position - ping.truth_position[chosen.echo]).T))
        chosen = published.select(moved & specular[published.echo] & (published.landmark_class == UNKNOWN))
        error = chosen.position - ping.truth_position[chosen.echo]
        inside += np.count_nonzero(np.einsum("ni,nij,nj->n", error, np.linalg.inv(chosen.covariance), error)
                                   <= CHI2_2DOF_3SIGMA)
        joint += len(chosen)
    assert joint > 1000
    assert inside / joint >= 0.98
    assert np.median(joint_error) < 0.6 * np.median(pair_error)


def test_an_echo_one_pair_heard_and_other_layouts_keep_their_landmarks():
    ping = room_pings(1, 1e-6, seed=2)[0]
    alone = dataclasses.replace(ping.echoes, group=ping.echoes.group[:1], transmitter=ping.echoes.transmitter[:1],
                                tof=ping.echoes.tof[:1], amplitude=ping.echoes.amplitude[:1],
                                phase_delay=ping.echoes.phase_delay[:1])
    labelled = pipeline.classify_ping(RING, alone, pipeline.localise_ping(RING, alone))
    published = pipeline.joint_landmarks(RING, alone, labelled)
    assert len(labelled) == 1
    assert_array_equal(published.position, labelled.position)
    assert_array_equal(published.covariance, labelled.covariance)
    pair = load_layout("barshan_kuc_pair")
    echoes = Simulator(load_scene("single_wall"), pair).ping((0.0, 0.0, 0.0)).echoes
    labelled = pipeline.classify_ping(pair, echoes, pipeline.localise_ping(pair, echoes))
    assert pipeline.joint_landmarks(pair, echoes, labelled) is labelled


def test_one_ping_labelled_and_published_at_once_is_what_each_step_gives():
    stage = PingStage(RING, pipeline.Settings(sigma_tof=1e-6, sigma_speed=1.2))
    for ping in room_pings(20, 1e-6, seed=4):
        hypotheses, labelled, published = stage.label_and_publish(ping.echoes)
        alone = stage.label(ping.echoes)
        for got, expected in ((hypotheses, alone[0]), (labelled, alone[1]),
                              (published, stage.publishable(ping.echoes, alone[1]))):
            for field in dataclasses.fields(Landmarks):
                assert_array_equal(getattr(got, field.name), getattr(expected, field.name))


def test_no_rows_paths_go_into_two_landmarks():
    # rows 0-2 one echo, row 3 joined 2 and 4 (a chain): 0 takes 0-2 first, 3 cannot, 4 keeps its own
    joined = np.array([[0, 1, 2], [1, 0, -1], [2, 0, -1], [3, 2, 4], [4, -1, -1], [5, 6, -1], [6, 5, -1]])
    fitting = np.array([True, True, True, True, True, False, False])
    joint, used = pipeline._joint_rows(joined, fitting)
    assert_array_equal(joint, [True, False, False, False, False, False, False])
    assert_array_equal(used, [True, True, True, False, False, False, False])


def test_error_handling():
    with pytest.raises(ValueError, match="models must be a non-empty subset"):
        pipeline.Settings(models=("plane", "wall"))
    with pytest.raises(ValueError, match="models must be a non-empty subset"):
        pipeline.Settings(models=())
    with pytest.raises(ValueError, match="each once"):
        pipeline.Settings(models=("plane", "plane"))
    triad = load_layout("kreczmer_triad")
    no_phase = EchoArrays(triad.name, 343.0, np.array([0]), np.array([0]), np.full((1, 3), 5e-3),
                          np.empty((1, 0)), np.empty((1, 0)))
    with pytest.raises(ValueError, match="two phase delays per row"):
        pipeline.localise_ping(triad, no_phase)
    # an empty triad ping as a message decodes (no phase-delay columns) has no landmarks
    empty_triad = EchoArrays(triad.name, 343.0, np.zeros(0, int), np.zeros(0, int), np.empty((0, 3)),
                             np.empty((0, 0)), np.empty((0, 0)))
    assert len(pipeline.classify_ping(triad, empty_triad, pipeline.localise_ping(triad, empty_triad))) == 0
    # bad data is flagged, never raised
    bad = EchoArrays(RING.name, 343.0, np.array([0, 1, 2]), np.zeros(3, int),
                     np.array([[np.nan, 5e-3], [-1e-3, 5e-3], [5e-3, 5e-3]]), np.empty((3, 0)), np.empty((3, 0)))
    hypotheses = pipeline.localise_ping(RING, bad)
    first_two = hypotheses.echo < 2
    assert not hypotheses.valid[first_two].any()
    assert np.isfinite(hypotheses.position).all() and np.isfinite(hypotheses.covariance).all()
    assert len(pipeline.classify_ping(RING, bad, hypotheses)) == 1
    empty = EchoArrays(RING.name, 343.0, np.zeros(0, int), np.zeros(0, int), np.empty((0, 2)), np.empty((0, 0)),
                       np.empty((0, 0)))
    assert len(pipeline.classify_ping(RING, empty, pipeline.localise_ping(RING, empty))) == 0
    # hypotheses naming no echo row of the ping, or no class, are left out (they may come off the network)
    kept = pipeline.classify_ping(RING, bad, hypotheses)
    stray = dataclasses.replace(hypotheses.select(np.flatnonzero(hypotheses.valid)[:2]),
                                echo=np.array([10**6, 2], dtype=np.uint32),
                                landmark_class=np.array([CORNER, 9], dtype=np.uint8))
    with_strays = pipeline.classify_ping(RING, bad, Landmarks.concatenate([hypotheses, stray]))
    assert_array_equal(with_strays.position, kept.position)
    # arrays that do not fit the layout or each other are refused (the compiled gather does not check bounds)
    for group, transmitter in (([0, 1, RING.n_groups], [0, 0, 0]), ([0, -1, 2], [0, 0, 0]), ([0, 1, 2], [0, 0, 5])):
        with pytest.raises(ValueError, match="names a group or transmitter the layout does not have"):
            pipeline.localise_ping(RING, dataclasses.replace(bad, group=np.array(group),
                                                             transmitter=np.array(transmitter)))
    with pytest.raises(ValueError, match="one group, one transmitter and two TOFs per echo row"):
        pipeline.localise_ping(RING, dataclasses.replace(bad, tof=bad.tof[:2]))
    with pytest.raises(ValueError, match="joint_landmarks: the landmarks name echo rows 2-1000000, the ping has 3"):
        pipeline.joint_landmarks(RING, bad, Landmarks.concatenate([kept, stray.select([0])]))
    # noise parameters that make no sense are refused, as by path_covariance
    for settings, speed in ((pipeline.Settings(sigma_tof=-1e-6), 343.0), (pipeline.Settings(sigma_speed=np.nan), 343.0),
                            (pipeline.Settings(), 0.0)):
        with pytest.raises(ValueError, match="localise_ping: need sigma_tof >= 0"):
            pipeline.localise_ping(RING, dataclasses.replace(bad, speed_of_sound=speed), settings)


def test_a_singular_path_covariance_falls_back_to_first_order():
    """sigma_t = 0 with a speed-of-sound error: the paths' covariance has rank one.

    Its Cholesky factor may not be real; those rows take the first-order
    covariance instead of failing the ping.
    """
    settings = pipeline.Settings(sigma_tof=0.0, sigma_speed=1.0)
    for ping in room_pings(5, 1e-6):
        hypotheses = pipeline.localise_ping(RING, ping.echoes, settings)
        valid = hypotheses.valid
        assert valid.any()
        assert np.isfinite(hypotheses.covariance[valid]).all()
        # Positive semi-definite: what the speed of sound alone can move, along one direction.
        assert (np.linalg.eigvalsh(hypotheses.covariance[valid]) > -1e-12).all()
