"""The generated interfaces: import, convert, and cross a process boundary over Fast DDS."""

import subprocess
import sys
import time
from pathlib import Path

import pytest
import rclpy
from message_samples import SAMPLE_NAMES, sample_arrays, sample_message
from numpy.testing import assert_array_equal
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sonar_ring.msg import Echoes, Landmark, LandmarkArray

from sonar_ring.ros.convert import MessageError, echoes_from_msg

pytestmark = pytest.mark.ros


def assert_same_echoes(received, expected):
    assert received.layout == expected.layout
    assert received.speed_of_sound == expected.speed_of_sound
    for field in ("group", "transmitter", "tof", "amplitude", "phase_delay"):
        assert_array_equal(getattr(received, field), getattr(expected, field), err_msg=field)


def test_generated_interfaces_have_documented_fields():
    assert {"header", "layout", "speed_of_sound", "receivers_per_group", "group", "transmitter", "tof",
            "amplitude", "phase_delay"} <= set(Echoes.get_fields_and_field_types())
    assert {"landmark_class", "position", "normal", "covariance", "confidence", "segment", "valid",
            "reason"} <= set(LandmarkArray.get_fields_and_field_types())
    assert (Landmark.UNKNOWN, Landmark.PLANE, Landmark.CORNER, Landmark.EDGE) == (0, 1, 2, 3)


def test_message_constants_are_the_core_codes():
    from sonar_ring import landmarks, localise

    for name in ("UNKNOWN", "PLANE", "CORNER", "EDGE"):
        assert getattr(Landmark, name) == getattr(landmarks, name)
    names = ("OK", "NOT_FINITE", "DEGENERATE", "NEGATIVE", "NO_INTERSECTION", "TOO_SHORT", "BELOW_HEIGHT", "BEHIND",
             "AMBIGUOUS", "NONE_VALID")
    assert [getattr(Landmark, name) for name in names] == [getattr(localise, name) for name in names]
    assert sorted(localise.REASONS) == [getattr(localise, name) for name in names]


@pytest.mark.parametrize("name", SAMPLE_NAMES)
def test_arrays_round_trip_through_a_message(name):
    expected = sample_arrays(name)
    assert_same_echoes(echoes_from_msg(sample_message(name)), expected)


def test_error_handling():
    message = sample_message("ring")
    message.tof = message.tof[:-1]
    with pytest.raises(MessageError, match=r"tof has 287 values, expected 288 for 144 echoes of 2 receivers"):
        echoes_from_msg(message)
    message = sample_message("triad")
    message.phase_delay = message.phase_delay[:3]
    with pytest.raises(MessageError, match="phase_delay has 3 values, expected 0 or 10"):
        echoes_from_msg(message)
    message = sample_message("ring")
    message.receivers_per_group = 1
    with pytest.raises(MessageError, match="receivers_per_group must be >= 2"):
        echoes_from_msg(message)
    message = sample_message("ring")
    message.transmitter = message.transmitter[:10]
    with pytest.raises(MessageError, match="transmitter has 10 values"):
        echoes_from_msg(message)


def test_messages_cross_processes_intact_over_dds():
    topic = f"round_trip_{time.monotonic_ns()}"
    peer = subprocess.Popen([sys.executable, str(Path(__file__).with_name("dds_peer.py")), topic])
    rclpy.init()
    try:
        node = rclpy.create_node("round_trip_listener")
        received = {}
        node.create_subscription(Echoes, topic, lambda m: received.setdefault(m.header.frame_id, m),
                                 QoSProfile(depth=len(SAMPLE_NAMES), reliability=ReliabilityPolicy.RELIABLE))
        deadline = time.monotonic() + 30
        while len(received) < len(SAMPLE_NAMES) and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
        assert sorted(received) == sorted(f"sample/{name}" for name in SAMPLE_NAMES)
        for name in SAMPLE_NAMES:
            message = received[f"sample/{name}"]
            sent = sample_message(name)
            assert (message.header.stamp.sec, message.header.stamp.nanosec) == (sent.header.stamp.sec, 123456789)
            assert message.receivers_per_group == sent.receivers_per_group
            assert_same_echoes(echoes_from_msg(message), sample_arrays(name))
        assert len(received["sample/large"].tof) == 100_000
    finally:
        rclpy.shutdown()
        peer.terminate()
        peer.wait(timeout=10)
