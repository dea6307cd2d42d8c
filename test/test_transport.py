"""The hardware reader loses its device -- serial unplugged, UDP silent, TCP reset -- and recovers by itself.

Everything runs on this machine: a pseudo-terminal pair stands in for the USB
serial adapter (reached through a symlink, as udev's /dev/serial/by-id links
are, so it can be "plugged in" again), and UDP and TCP use 127.0.0.1.  Pauses,
restarts and frames left out on purpose: nothing the device sent while the
reader could keep it is lost, and what is lost is counted exactly.
"""

import os
import socket
import struct
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
from test_frames import ring_ping

from sonar_ring.frames import encode_echoes
from sonar_ring.transport import DeviceError, HardwareReader, parse_device

FAST = {"min_backoff": 0.05, "max_backoff": 0.2, "read_timeout": 0.05}
"""Reader timings that keep the tests short."""
PING_PERIOD_US = 33_333
"""Device time between the test frames' pings (the ring's 30 Hz)."""


def frame(sequence, device_time_us=None):
    """One frame of a one-echo ping of the Browne ring; its sequence number tells frames apart.

    Its device time is ``sequence`` ping periods after a second, unless given.
    """
    if device_time_us is None:
        device_time_us = 1_000_000 + (sequence % 2**32) * PING_PERIOD_US
    return encode_echoes(replace(ring_ping(sequence, n=1), transmitter=np.zeros(1, np.uint8)), sequence=sequence,
                         device_time_us=device_time_us)


class Collector:
    """The reader's callback: frames by sequence number, from the reader's thread."""

    def __init__(self):
        self.sequences = []
        self._lock = threading.Lock()

    def __call__(self, decoded, arrival_ns):
        with self._lock:
            self.sequences.append(decoded.sequence)

    def has(self, sequence):
        with self._lock:
            return sequence in self.sequences


def wait_for(condition, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.01)
    return condition()


def keep_sending(send, collector, sequence, timeout=5.0):
    """Send frame ``sequence`` every 20 ms until the reader delivered it; True if it did."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        send(frame(sequence))
        if wait_for(lambda: collector.has(sequence), timeout=0.02):
            return True
    return False


@pytest.fixture
def reader_of():
    readers = []

    def start(address, **kwargs):
        collector = Collector()
        reader = HardwareReader(address, collector, **{**FAST, **kwargs})
        reader.start()
        readers.append(reader)
        return reader, collector

    yield start
    for reader in readers:
        reader.stop()


def free_port(kind):
    with socket.socket(socket.AF_INET, kind) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class PlugablePty:
    """A pseudo-terminal behind a fixed path; unplugging closes it, plugging in makes a new one."""

    def __init__(self, link):
        self.link = link
        self.master = None
        self.plug()

    def plug(self):
        self.master, slave = os.openpty()
        target = os.ttyname(slave)
        os.close(slave)
        if os.path.lexists(self.link):
            os.unlink(self.link)
        os.symlink(target, self.link)

    def unplug(self):
        os.close(self.master)
        os.unlink(self.link)
        self.master = None

    def write(self, data):
        os.write(self.master, data)


def test_serial_adapter_unplugged_and_plugged_in_again(reader_of, tmp_path):
    pty = PlugablePty(tmp_path / "ttyRING")
    reader, collector = reader_of(f"serial://{tmp_path / 'ttyRING'}?baud=921600")
    assert wait_for(reader.connected.is_set)
    assert keep_sending(pty.write, collector, 1)
    pty.unplug()
    assert wait_for(lambda: reader.counts()["device lost: SerialException"] == 1)
    assert wait_for(lambda: reader.counts()["device open failed: SerialException"] >= 1)  # while unplugged
    pty.plug()
    assert wait_for(reader.connected.is_set)
    assert keep_sending(pty.write, collector, 2)
    assert reader.counts()["connected"] == 2
    pty.unplug()


def send_frames(send, sequences, device_times=None, spacing=0.002):
    """Send the frames of ``sequences`` (at ``device_times``, or their default), one every ``spacing`` seconds."""
    for sequence, device_time_us in zip(sequences, device_times or [None] * len(sequences), strict=True):
        send(frame(sequence, device_time_us))
        time.sleep(spacing)


def test_udp_senders_pausing_2_5_s_and_25_s_lose_no_frame_after_they_resume(reader_of):
    """Silence is counted, the socket stays open: every frame after the pause arrives, none counted lost.

    The two pauses run at once, each to its own reader.  The 2.5 s pause comes
    after 10 s of an idle device and a first burst, as at a robot's start.
    """
    schedules = {2.5: (10.0, 2.5), 25.0: (0.0, 25.0)}  # pause: (idle before the first burst, pause), s
    runs = {}
    for pause, (idle, gap) in schedules.items():
        port = free_port(socket.SOCK_DGRAM)
        reader, collector = reader_of(f"udp://127.0.0.1:{port}")  # default timings: silent after 2 s
        assert wait_for(reader.connected.is_set)

        def sender(port=port, idle=idle, gap=gap):
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
                def send(data):
                    udp.sendto(data, ("127.0.0.1", port))

                time.sleep(idle)
                send_frames(send, range(50), spacing=0.005)
                time.sleep(gap)
                send_frames(send, range(50, 350), spacing=0.005)

        thread = threading.Thread(target=sender)
        thread.start()
        runs[pause] = (reader, collector, thread)
    for pause, (reader, collector, thread) in runs.items():
        thread.join()
        assert wait_for(lambda collector=collector: collector.has(349)), f"{pause} s pause"
        assert collector.sequences == list(range(350)), f"{pause} s pause"
        counts = reader.counts()
        assert counts["frames_lost"] == 0 and counts["connected"] == 1, (pause, counts)
        assert counts["device silent"] >= 1, (pause, counts)


def test_tcp_reset_by_the_device_reconnects(reader_of):
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    server.settimeout(5)
    reader, collector = reader_of(f"tcp://127.0.0.1:{port}")
    with server:
        connection, _ = server.accept()
        assert keep_sending(connection.sendall, collector, 1)
        connection.sendall(frame(2)[:20])  # the reset cuts a frame in half
        connection.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        connection.close()  # linger 0: the close sends RST
        assert wait_for(lambda: reader.counts()["device lost: ConnectionResetError"] >= 1)
        connection, _ = server.accept()
        with connection:
            assert keep_sending(connection.sendall, collector, 3)
    assert reader.counts()["connected"] == 2 and not collector.has(2)


def test_a_restarting_tcp_device_is_read_again_within_the_least_back_off(reader_of):
    """Each restart (a reset, the device listening again) is read ``min_backoff`` + a read timeout later.

    Measured from the reset to the first frame of the new connection, with a
    second of slack for a busy machine; a back-off that kept doubling would
    wait 0.3, 0.6, 1.2, 2.4 and 4.8 s.
    """
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    server.settimeout(10)
    timings = {"min_backoff": 0.3, "max_backoff": 5.0, "read_timeout": 0.1}
    reader, collector = reader_of(f"tcp://127.0.0.1:{port}", **timings)
    waits = []
    with server:
        connection, _ = server.accept()
        for restart in range(6):
            assert keep_sending(connection.sendall, collector, 10 * restart)
            connection.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            connection.close()  # linger 0: the close sends RST
            reset = time.monotonic()
            if restart == 5:
                break
            connection, _ = server.accept()
            connection.sendall(frame(10 * restart + 1))
            assert wait_for(lambda restart=restart: collector.has(10 * restart + 1))
            waits.append(time.monotonic() - reset)
    assert max(waits) < timings["min_backoff"] + timings["read_timeout"] + 1.0, waits
    assert reader.counts()["connected"] == 6


class Transport:
    """A device on one transport, for the loss-counting test: its reader's address, and its bytes out."""

    def __init__(self, kind, tmp_path):
        self.kind = kind
        if kind == "udp":
            self._port = free_port(socket.SOCK_DGRAM)
            self.address = f"udp://127.0.0.1:{self._port}"
            self._socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        elif kind == "tcp":
            self._server = socket.create_server(("127.0.0.1", 0))
            self._server.settimeout(10)
            self.address = f"tcp://127.0.0.1:{self._server.getsockname()[1]}"
            self._socket = None  # the reader's connection, accepted at the first send
        else:
            self._pty = PlugablePty(tmp_path / "ttyRING")
            self.address = f"serial://{tmp_path / 'ttyRING'}?baud=921600"

    def send(self, data):
        if self.kind == "udp":
            self._socket.sendto(data, ("127.0.0.1", self._port))
        elif self.kind == "tcp":
            if self._socket is None:
                self._socket, _ = self._server.accept()
            self._socket.sendall(data)
        else:
            self._pty.write(data)

    def close(self):
        if self.kind == "serial":
            self._pty.unplug()
            return
        self._socket.close()
        if self.kind == "tcp":
            self._server.close()


