"""Byte transports to the ring electronics: serial, UDP and TCP, with reconnection.

:class:`HardwareReader` runs one background thread that opens the device, reads
bytes, decodes frames (:mod:`sonar_ring.frames`), places them in the device's
sequence (:class:`sonar_ring.frames.FrameSequence`: frames lost, duplicates,
late frames, restarts) and hands each new frame, with the host time its bytes
were read, to a callback.

Nothing that can still deliver a frame is closed: a UDP socket listens for the
life of the reader, and silence (no bytes for ``silence_timeout``) is counted,
not acted on.  A serial port or TCP connection that fails (cable unplugged,
connection reset or closed by the device, a TCP peer that stopped answering
keep-alive probes) is closed and opened again after a back-off that starts at
``min_backoff`` and doubles, up to ``max_backoff``, while opening fails; every
read that brings bytes sets it back to ``min_backoff``.  The caller sees no
more of this than the counts of :meth:`HardwareReader.counts`.

Device addresses:

* ``serial:///dev/ttyUSB0?baud=921600`` -- pyserial;
* ``udp://0.0.0.0:5600`` -- listen for datagrams, one frame each;
* ``tcp://192.168.1.50:5601`` -- connect to the device.
"""

from __future__ import annotations

import socket
import threading
import time
from collections import Counter
from collections.abc import Callable
from urllib.parse import parse_qs, urlparse

from sonar_ring.frames import EchoFrame, FrameDecoder, FrameSequence

READ_SIZE = 65536
KEEPALIVE_INTERVAL = 1
"""Seconds between TCP keep-alive probes once the device has been silent for ``silence_timeout``."""
KEEPALIVE_PROBES = 3
"""Unanswered keep-alive probes after which the TCP connection counts as lost."""


class DeviceError(ValueError):
    """A device address that cannot be used (the text says what to write instead)."""


class _Serial:
    def __init__(self, path: str, baud: int, timeout: float):
        import serial  # pyserial: only needed by serial devices

        self._port = serial.Serial(path, baudrate=baud, timeout=timeout)

    def read(self) -> bytes:
        return self._port.read(max(1, self._port.in_waiting))

    def close(self) -> None:
        self._port.close()


class _Udp:
    datagrams = True

    def __init__(self, host: str, port: int, timeout: float):
        self._socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._socket.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._socket.bind((host, port))
        self._socket.settimeout(timeout)

    def read(self) -> bytes:
        try:
            return self._socket.recv(READ_SIZE)
        except TimeoutError:
            return b""

    def close(self) -> None:
        self._socket.close()


class _Tcp:
    def __init__(self, host: str, port: int, timeout: float, keepalive_idle: float):
        self._socket = socket.create_connection((host, port), timeout=timeout)
        # A device that lost power sends no reset: keep-alive probes find it gone, and a silent but
        # living device keeps its connection (closing it would lose the frames it sends next).
        self._socket.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        for option, value in (("TCP_KEEPIDLE", max(1, round(keepalive_idle))), ("TCP_KEEPINTVL", KEEPALIVE_INTERVAL),
                              ("TCP_KEEPCNT", KEEPALIVE_PROBES)):
            if hasattr(socket, option):  # Linux; elsewhere the system's keep-alive timing applies
                self._socket.setsockopt(socket.IPPROTO_TCP, getattr(socket, option), value)

    def read(self) -> bytes:
        try:
            data = self._socket.recv(READ_SIZE)
        except TimeoutError as error:
            if error.errno is not None:  # ETIMEDOUT: the keep-alive probes went unanswered, not the read timeout
                raise
            return b""
        if not data:
            raise ConnectionResetError("device closed the connection")
        return data

    def close(self) -> None:
        self._socket.close()


def parse_device(address: str) -> tuple[str, dict]:
    """Split a device address into its kind and the arguments to open it.

    Raises :class:`DeviceError` for an unknown scheme or a missing port/path.
    """
    parts = urlparse(address)
    if parts.scheme == "serial":
        if not parts.path:
            raise DeviceError(f"device {address!r}: write serial:///dev/ttyUSB0?baud=921600")
        baud = parse_qs(parts.query).get("baud", ["921600"])[0]
        if not baud.isdigit() or int(baud) == 0:
            raise DeviceError(f"device {address!r}: baud must be a positive integer, e.g. ?baud=921600")
        return "serial", {"path": parts.path, "baud": int(baud)}
    if parts.scheme in ("udp", "tcp"):
        try:
            port = parts.port
        except ValueError:
            port = None
        if not parts.hostname or port is None:
            raise DeviceError(f"device {address!r}: write {parts.scheme}://HOST:PORT")
        return parts.scheme, {"host": parts.hostname, "port": port}
    raise DeviceError(f"device {address!r}: scheme must be serial://, udp:// or tcp://")


