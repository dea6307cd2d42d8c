"""Property-based fuzzing of every function that takes outside data: no exception, no NaN in a valid output.

Each test draws whole batches of inputs -- NaN, infinities, negative, zero, subnormal
and huge values mixed with realistic ones -- and checks the contract of the core:
bad data never raises, a result marked valid is finite, an invalid one carries a
reason.  CI runs a modest number of examples per test; set
``SONAR_RING_FUZZ_EXAMPLES`` (e.g. 100000) for a long run:

    SONAR_RING_FUZZ_EXAMPLES=100000 pytest test/test_fuzz.py --hypothesis-show-statistics
"""

import copy
import os
from dataclasses import replace

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from sonar_ring import doa, localise, pipeline, ring_consistency
from sonar_ring.echoes import EchoArrays, screen_ping
from sonar_ring.frames import FrameDecoder, encode_echoes
from sonar_ring.geometry import LayoutError, config_path, load_layout
from sonar_ring.landmarks import EDGE, UNKNOWN, make_landmarks
from sonar_ring.mapping import LandmarkMap
from sonar_ring.simulate import SceneError, load_scene

FUZZ = settings(max_examples=int(os.environ.get("SONAR_RING_FUZZ_EXAMPLES", "150")), deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large], database=None)
"""Every fuzz test's settings: the example count comes from SONAR_RING_FUZZ_EXAMPLES."""

LAYOUTS = {name: load_layout(name) for name in ("browne_ring", "barshan_kuc_pair", "barshan_kuc_array",
                                                "kreczmer_triad")}
ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True)
"""Every float64: NaN, +-inf, +-0, subnormals, +-1.8e308."""
SENSOR_LENGTH = st.floats(-12.0, 12.0)
"""Coordinates and path lengths of a sensor's working range, m."""
LENGTH = st.one_of(SENSOR_LENGTH, SENSOR_LENGTH, ANY_FLOAT)
"""Mostly realistic lengths, a third anything at all."""
TOF = st.one_of(st.floats(1e-4, 0.07), st.floats(1e-4, 0.07), st.just(np.nan), ANY_FLOAT)
"""Mostly realistic times of flight, s, the rest missed echoes and anything at all."""


def finite(*arrays):
    return all(np.all(np.isfinite(a)) for a in arrays)


def batch(shape, elements):
    return hnp.arrays(np.float64, shape, elements=elements)


@st.composite
def pair_geometry(draw):
    """tx, rx1, rx2 (N, 2) and d1, d2 (N,): a sensor pair and path lengths, mostly plausible."""
    n = draw(st.integers(1, 12))
    tx = draw(batch((n, 2), LENGTH))
    if draw(st.booleans()):  # a real pair: receivers 1-100 mm apart in front of the transmitter
        offset = draw(batch((n, 1), st.floats(0.0, 0.2)))
        half = draw(batch((n, 1), st.floats(5e-4, 0.05)))
        rx1 = tx + np.hstack([offset, half])
        rx2 = tx + np.hstack([offset, -half])
    else:
        rx1, rx2 = draw(batch((n, 2), LENGTH)), draw(batch((n, 2), LENGTH))
    return tx, rx1, rx2, draw(batch((n,), LENGTH)), draw(batch((n,), LENGTH))


@pytest.mark.parametrize("model", ["plane", "corner", "edge", "virtual_image", "on_axis"])
@FUZZ
@given(geometry=pair_geometry())
def test_localisation_models_flag_every_input_they_cannot_solve(model, geometry):
    estimate = getattr(localise, model)(*geometry)
    assert estimate.valid.shape == geometry[3].shape
    assert np.all((estimate.reason == localise.OK) == estimate.valid)
    assert finite(estimate.position[estimate.valid])
    if model == "plane":
        assert finite(estimate.normal[estimate.valid], estimate.reflection_points[estimate.valid])


@pytest.mark.parametrize("function", [
    lambda d1, d2, separation: localise.bearing(d1, d2, separation),
    lambda d1, d2, separation: localise.bearing(d1, d2, separation, exact=False),
    lambda d, dz, _: localise.horizontal_path(d, dz)], ids=["bearing", "bearing_far_field", "horizontal_path"])
@FUZZ
@given(lengths=batch(st.tuples(st.integers(1, 12), st.just(2)), LENGTH), separation=ANY_FLOAT)
def test_bearing_and_horizontal_path_flag_what_they_cannot_compute(function, lengths, separation):
    result = function(lengths[:, 0], lengths[:, 1], separation)
    assert np.all((result.reason == localise.OK) == result.valid)
    assert finite(result.value[result.valid])