@pytest.mark.parametrize("kind", ["udp", "tcp", "serial"])
def test_frames_left_out_by_the_device_are_counted_exactly_on_every_transport(reader_of, tmp_path, kind):
    """Gaps in the sequence, across its wrap from 2**32 - 1 to 0, count as ``frames_lost``, one for one.

    A duplicate and a frame overtaken by the next (as UDP may deliver them)
    are dropped and counted by name, not as lost frames, and a restarted
    device (its time back at zero) starts the sequence afresh.
    """
    device = Transport(kind, tmp_path)
    reader, collector = reader_of(device.address)
    assert wait_for(reader.connected.is_set)
    wrap = 2**32
    offsets = [*range(0, 10), *range(13, 19), *range(22, 30)]  # 10..12 and 19..21 (2**32 - 1, 0, 1) left out
    sent = [(wrap - 20 + offset) % wrap for offset in offsets]
    device_times = [1_000_000 + offset * PING_PERIOD_US for offset in offsets]
    send_frames(device.send, sent, device_times)
    late = 1_000_000 + 21 * PING_PERIOD_US
    send_frames(device.send, [sent[-1], 1], [device_times[-1], late])  # a duplicate; 1 overtaken by 2..9
    send_frames(device.send, [7, 8], [100, 100 + PING_PERIOD_US])  # the device restarted: 7 is its first ping
    assert wait_for(lambda: collector.has(8))
    counts = reader.counts()
    device.close()
    assert collector.sequences == [*sent, 7, 8]
    assert counts["frames_lost"] == 6
    assert (counts["duplicate_frame"], counts["late_frame"], counts["device restarted"]) == (1, 1, 1)


def test_device_addresses_are_checked_before_anything_opens():
    assert parse_device("serial:///dev/ttyUSB0?baud=115200") == ("serial", {"path": "/dev/ttyUSB0", "baud": 115200})
    assert parse_device("udp://0.0.0.0:5600") == ("udp", {"host": "0.0.0.0", "port": 5600})
    for address, hint in (("udp://0.0.0.0", "udp://HOST:PORT"), ("tcp://:99999", "tcp://HOST:PORT"),
                          ("serial://", "serial:///dev/ttyUSB0"), ("usb://x", "scheme must be"),
                          ("serial:///dev/ttyUSB0?baud=fast", "baud")):
        with pytest.raises(DeviceError, match=hint):
            parse_device(address)