class HardwareReader:
    """Background reader of one device; new frames go to ``on_frame(frame, arrival_ns)`` (from its thread).

    ``arrival_ns`` is ``clock()`` when the read that completed the frame
    returned, before decoding (ns; the driver passes its node clock).  The
    counters are written by the reader thread; read them with :meth:`counts`.
    """

    def __init__(self, address: str, on_frame: Callable[[EchoFrame, int], None], *, silence_timeout: float = 2.0,
                 min_backoff: float = 0.1, max_backoff: float = 5.0, read_timeout: float = 0.1,
                 clock: Callable[[], int] = time.time_ns) -> None:
        self.kind, self._args = parse_device(address)
        self.address = address
        self._on_frame = on_frame
        self._silence_timeout = silence_timeout
        self._min_backoff = min_backoff
        self._max_backoff = max_backoff
        self._read_timeout = read_timeout
        self._clock = clock
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"sonar_ring reader {address}", daemon=True)
        self.decoder = FrameDecoder()
        self._sequence = FrameSequence()
        self._events: Counter[str] = Counter()
        self._counts_lock = threading.Lock()
        self.connected = threading.Event()

    def counts(self) -> Counter:
        """Connection events, frames lost and dropped bytes since start, a copy safe to read from any thread.

        ``connected``; ``device lost: <error>`` (cable unplugged, connection
        reset or closed), ``device silent`` (once per spell of
        ``silence_timeout`` or more without bytes), ``device open failed:
        <error>``; from the frames' sequence numbers and device times
        (:class:`sonar_ring.frames.FrameSequence`) ``frames_lost`` (numbers
        skipped), ``duplicate_frame``, ``late_frame`` (both dropped),
        ``device restarted`` and ``sequence restarted``; and the decoder's
        drops as ``frame_<reason>`` (:class:`sonar_ring.frames.FrameDecoder`).
        """
        with self._counts_lock:
            return self._events + Counter({f"frame_{reason}": n for reason, n in self.decoder.errors.items()})

    def _count(self, event: str, count: int = 1) -> None:
        with self._counts_lock:
            self._events[event] += count

    def start(self) -> None:
        """Start reading in the background."""
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the thread and close the device."""
        self._stop.set()
        self._thread.join(timeout)

    def _open(self):
        if self.kind == "serial":
            return _Serial(**self._args, timeout=self._read_timeout)
        if self.kind == "udp":
            return _Udp(**self._args, timeout=self._read_timeout)
        return _Tcp(**self._args, timeout=self._read_timeout, keepalive_idle=self._silence_timeout)

    def _run(self) -> None:
        backoff = self._min_backoff
        while not self._stop.is_set():
            try:
                device = self._open()
            except (OSError, ValueError) as error:
                self._count(f"device open failed: {type(error).__name__}")
            else:
                self._count("connected")
                self.connected.set()
                try:
                    if self._read_until_lost(device):
                        backoff = self._min_backoff
                finally:
                    self.connected.clear()
                    device.close()
            if self._stop.wait(backoff):
                return
            backoff = min(2 * backoff, self._max_backoff)

    def _read_until_lost(self, device) -> bool:
        """Read until the device fails or the reader stops; whether any read brought bytes."""
        datagrams = getattr(device, "datagrams", False)
        last_bytes = time.monotonic()
        silent = False
        read_any = False
        while not self._stop.is_set():
            try:
                data = device.read()
            except OSError as error:
                self._count(f"device lost: {type(error).__name__}")
                return read_any
            if not data:
                if not silent and time.monotonic() - last_bytes >= self._silence_timeout:
                    silent = True
                    self._count("device silent")
                continue
            arrival_ns = self._clock()
            last_bytes = time.monotonic()
            silent = False
            read_any = True
            with self._counts_lock:
                frames = self.decoder.feed_datagram(data) if datagrams else self.decoder.feed(data)
            for frame in frames:
                self._deliver(frame, arrival_ns)
        return read_any

    def _deliver(self, frame: EchoFrame, arrival_ns: int) -> None:
        """Count the frame's place in the sequence; hand it on unless it is a duplicate or late."""
        place, lost = self._sequence.place(frame.sequence, frame.device_time_us)
        if lost:
            self._count("frames_lost", lost)
        if place in ("duplicate", "late"):
            self._count(f"{place}_frame")
            return
        if place != "next":
            self._count(place)
        self._on_frame(frame, arrival_ns)
