"""screen_ping: what it keeps of a ping, what it counts, and the pings it refuses whole."""

import dataclasses

import numpy as np
from numpy.testing import assert_array_equal

from sonar_ring.echoes import EchoArrays, longest_tof, screen_ping
from sonar_ring.geometry import load_layout

RING = load_layout("browne_ring")
TRIAD = load_layout("kreczmer_triad")


def _ring_ping(tof, group=None, transmitter=None):
    tof = np.asarray(tof, dtype=float)
    rows = len(tof)
    return EchoArrays(RING.name, 343.0, np.arange(rows) if group is None else np.asarray(group),
                      np.zeros(rows, int) if transmitter is None else np.asarray(transmitter), tof,
                      np.empty((rows, 0)), np.empty((rows, 0)))


def test_bad_values_become_nan_and_bad_rows_go_each_counted():
    longest = longest_tof(RING)
    ping = _ring_ping([[5e-3, 6e-3], [np.inf, 5e-3], [-1e-3, 5e-3], [2 * longest, 5e-3], [np.nan, np.nan],
                       [5e-3, 5e-3], [5e-3, 5e-3]], group=[0, 1, 2, 3, 4, RING.n_groups, 6],
                      transmitter=[0, 0, 0, 0, 0, 0, 1])
    screened = screen_ping(ping, RING)
    assert screened.problems == {"unknown_group": 1, "unknown_transmitter": 1, "not_finite_tof": 1,
                                 "not_positive_tof": 1, "tof_too_long": 1, "empty_row": 1}
    assert_array_equal(screened.echoes.group, [0, 1, 2, 3])
    assert np.isnan(screened.echoes.tof[1:, 0]).all() and np.isfinite(screened.echoes.tof[:, 1]).all()


def test_a_triad_phase_delay_out_of_range_becomes_nan_and_is_counted():
    longest = longest_tof(TRIAD)
    ping = EchoArrays(TRIAD.name, 343.0, np.zeros(2, int), np.zeros(2, int), np.full((2, 3), 5e-3), np.empty((2, 0)),
                      np.array([[1e-6, np.nan], [2 * longest, -np.inf]]))
    screened = screen_ping(ping, TRIAD)
    assert screened.problems == {"bad_phase_delay": 2}
    assert_array_equal(np.isnan(screened.echoes.phase_delay), [[False, True], [True, True]])


def test_error_handling():
    """Pings that cannot be read are refused whole, with a reason and a detail; nothing raises."""
    good = _ring_ping(np.full((3, 2), 5e-3))
    refused = {
        "mismatched_rows": [dataclasses.replace(good, group=good.group[:2]),
                            dataclasses.replace(good, transmitter=good.transmitter[:2]),
                            dataclasses.replace(good, amplitude=np.ones((2, 2))),
                            dataclasses.replace(good, phase_delay=np.ones(3)),
                            dataclasses.replace(good, phase_delay=np.ones((2, 1)))],
        "wrong_receivers_per_group": [dataclasses.replace(good, tof=np.full((3, 3), 5e-3)),
                                      dataclasses.replace(good, tof=np.full(3, 5e-3))],
        "bad_speed_of_sound": [dataclasses.replace(good, speed_of_sound=speed) for speed in (np.nan, 100.0, 600.0)],
    }
    for reason, pings in refused.items():
        for ping in pings:
            screened = screen_ping(ping, RING)
            assert screened.echoes is None and screened.problems == {reason: 1} and screened.detail
    no_phase = EchoArrays(TRIAD.name, 343.0, np.zeros(1, int), np.zeros(1, int), np.full((1, 3), 5e-3),
                          np.empty((1, 0)), np.empty((1, 0)))
    assert screen_ping(no_phase, TRIAD).problems == {"missing_phase_delay": 1}
