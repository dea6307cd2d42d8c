"""The hardware reader loses its device -- serial unplugged, UDP silent, TCP reset -- and recovers by itself.

Everything runs on this machine: a pseudo-terminal pair stands in for the USB
serial adapter (reached through a symlink, as udev's /dev/serial/by-id links
are, so it can be "plugged in" again), and UDP and TCP use 127.0.0.1.
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


def frame(sequence):
    """One frame of a one-echo ping of the Browne ring; its sequence number tells frames apart."""
    return encode_echoes(replace(ring_ping(sequence, n=1), transmitter=np.zeros(1, np.uint8)), sequence=sequence)


class Collector:
    """The reader's callback: frames by sequence number, from the reader's thread."""

    def __init__(self):
        self.sequences = []
        self._lock = threading.Lock()

    def __call__(self, decoded):
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


def test_udp_silence_reopens_the_socket_and_datagrams_flow_again(reader_of):
    port = free_port(socket.SOCK_DGRAM)
    reader, collector = reader_of(f"udp://127.0.0.1:{port}", silence_timeout=0.3)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        def send(data):
            sender.sendto(data, ("127.0.0.1", port))

        assert keep_sending(send, collector, 1)
        assert wait_for(lambda: reader.counts()["device silent"] >= 1)
        assert keep_sending(send, collector, 2)
        send(frame(3)[:-3])  # a datagram cut short is dropped, the next one decodes
        assert keep_sending(send, collector, 4)
    counts = reader.counts()
    assert counts["connected"] >= 2 and counts["frame_truncated"] > 0 and not collector.has(3)


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


def test_device_addresses_are_checked_before_anything_opens():
    assert parse_device("serial:///dev/ttyUSB0?baud=115200") == ("serial", {"path": "/dev/ttyUSB0", "baud": 115200})
    assert parse_device("udp://0.0.0.0:5600") == ("udp", {"host": "0.0.0.0", "port": 5600})
    for address, hint in (("udp://0.0.0.0", "udp://HOST:PORT"), ("tcp://:99999", "tcp://HOST:PORT"),
                          ("serial://", "serial:///dev/ttyUSB0"), ("usb://x", "scheme must be"),
                          ("serial:///dev/ttyUSB0?baud=fast", "baud")):
        with pytest.raises(DeviceError, match=hint):
            parse_device(address)
