"""The C reference encoder for firmware (``firmware/sonar_ring_frame.h``) against the Python encoder and decoder.

A small C program, built here with the machine's C compiler (strict C99,
warnings as errors), encodes the README's example ping and a triad ping with
phase delays and prints the frames in hex; its bytes must be the Python
encoder's, and the decoder must read them back.
"""

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from test_frames import EXAMPLE_DEVICE_TIME_US, EXAMPLE_FRAME, EXAMPLE_PING, EXAMPLE_SEQUENCE, assert_same

from sonar_ring.echoes import EchoArrays
from sonar_ring.frames import FrameDecoder, encode_echoes

HEADER_DIRECTORY = Path(__file__).resolve().parents[1] / "firmware"
COMPILER = next((shutil.which(name) for name in ("cc", "gcc", "clang") if shutil.which(name)), None)

PROGRAM = r"""
#include <stdio.h>
#include "sonar_ring_frame.h"

static void print_frame(const srf_ping *ping, uint8_t *buffer, size_t capacity) {
    size_t length = srf_encode_echoes(ping, buffer, capacity);
    for (size_t i = 0; i < length; ++i) printf("%02x", buffer[i]);
    printf("\n");
}

int main(void) {
    /* The README's example: two rows of a Browne ring ping, amplitudes, the second receiver of row 1 missed. */
    const uint16_t group[] = {3, 17};
    const uint8_t transmitter[] = {0, 0};
    const uint32_t tof_ns[] = {5831000, 5902500, 12040500, SRF_NO_ECHO};
    const uint16_t amplitude[] = {40000, 38500, 12345, 0};
    const srf_ping example = {1000, 1234567890, 2, 2, SRF_FLAG_AMPLITUDE, 343200, group, transmitter, tof_ns,
                              amplitude, NULL};
    uint8_t frame[SRF_FRAME_SIZE(2, 2, SRF_FLAG_AMPLITUDE)];
    print_frame(&example, frame, sizeof frame);

    /* A Kreczmer triad: three receivers, phase delays (one negative), no amplitudes, a sequence about to wrap. */
    const uint16_t triad_group[] = {0};
    const uint8_t triad_transmitter[] = {0};
    const uint32_t triad_tof_ns[] = {4000000, 4000120, 3999950};
    const int32_t phase_ns[] = {118, -52};
    const srf_ping triad = {0xFFFFFFFFu, 77, 1, 3, SRF_FLAG_PHASE, 0, triad_group, triad_transmitter, triad_tof_ns,
                            NULL, phase_ns};
    uint8_t triad_frame[SRF_FRAME_SIZE(1, 3, SRF_FLAG_PHASE)];
    print_frame(&triad, triad_frame, sizeof triad_frame);

    /* A buffer one byte short: nothing written, length 0 (an empty line). */
    print_frame(&example, frame, sizeof frame - 1);
    return 0;
}
"""

TRIAD_PING = EchoArrays(layout="", speed_of_sound=0.0, group=np.zeros(1, np.uint16), transmitter=np.zeros(1, np.uint8),
                        tof=np.array([[4_000_000e-9, 4_000_120e-9, 3_999_950e-9]]),
                        amplitude=np.empty((1, 0), np.float32), phase_delay=np.array([[118e-9, -52e-9]]))


@pytest.fixture(scope="module")
def c_frames(tmp_path_factory):
    """The C program's output lines: the example frame, the triad frame, and the refused one."""
    if COMPILER is None:
        pytest.skip("no C compiler (cc, gcc or clang) on PATH to build the firmware encoder")
    build = tmp_path_factory.mktemp("firmware")
    (build / "encode.c").write_text(PROGRAM)
    subprocess.run([COMPILER, "-std=c99", "-Wall", "-Wextra", "-Wconversion", "-pedantic", "-Werror",
                    f"-I{HEADER_DIRECTORY}", "-o", str(build / "encode"), str(build / "encode.c")],
                   check=True, capture_output=True, text=True)
    return subprocess.run([str(build / "encode")], check=True, capture_output=True, text=True).stdout.split("\n")


def test_c_encoder_writes_the_readme_example_byte_for_byte(c_frames):
    assert bytes.fromhex(c_frames[0]) == EXAMPLE_FRAME == encode_echoes(EXAMPLE_PING, EXAMPLE_SEQUENCE,
                                                                        EXAMPLE_DEVICE_TIME_US)


def test_c_encoder_writes_phase_delays_as_the_python_one_and_the_decoder_reads_both(c_frames):
    python = encode_echoes(TRIAD_PING, sequence=0xFFFFFFFF, device_time_us=77)
    assert bytes.fromhex(c_frames[1]) == python
    decoder = FrameDecoder()
    (decoded,) = decoder.feed(bytes.fromhex(c_frames[1]))
    assert (decoded.sequence, decoded.device_time_us, decoded.speed_of_sound) == (0xFFFFFFFF, 77, 0.0)
    assert_same(decoded.echoes, TRIAD_PING)
    assert not decoder.errors


def test_c_encoder_refuses_a_buffer_too_small(c_frames):
    assert c_frames[2] == ""
