"""The hardware frame: the README's example, round trip, resynchronisation, corrupt input, the sequence."""

import re
import zlib
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from sonar_ring.echoes import EchoArrays
from sonar_ring.frames import FrameDecoder, FrameError, FrameSequence, encode_echoes

README = Path(__file__).resolve().parents[1] / "README.md"
EXAMPLE_FRAME = bytes.fromhex(
    "a55a 01 01 3200 cb"  # header: magic, version, type, payload length 50, check
    "e8030000 d202964900000000 0200 02 01 a03c0500"  # sequence, device time, N, K, flags, speed of sound
    "0300 00 58f95800 a4105a00 409c 6496"  # row 0: group, transmitter, TOF x 2, amplitude x 2
    "1100 00 34b9b700 ffffffff 3930 0000"  # row 1: the second receiver missed
    "1c59827c")  # CRC-32
"""The README's example frame: two echo rows of the Browne ring with amplitudes."""
EXAMPLE_PING = EchoArrays(layout="", speed_of_sound=343.2, group=np.array([3, 17], np.uint16),
                          transmitter=np.zeros(2, np.uint8),
                          tof=np.array([[5_831_000e-9, 5_902_500e-9], [12_040_500e-9, np.nan]]),
                          amplitude=np.array([[40000, 38500], [12345, np.nan]], np.float32) / np.float32(65535),
                          phase_delay=np.empty((2, 0)))
EXAMPLE_SEQUENCE, EXAMPLE_DEVICE_TIME_US = 1000, 1_234_567_890


def readme_example():
    """The README's example frame: its bytes, and the text beside them."""
    section = README.read_text().split("### Hardware frame")[1].split("\n## ")[0]
    block = section.split("```text\n")[1].split("```")[0]
    lines = [re.match(r"((?:[0-9a-f]{2} )*[0-9a-f]{2}) {2,}(.*)", line) for line in block.splitlines()]
    assert all(lines), "every line: bytes in hex, two spaces, what they mean"
    return bytes.fromhex(" ".join(line[1] for line in lines)), " ".join(line[2] for line in lines)


def test_the_readme_example_frame_decodes_to_the_values_it_states():
    data, text = readme_example()
    assert data == EXAMPLE_FRAME == encode_echoes(EXAMPLE_PING, EXAMPLE_SEQUENCE, EXAMPLE_DEVICE_TIME_US)
    decoder = FrameDecoder()
    (frame,) = decoder.feed(data)
    assert not decoder.errors
    assert (frame.sequence, frame.device_time_us, frame.speed_of_sound) == (1000, 1_234_567_890, 343.2)
    assert_same(frame.echoes, EXAMPLE_PING)
    echoes = frame.echoes
    stated = {int(number.replace(",", "")) for number in re.findall(r"\d[\d,]*", text)}
    payload_length = len(data) - 11
    decoded = {frame.sequence, frame.device_time_us, echoes.n_echoes, echoes.tof.shape[1],
               round(frame.speed_of_sound * 1000), payload_length, 255 - (2 + payload_length) % 256,
               *echoes.group.tolist(), *echoes.transmitter.tolist(),
               *np.round(echoes.tof[np.isfinite(echoes.tof)] * 1e9).astype(int).tolist(),
               *np.round(echoes.amplitude[np.isfinite(echoes.amplitude)] * 65535).astype(int).tolist()}
    assert decoded <= stated, f"the README does not state {decoded - stated}"
    assert f"0x{zlib.crc32(data[:-4]):08x}" in text and "missed" in text


def ring_ping(seed=0, n=144, k=2, amplitude=True, phase=False):
    rng = np.random.default_rng(seed)
    tof = rng.uniform(1e-4, 3.5e-2, (n, k))
    tof[::5, 0] = np.nan
    return EchoArrays(layout="", speed_of_sound=343.21, group=rng.integers(0, 48, n).astype(np.uint16),
                      transmitter=rng.integers(0, 2, n).astype(np.uint8), tof=tof,
                      amplitude=rng.uniform(0, 1, (n, k)).astype(np.float32) if amplitude
                      else np.empty((n, 0), np.float32),
                      phase_delay=rng.uniform(-2e-5, 2e-5, (n, k - 1)) if phase else np.empty((n, 0)))


def assert_same(decoded, sent):
    assert_array_equal(decoded.group, sent.group)
    assert_array_equal(decoded.transmitter, sent.transmitter)
    assert_allclose(decoded.tof, sent.tof, atol=0.5e-9, rtol=0)  # whole nanoseconds on the wire
    assert_array_equal(np.isnan(decoded.tof), np.isnan(sent.tof))
    if sent.amplitude.size:  # a receiver that missed has no amplitude
        assert_allclose(decoded.amplitude, np.where(np.isnan(sent.tof), np.nan, sent.amplitude), atol=1 / 65535)
    else:
        assert decoded.amplitude.shape == sent.amplitude.shape
    assert_allclose(decoded.phase_delay, sent.phase_delay, atol=0.5e-9, rtol=0)