@st.composite
def pings(draw):
    """A layout and a ping for it as a sensor could send it: any ids, any TOFs, any speed of sound."""
    layout = LAYOUTS[draw(st.sampled_from(sorted(LAYOUTS)))]
    n = draw(st.integers(0, 40))
    k = layout.receivers_per_group
    group = draw(hnp.arrays(np.uint16, n, elements=st.one_of(st.integers(0, layout.n_groups - 1),
                                                               st.integers(0, 65535))))
    transmitter = draw(hnp.arrays(np.uint8, n, elements=st.one_of(st.integers(0, len(layout.transmitters) - 1),
                                                                    st.integers(0, 255))))
    amplitude = draw(hnp.arrays(np.float32, (n, k), elements=st.one_of(st.floats(0, 1, width=32),
                                                                        st.floats(width=32)))) \
        if draw(st.booleans()) else np.empty((n, 0), np.float32)
    phase = draw(batch((n, k - 1), st.one_of(st.floats(-3e-5, 3e-5), ANY_FLOAT))) if k == 3 else np.empty((n, 0))
    speed = draw(st.one_of(st.floats(300.0, 360.0), ANY_FLOAT))
    echoes = EchoArrays(layout=layout.name, speed_of_sound=speed, group=group, transmitter=transmitter,
                        tof=draw(batch((n, k), TOF)), amplitude=amplitude, phase_delay=phase)
    return layout, echoes


@FUZZ
@given(pings(), st.floats(1e-8, 1e-4), st.booleans())
def test_a_ping_through_screening_localisation_and_labelling(layout_and_ping, sigma_tof, vertical):
    layout, echoes = layout_and_ping
    screened = screen_ping(echoes, layout)
    if screened.echoes is None:
        assert sum(screened.problems.values()) == 1 and screened.detail
        return
    kept = screened.echoes
    assert kept.n_echoes + sum(n for reason, n in screened.problems.items()
                               if reason in ("unknown_group", "unknown_transmitter", "empty_row")) == echoes.n_echoes
    assert np.all(np.isnan(kept.tof) | ((kept.tof > 0) & np.isfinite(kept.tof)))
    settings = pipeline.Settings(sigma_tof=sigma_tof, vertical_correction=vertical)
    hypotheses = pipeline.localise_ping(layout, kept, settings)
    assert np.all((hypotheses.reason == localise.OK) == hypotheses.valid)
    valid = hypotheses.valid
    assert finite(hypotheses.position[valid], hypotheses.covariance[valid], hypotheses.normal[valid])
    assert np.all(hypotheses.echo < max(kept.n_echoes, 1))
    labelled = pipeline.classify_ping(layout, kept, hypotheses.select(valid), settings)
    assert np.all(labelled.valid) and finite(labelled.position, labelled.covariance, labelled.confidence)
    assert np.all((labelled.confidence >= 0) & (labelled.confidence <= 1))
    assert len(np.unique(labelled.echo)) == len(labelled), "one landmark per echo"


@FUZZ
@given(st.data(), st.floats(1e-6, 1.0), st.floats(0.5, 10.0))
def test_ring_consistency_decides_only_on_finite_evidence(data, sigma_path, z):
    layout = LAYOUTS["browne_ring"]
    n = data.draw(st.integers(0, 30))
    group = data.draw(hnp.arrays(np.int64, n, elements=st.integers(0, layout.n_groups - 1)))
    paths = data.draw(batch((n, 2), st.one_of(st.floats(0.05, 12.0), st.just(np.nan), ANY_FLOAT)))
    result = ring_consistency.ring_consistency(layout, group, paths, sigma_path, z=z)
    assert set(np.unique(result.cls).tolist()) <= {UNKNOWN, EDGE}
    decided = (result.cls == EDGE) | result.specular
    assert finite(result.confidence, result.margin)
    assert np.all((result.confidence >= 0) & (result.confidence <= 1))
    assert np.all(result.confidence[~decided] == 0)


@FUZZ
@given(batch(st.integers(1, 16), st.one_of(st.floats(-1e-4, 1e-4), ANY_FLOAT)),
       st.one_of(st.floats(-1e-4, 1e-4), ANY_FLOAT), st.floats(0.05, 0.5), st.floats(0.1, 1.5))
def test_phase_azimuth_is_in_range_where_valid(t01, t02, eps, max_angle):
    result = doa.azimuth(t01, t02, 0.011, 0.004, 8.7e-3, 343.0, eps, max_angle)
    assert np.all(result.valid == (result.reason == doa.Reason.OK))
    assert finite(result.angle[result.valid])
    assert np.all(np.abs(result.angle[result.valid]) <= max_angle + 1e-12)


@st.composite
def sightings(draw):
    """One ping's landmarks in odom as anything upstream might send: any class, values and covariances."""
    n = draw(st.integers(0, 20))
    realistic = st.floats(-10, 10)
    position = draw(batch((n, 2), st.one_of(realistic, realistic, ANY_FLOAT)))
    spread = draw(batch((n, 2), st.one_of(st.floats(1e-4, 0.1), st.floats(-1e150, 1e150), st.just(np.nan))))
    covariance = np.zeros((n, 2, 2))
    covariance[:, 0, 0], covariance[:, 1, 1] = spread[:, 0] ** 2, spread[:, 1] ** 2
    covariance[:, 0, 1] = covariance[:, 1, 0] = draw(batch((n,), st.one_of(st.just(0.0), ANY_FLOAT)))
    angle = draw(batch((n,), st.floats(-np.pi, np.pi)))
    normal = np.stack([np.cos(angle), np.sin(angle)], axis=1) * draw(batch((n, 1), st.sampled_from([1.0, 0.0,
                                                                                                      np.nan])))
    landmarks = make_landmarks(draw(hnp.arrays(np.uint8, n, elements=st.integers(0, 5))), position, normal=normal,
                               covariance=covariance,
                               segment=position[:, None, :] + draw(batch((n, 2, 2), st.floats(-1, 1))),
                               valid=draw(hnp.arrays(bool, n)))
    pose = draw(hnp.arrays(np.float64, 3, elements=st.one_of(st.floats(-10, 10), ANY_FLOAT)))
    return landmarks, pose


