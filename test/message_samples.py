"""Deterministic Echoes / LandmarkArray samples shared by a test and its DDS peer."""

import numpy as np
from std_msgs.msg import Header

from sonar_ring.echoes import EchoArrays
from sonar_ring.ros.convert import echoes_to_msg

SAMPLE_NAMES = ("empty", "ring", "triad", "large")


def sample_arrays(name: str) -> EchoArrays:
    rng = np.random.default_rng(SAMPLE_NAMES.index(name))
    n, k, amplitude, phase = {"empty": (0, 2, False, False), "ring": (144, 2, True, False),
                              "triad": (5, 3, True, True), "large": (50_000, 2, True, False)}[name]
    tof = rng.uniform(1e-4, 3e-2, (n, k))
    if n:
        tof[::7, 1] = np.nan
    return EchoArrays(
        layout=f"layout-{name}",
        speed_of_sound=343.2 + SAMPLE_NAMES.index(name),
        group=rng.integers(0, 48, n).astype(np.uint16),
        transmitter=rng.integers(0, 2, n).astype(np.uint8),
        tof=tof,
        amplitude=rng.uniform(0, 1, (n, k)).astype(np.float32) if amplitude else np.empty((n, 0), np.float32),
        phase_delay=rng.uniform(0, 2.5e-5, (n, k - 1)) if phase else np.empty((n, 0)),
    )


def sample_message(name: str):
    header = Header(frame_id=f"sample/{name}")
    header.stamp.sec, header.stamp.nanosec = 1700000000 + SAMPLE_NAMES.index(name), 123456789
    return echoes_to_msg(sample_arrays(name), header)
