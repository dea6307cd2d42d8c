"""The air's speed of sound from the map's sightings (sonar_ring.air)."""

import math

import numpy as np
import pytest

from sonar_ring import localise
from sonar_ring.air import AirSpeed
from sonar_ring.geometry import load_layout
from sonar_ring.uncertainty import position_jacobian

RING = load_layout("browne_ring")


def _ring_sightings(count, seed):
    """``count`` virtual-image landmarks 0.6-4 m in front of random pairs of the ring, up to 12 deg off their axes."""
    rng = np.random.default_rng(seed)
    group = rng.integers(0, len(RING.plan.yaw), count)
    bearing = RING.plan.yaw[group] + np.radians(rng.uniform(-12.0, 12.0, count))
    position = rng.uniform(0.6, 4.0, count)[:, None] * np.stack([np.cos(bearing), np.sin(bearing)], axis=-1)
    return RING.plan.transmitters[group, 0], RING.plan.receivers[group], position


def test_the_stretch_is_the_closed_forms_derivative_by_the_paths_scale():
    # what the SLAM's fit takes for a sighting's stretch: J d, the corner model's Jacobian times the paths
    transmitter, receivers, position = _ring_sightings(200, 1)
    estimate = localise.PointEstimate(position, np.ones(200, bool), np.zeros(200, np.int8), "corner")
    jacobian = position_jacobian(estimate, transmitter, receivers[:, 0], receivers[:, 1])
    paths = localise.reflector_paths(transmitter, receivers, position, np.zeros(200, bool))
    step = 1e-6
    for k in range(2):
        up, down = paths.copy(), paths.copy()
        up[:, k] += step
        down[:, k] -= step
        moved = [localise.corner(transmitter, receivers[:, 0], receivers[:, 1], p[:, 0], p[:, 1]).position
                 for p in (up, down)]
        assert np.allclose((moved[0] - moved[1]) / (2 * step), jacobian[:, :, k], atol=1e-6)
    # paths 1 + e times longer: the landmark moves by e J d, mostly along its line of sight (the scale) and, across
    # it, by up to about a millimetre a metre per unit of e
    stretched = localise.corner(transmitter, receivers[:, 0], receivers[:, 1], *(paths * (1 + step)).T).position
    stretch = np.einsum("nij,nj->ni", jacobian, paths)
    assert np.allclose((stretched - position) / step, stretch, atol=1e-5)
    moved = stretch - position
    across = np.abs(moved[:, 0] * position[:, 1] - moved[:, 1] * position[:, 0]) / np.linalg.norm(position, axis=1) ** 2
    assert 0.05 < across.max() < 0.3


def _entries(rng, count, sightings, e, noise):
    """Sightings of ``count`` entries, each with its own unknown value: points seen across their line of sight."""
    entry = np.repeat(np.arange(count), sightings)
    value = rng.normal(0.0, 3.0, (count, 2))[entry]
    angle = rng.uniform(0.0, 2 * np.pi, entry.size)
    observes = np.stack([-np.sin(angle), np.cos(angle)], axis=-1)
    stretch = rng.normal(0.0, 0.2, entry.size)
    variance = noise ** 2 * rng.uniform(0.5, 2.0, entry.size)
    measured = np.einsum("ni,ni->n", observes, value) - e * stretch + rng.normal(0.0, np.sqrt(variance))
    return entry, observes, measured, stretch, variance


def test_air_speed_is_found_whatever_the_entries_are():
    rng = np.random.default_rng(7)
    true_error = 0.0035
    z = []
    for _ in range(200):
        air = AirSpeed(prior_sigma=1.0)  # no prior to speak of: the data alone
        air.add(*_entries(rng, 30, 60, true_error, 0.03))
        error, sigma = air.fit()
        z.append((error - true_error) / sigma)
    # unbiased, and its standard deviation the one it reports
    assert abs(np.mean(z)) < 0.25 and 0.85 < np.std(z) < 1.15


def test_an_entrys_own_offset_does_not_count():
    rng = np.random.default_rng(3)
    entry, observes, measured, stretch, variance = _entries(rng, 10, 100, 0.004, 0.01)
    first, second = AirSpeed(0.01), AirSpeed(0.01)
    first.add(entry, observes, measured, stretch, variance)
    # entry 2 a metre off everywhere: what each of its sightings says against the others stays
    shifted = measured + np.where(entry == 2, observes @ np.array([1.0, -0.5]), 0.0)
    second.add(entry, observes, shifted, stretch, variance)
    assert np.allclose(first.fit(), second.fit(), rtol=1e-9, atol=1e-12)


def test_a_forgotten_entry_leaves_no_trace():
    rng = np.random.default_rng(4)
    good = _entries(rng, 10, 100, 0.002, 0.01)
    entry, observes, measured, stretch, variance = _entries(rng, 2, 100, -0.05, 0.01)
    alone, polluted = AirSpeed(0.01), AirSpeed(0.01)
    alone.add(*good)
    polluted.add(*good)
    polluted.add(entry + 100, observes, measured, stretch, variance)
    assert abs(polluted.fit()[0] - alone.fit()[0]) > 0.01
    polluted.forget([100, 101])
    assert np.allclose(polluted.fit(), alone.fit(), rtol=1e-9, atol=1e-12)


def test_the_prior_holds_the_estimate_until_sightings_outweigh_it():
    air = AirSpeed(0.0035)
    assert air.fit() == (0.0, 0.0035) and math.copysign(1.0, air.fit()[0]) == 1.0  # "+0.000 %", not "-0.000 %"
    rng = np.random.default_rng(5)
    air.add(*_entries(rng, 2, 3, 0.05, 0.03))  # a few noisy sightings: pulled little towards 5 %
    assert abs(air.fit()[0]) < 0.0035
    off = AirSpeed(0.0)  # the assumed air taken as right
    off.add(*_entries(rng, 10, 100, 0.05, 0.001))
    assert off.fit() == (0.0, 0.0) and off.sightings == 0


def test_error_handling():
    for prior in (-1e-3, math.nan, math.inf):
        with pytest.raises(ValueError, match="prior_sigma must be a finite number >= 0"):
            AirSpeed(prior)
    air = AirSpeed(0.0035)
    # rows with a non-finite value or no variance are left out; the rest count
    air.add([0, 0, 0, 1, 1], [[1.0, 0.0], [1.0, 0.0], [np.nan, 0.0], [0.0, 1.0], [0.0, 1.0]],
            [0.1, 0.2, 0.2, 0.3, np.inf], [0.1, 0.3, 0.1, 0.1, 0.1], [1e-4, 1e-4, 1e-4, 0.0, 1e-4])
    assert air.sightings == 2
    air.forget([7])  # an entry it never saw
    assert air.fit()[1] < 0.0035  # entry 0's two sightings disagree: they tell something


def test_a_new_session_keeps_what_the_old_one_gave_and_numbers_its_own_entries():
    rng = np.random.default_rng(6)
    first, second = _entries(rng, 10, 100, 0.003, 0.01), _entries(rng, 10, 100, 0.003, 0.01)
    together, sessions = AirSpeed(0.01), AirSpeed(0.01)
    together.add(*first)
    together.add(second[0] + 10, *second[1:])  # the second session's entries are other reflectors
    sessions.add(*first)
    sessions.start_session()
    sessions.add(*second)  # numbered from 0 again
    assert np.allclose(sessions.fit(), together.fit(), rtol=1e-9, atol=1e-12)
