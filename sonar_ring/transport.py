"""Byte transports to the ring electronics: serial, UDP and TCP, with reconnection.

:class:`HardwareReader` runs one background thread that opens the device, reads
bytes, decodes frames (:mod:`sonar_ring.frames`) and hands each frame to a
callback.  When the device goes away (cable unplugged, TCP reset, UDP silence
longer than ``silence_timeout``) it closes, waits with exponential back-off
(``min_backoff`` doubling up to ``max_backoff``) and opens again, without the
caller noticing more than the counts of :meth:`HardwareReader.counts`.

Device addresses:

* ``serial:///dev/ttyUSB0?baud=921600`` -- pyserial;
* ``udp://0.0.0.0:5600`` -- listen for datagrams, one frame each;
* ``tcp://192.168.1.50:5601`` -- connect to the device.
"""

from __future__ import annotations

import socket
import threading
from collections import Counter
from collections.abc import Callable
from urllib.parse import parse_qs, urlparse

from sonar_ring.frames import EchoFrame, FrameDecoder

READ_SIZE = 65536


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
    def __init__(self, host: str, port: int, timeout: float):
        self._socket = socket.create_connection((host, port), timeout=timeout)

    def read(self) -> bytes:
        try:
            data = self._socket.recv(READ_SIZE)
        except TimeoutError:
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
    """Background reader of one device; frames go to ``on_frame`` (from its thread).

    The counters are written by the reader thread; read them with :meth:`counts`.
    """

    def __init__(self, address: str, on_frame: Callable[[EchoFrame], None], *, silence_timeout: float = 2.0,
                 min_backoff: float = 0.1, max_backoff: float = 5.0, read_timeout: float = 0.1) -> None:
        self.kind, self._args = parse_device(address)
        self.address = address
        self._on_frame = on_frame
        self._silence_timeout = silence_timeout
        self._min_backoff = min_backoff
        self._max_backoff = max_backoff
        self._read_timeout = read_timeout
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"sonar_ring reader {address}", daemon=True)
        self.decoder = FrameDecoder()
        self._events: Counter[str] = Counter()
        self._counts_lock = threading.Lock()
        self.connected = threading.Event()

    def counts(self) -> Counter:
        """Connection events and dropped bytes since start, a copy safe to read from any thread.

        ``connected``; ``device lost: <error>`` (cable unplugged, connection
        reset), ``device silent`` (no bytes for ``silence_timeout``), ``device
        open failed: <error>``; and the decoder's drops as ``frame_<reason>``
        (:class:`sonar_ring.frames.FrameDecoder`).
        """
        with self._counts_lock:
            return self._events + Counter({f"frame_{reason}": n for reason, n in self.decoder.errors.items()})

    def _count(self, event: str) -> None:
        with self._counts_lock:
            self._events[event] += 1

    def start(self) -> None:
        """Start reading in the background."""
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the thread and close the device."""
        self._stop.set()
        self._thread.join(timeout)

    def _open(self):
        opener = {"serial": _Serial, "udp": _Udp, "tcp": _Tcp}[self.kind]
        return opener(**self._args, timeout=self._read_timeout)

    def _run(self) -> None:
        backoff = self._min_backoff
        while not self._stop.is_set():
            try:
                device = self._open()
            except (OSError, ValueError) as error:
                self._count(f"device open failed: {type(error).__name__}")
                self._stop.wait(backoff)
                backoff = min(2 * backoff, self._max_backoff)
                continue
            self._count("connected")
            self.connected.set()
            try:
                self._read_until_lost(device)
                backoff = self._min_backoff
            except OSError as error:
                if not isinstance(error, TimeoutError):
                    self._count(f"device lost: {type(error).__name__}")
            finally:
                self.connected.clear()
                device.close()
            if not self._stop.is_set():
                self._stop.wait(backoff)
                backoff = min(2 * backoff, self._max_backoff)

    def _read_until_lost(self, device) -> None:
        silent = 0.0
        datagrams = getattr(device, "datagrams", False)
        while not self._stop.is_set():
            data = device.read()
            if not data:
                silent += self._read_timeout
                if silent >= self._silence_timeout:
                    self._count("device silent")
                    raise TimeoutError(f"no bytes for {self._silence_timeout} s")
                continue
            silent = 0.0
            with self._counts_lock:
                frames = self.decoder.feed_datagram(data) if datagrams else self.decoder.feed(data)
            for frame in frames:
                self._on_frame(frame)