@FUZZ
@given(st.lists(sightings(), min_size=1, max_size=6))
def test_map_update_survives_any_landmarks_and_pose(pings_of_landmarks):
    landmark_map = LandmarkMap(max_points=8, max_walls=4)
    for landmarks, pose in pings_of_landmarks:
        landmark_map.update(landmarks, pose)
    snapshot = landmark_map.snapshot()
    assert finite(snapshot.position, snapshot.covariance, snapshot.normal, snapshot.segment)
    assert len(landmark_map) <= 12
    counts = landmark_map.counts
    assert counts.pings + counts.rejected_pings == len(pings_of_landmarks)


def ring_frame(seed, n=4):
    rng = np.random.default_rng(seed)
    return EchoArrays(layout="", speed_of_sound=343.0, group=rng.integers(0, 48, n).astype(np.uint16),
                      transmitter=np.zeros(n, np.uint8), tof=rng.uniform(1e-3, 3e-2, (n, 2)),
                      amplitude=rng.uniform(0, 1, (n, 2)).astype(np.float32), phase_delay=np.empty((n, 0)))


@FUZZ
@given(st.binary(max_size=400), st.lists(st.tuples(st.integers(0, 10**6), st.integers(1, 255)), max_size=6),
       st.integers(0, 1000), st.integers(1, 64), st.booleans())
def test_frame_decoder_survives_random_and_mutated_bytes_and_resynchronises(noise, flips, seed, chunk, datagrams):
    mutated = bytearray(encode_echoes(ring_frame(seed + 1)))
    for where, mask in flips:
        mutated[where % len(mutated)] ^= mask
    good = encode_echoes(ring_frame(seed), sequence=seed)
    decoder = FrameDecoder()
    if datagrams:  # UDP: one frame per datagram, whatever came before
        decoded = decoder.feed_datagram(noise) + decoder.feed_datagram(bytes(mutated)) + decoder.feed_datagram(good)
    else:  # a byte stream cut anywhere
        stream = noise + bytes(mutated) + good
        decoded = []
        for start in range(0, len(stream), chunk):
            decoded += decoder.feed(stream[start:start + chunk])
    assert decoded and decoded[-1].sequence == seed, "the good frame after the damage must decode"
    np.testing.assert_allclose(decoded[-1].echoes.tof, ring_frame(seed).tof, atol=1e-9)


CONFIG_VALUES = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6), ANY_FLOAT, st.text(max_size=8),
                          st.lists(st.floats(-5, 5), max_size=4), st.dictionaries(st.text(max_size=4),
                                                                                   st.integers(), max_size=2))
"""What a hand-edited YAML field might hold instead of the right value."""


def field_paths(node, path=()):
    """Every path of keys and indices into a parsed YAML document."""
    yield path
    children = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, child in children:
        yield from field_paths(child, (*path, key))


@pytest.mark.parametrize(("folder", "name", "load", "error"), [
    ("layouts", name, load_layout, LayoutError) for name in LAYOUTS] + [
    ("scenes", name, load_scene, SceneError) for name in ("room", "barshan_kuc_bench")])
@FUZZ
@given(data=st.data())
def test_a_damaged_config_gives_its_own_error_or_loads(folder, name, load, error, data):
    document = yaml.safe_load(config_path(folder, name).read_text())
    damaged = copy.deepcopy(document)
    paths = list(field_paths(document))[1:]
    for _ in range(data.draw(st.integers(1, 3))):
        path = data.draw(st.sampled_from(paths))
        parent = damaged
        try:
            for key in path[:-1]:
                parent = parent[key]
            if data.draw(st.booleans()) and isinstance(parent, dict):
                parent.pop(path[-1], None)
            else:
                parent[path[-1]] = data.draw(CONFIG_VALUES)
        except (KeyError, IndexError, TypeError):
            continue  # an earlier damage removed or replaced this path
    try:
        load(damaged)
    except error as exc:
        assert str(exc).startswith("<mapping>") and "\n" not in str(exc)


def test_damaged_pings_keep_their_valid_rows():
    """The screening the fuzzing relies on, on one ping whose damage is known."""
    layout = LAYOUTS["browne_ring"]
    ping = replace(ring_frame(3, n=6), layout=layout.name)
    tof = ping.tof.copy()
    tof[0] = [np.nan, np.nan]
    tof[1, 0] = -1.0
    screened = screen_ping(replace(ping, tof=tof), layout)
    assert screened.echoes.n_echoes == 5 and screened.problems == {"empty_row": 1, "not_positive_tof": 1}
