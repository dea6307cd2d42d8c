"""The generated interfaces: import, convert, and cross a process boundary over Fast DDS."""

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from builtin_interfaces.msg import Time
from hypothesis import given, settings
from hypothesis import strategies as st
from message_samples import SAMPLE_NAMES, sample_arrays, sample_message
from numpy.testing import assert_array_equal
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from sonar_ring.msg import Echoes, Landmark, LandmarkArray
from std_msgs.msg import Header

from sonar_ring.echoes import EchoArrays
from sonar_ring.geometry import load_layout
from sonar_ring.ros.bag import typestore
from sonar_ring.ros.convert import MessageError, as_message_types, echoes_from_cdr, echoes_to_msg, header_message
from sonar_ring.ros.ranges import range_messages

pytestmark = pytest.mark.ros


def decoded(message):
    """The arrays of an Echoes message object, through rclpy's serialization and :func:`echoes_from_cdr`."""
    return echoes_from_cdr(serialize_message(message))[1]


def assert_same_echoes(received, expected):
    assert received.layout == expected.layout
    assert received.speed_of_sound == expected.speed_of_sound
    for field in ("group", "transmitter", "tof", "amplitude", "phase_delay"):
        assert_array_equal(getattr(received, field), getattr(expected, field), err_msg=field)
        assert getattr(received, field).dtype == getattr(expected, field).dtype, field
        assert getattr(received, field).shape == getattr(expected, field).shape, field


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
             "AMBIGUOUS")
    assert [getattr(Landmark, name) for name in names] == [getattr(localise, name) for name in names]
    assert sorted(localise.REASONS) == [getattr(localise, name) for name in names]


@pytest.mark.parametrize("name", SAMPLE_NAMES)
def test_arrays_round_trip_through_a_message(name):
    message = sample_message(name)
    header, echoes = echoes_from_cdr(serialize_message(message))
    assert header_message(header) == message.header
    assert_same_echoes(echoes, sample_arrays(name))
    assert echoes.tof.flags.writeable and echoes.tof.flags.aligned


@pytest.mark.parametrize("name", [*SAMPLE_NAMES, "empty triad"])
def test_arrays_in_message_types_are_what_the_message_decodes_to(name):
    """What the driver hands on in one process is what a node decodes from its message."""
    if name == "empty triad":
        arrays = EchoArrays("kreczmer_triad", 343.0, np.empty(0, np.uint16), np.empty(0, np.uint8), np.empty((0, 3)),
                            np.empty((0, 3), np.float32), np.empty((0, 2)))
    else:
        arrays = sample_arrays(name)
    assert_same_echoes(as_message_types(arrays), decoded(echoes_to_msg(arrays, Header(frame_id="f"))))


def test_a_decoded_header_reads_and_publishes_as_the_message():
    message = Header(stamp=Time(sec=12, nanosec=345), frame_id="sonar_ring")
    header, _ = echoes_from_cdr(serialize_message(echoes_to_msg(sample_arrays("ring"), message)))
    assert (header.stamp.sec, header.stamp.nanosec, header.frame_id) == (12, 345, "sonar_ring")
    assert header_message(header) == message
    assert header_message(message) is message
    # typed publishers take it: the echoes and Range messages built from it carry the same header
    assert echoes_to_msg(sample_arrays("ring"), header).header == message
    assert {(m.header.stamp.sec, m.header.stamp.nanosec) for m in range_messages(load_layout("browne_ring"),
                                                                                  sample_arrays("ring"), header)} == {
        (12, 345)}


def test_a_string_is_cut_at_a_nul_inside_as_rclpy_reads_it():
    data = serialize_message(echoes_to_msg(sample_arrays("triad"), Header(frame_id="sonar\x01ring")))
    header, _ = echoes_from_cdr(data.replace(b"sonar\x01ring", b"sonar\x00ring"))
    assert header.frame_id == "sonar"


@pytest.mark.parametrize("little_endian", [True, False])
def test_cdr_of_another_writer_in_either_byte_order_decodes(little_endian):
    """rosbags' serializer, not rclpy's, in both byte orders CDR allows."""
    store = typestore()
    message = sample_message("triad")
    ours = store.deserialize_cdr(serialize_message(message), "sonar_ring/msg/Echoes")
    data = store.serialize_cdr(ours, "sonar_ring/msg/Echoes", little_endian=little_endian)
    header, echoes = echoes_from_cdr(bytes(data))
    assert header_message(header) == message.header
    assert_same_echoes(echoes, sample_arrays("triad"))
    assert echoes.tof.dtype.isnative


def test_error_handling():
    message = sample_message("ring")
    message.tof = message.tof[:-1]
    with pytest.raises(MessageError, match=r"tof has 287 values, expected 288 for 144 echoes of 2 receivers"):
        decoded(message)
    message = sample_message("triad")
    message.phase_delay = message.phase_delay[:3]
    with pytest.raises(MessageError, match="phase_delay has 3 values, expected 0 or 10"):
        decoded(message)
    message = sample_message("ring")
    message.receivers_per_group = 1
    with pytest.raises(MessageError, match="receivers_per_group must be >= 2"):
        decoded(message)
    message = sample_message("ring")
    message.transmitter = message.transmitter[:10]
    with pytest.raises(MessageError, match="transmitter has 10 values"):
        decoded(message)

    data = serialize_message(sample_message("triad"))
    for end in range(len(data)):  # cut anywhere: never a ping, never another exception
        with pytest.raises(MessageError, match="sonar_ring/Echoes"):
            echoes_from_cdr(data[:end])
    with pytest.raises(MessageError, match="not plain CDR"):
        echoes_from_cdr(b"\x00\x07\x00\x00" + data[4:])  # XCDR2
    frame_length = 4 + 8  # encapsulation, stamp: then the frame_id's length
    huge = bytearray(data)
    huge[frame_length:frame_length + 4] = (2**32 - 1).to_bytes(4, "little")
    with pytest.raises(MessageError, match="runs past the end"):
        echoes_from_cdr(bytes(huge))
    not_utf8 = bytearray(data)
    not_utf8[frame_length + 4] = 0xFF
    with pytest.raises(MessageError, match="not UTF-8"):
        echoes_from_cdr(bytes(not_utf8))
    unterminated = bytearray(data)
    length = int.from_bytes(data[frame_length:frame_length + 4], "little")
    unterminated[frame_length + 4 + length - 1] = ord("x")
    with pytest.raises(MessageError, match="lacks its NUL"):
        echoes_from_cdr(bytes(unterminated))


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 10**6), st.integers(1, 255)), min_size=1, max_size=8))
def test_damaged_cdr_gives_a_ping_or_a_message_error(flips):
    data = bytearray(serialize_message(sample_message("triad")))
    for where, mask in flips:
        data[where % len(data)] ^= mask
    try:
        _, echoes = echoes_from_cdr(bytes(data))
    except MessageError:
        return
    n, k = echoes.tof.shape
    assert echoes.group.shape == echoes.transmitter.shape == (n,) and k >= 2
    assert echoes.amplitude.shape in ((n, k), (n, 0)) and echoes.phase_delay.shape in ((n, k - 1), (n, 0))
    assert [echoes.group.dtype, echoes.tof.dtype, echoes.amplitude.dtype] == [np.uint16, np.float64, np.float32]


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
            assert_same_echoes(decoded(message), sample_arrays(name))
        assert len(received["sample/large"].tof) == 100_000
    finally:
        rclpy.shutdown()
        peer.terminate()
        peer.wait(timeout=10)