@pytest.mark.parametrize("kwargs", [{}, {"n": 0}, {"k": 3, "phase": True}, {"amplitude": False}])
def test_frames_round_trip(kwargs):
    sent = ring_ping(**kwargs)
    decoder = FrameDecoder()
    (frame,) = decoder.feed(encode_echoes(sent, sequence=7, device_time_us=123456789))
    assert (frame.sequence, frame.device_time_us, frame.speed_of_sound) == (7, 123456789, 343.21)
    assert_same(frame.echoes, sent)
    assert not decoder.errors


def test_stream_split_anywhere_with_garbage_between_frames():
    pings = [ring_ping(seed) for seed in range(3)]
    stream = b"\x00\xa5junk" + encode_echoes(pings[0]) + b"\xa5\x5a\x09" + encode_echoes(pings[1]) \
        + encode_echoes(pings[2])
    decoder = FrameDecoder()
    frames = []
    for start in range(0, len(stream), 97):
        frames += decoder.feed(stream[start:start + 97])
    assert len(frames) == 3
    for frame, sent in zip(frames, pings, strict=True):
        assert_same(frame.echoes, sent)
    assert decoder.errors["garbage"] > 0 and decoder.errors["bad_header"] == 1


def test_corrupt_crc_is_dropped_and_the_next_frame_decodes():
    good = encode_echoes(ring_ping(1))
    bad = bytearray(encode_echoes(ring_ping(2)))
    bad[40] ^= 0xFF
    decoder = FrameDecoder()
    frames = decoder.feed(bytes(bad) + good)
    assert len(frames) == 1
    assert_same(frames[0].echoes, ring_ping(1))
    assert decoder.errors["bad_crc"] == 1


def test_truncated_frame_waits_then_completes():
    frame = encode_echoes(ring_ping(3))
    decoder = FrameDecoder()
    assert decoder.feed(frame[:-10]) == []
    assert len(decoder.feed(frame[-10:])) == 1


def test_datagram_cut_inside_a_frame_is_dropped_not_carried_over():
    frame = encode_echoes(ring_ping(4))
    decoder = FrameDecoder()
    assert decoder.feed_datagram(frame[:50]) == []
    assert decoder.errors["truncated"] == 50
    assert len(decoder.feed_datagram(frame)) == 1


def test_version_two_frames_are_refused_by_name():
    frame = bytearray(encode_echoes(ring_ping(5)))
    frame[2] = 2
    frame[6] = (frame[6] - 1) % 256  # keep the header check right, so the version is what is refused
    decoder = FrameDecoder()
    assert decoder.feed(bytes(frame)) == []
    assert decoder.errors["bad_version"] == 1


def test_error_handling():
    with pytest.raises(FrameError, match="exceeds 65535"):
        encode_echoes(ring_ping(n=8000))
    negative = ring_ping(n=2)
    negative.tof[0, 0] = -1.0
    with pytest.raises(FrameError, match=r"TOF must be in \[0, 4.29\) s"):
        encode_echoes(negative)



def test_sequence_places_frames_and_counts_the_ones_missing():
    sequence = FrameSequence()
    wrap = 2**32
    places = [sequence.place(number % wrap, 1000 * i) for i, number in
              enumerate([wrap - 3, wrap - 2, wrap + 1, wrap + 2, wrap + 6])]
    assert places == [("next", 0), ("next", 0), ("next", 2), ("next", 0), ("next", 3)]  # across the wrap
    assert sequence.place(6, 4000) == ("duplicate", 0)
    assert sequence.place(4, 3500) == ("late", 0)  # one of the three missing, overtaken by 6
    assert sequence.place(7, 5000) == ("next", 0)
    assert sequence.place(900, 20) == ("device restarted", 0)  # its clock went back
    assert sequence.place(901, 40) == ("next", 0)
    assert sequence.place(3, 60) == ("sequence restarted", 0)  # the clock went on, the number back
    assert sequence.place(4, 80) == ("next", 0)


def test_sequence_without_device_time_goes_by_the_numbers():
    sequence = FrameSequence()
    assert [sequence.place(number, 0) for number in (100, 101, 103, 103, 102, 104, 0)] == [
        ("next", 0), ("next", 0), ("next", 1), ("duplicate", 0), ("late", 0), ("next", 0), ("sequence restarted", 0)]
