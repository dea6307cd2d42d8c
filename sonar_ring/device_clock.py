"""The device's clock on the host's time line: a ping's stamp is when its transmitter fired.

A frame carries the device time ``t`` (µs, the device's own clock) at which the
ping's transmitter fired, and reaches the host a transport delay ``d >= 0``
later.  Over minutes the two clocks differ by an offset and a rate, the drift
(a device clock 50 ppm fast gains 50 µs a second), so the frame arrives on the
host clock at

    arrival = offset + t / (1 + drift) + d.

Every point ``(t, arrival - t)`` therefore lies on or above a straight line,
and the least-delayed frames lie closest to it.  :class:`DeviceClock` keeps the
lower convex hull of these points and takes the line below all of them that is
nearest to them on average (the linear programme of Moon, Skelly & Towsley,
"Estimation and removal of clock skew from network delay measurements", 1999;
the one-way case of TICSync, Harrison & Newman, 2011): its error comes from the
delays of the few fastest frames, not from the mean or the spread of the
delays, so stalls and jitter leave the stamps alone.  With delays spread evenly
over ``R``, ``n`` frames put the line within about ``R / n`` of the truth.

The hull covers a sliding window (between 3/4 of ``window`` and ``window``
seconds of frames) so that the estimate follows a drift that changes with
temperature.  The estimate starts over when the device restarts (its time goes
back) or the clocks jump apart (a frame arrives more than ``resync`` seconds
before the estimate says its ping fired, or every frame for ``resync`` seconds
arrives more than ``resync`` late: the host clock was stepped).

No ROS here: the driver feeds it (device time, arrival) per frame and
publishes the stamps it returns.
"""

from __future__ import annotations

import bisect
from collections import deque

import numpy as np

MAX_DRIFT = 1e-3
"""Largest clock rate difference believed, s/s (1000 ppm; crystals are within 100 ppm).

Bounds the drift fitted to the first few frames, whose line the delays of
only two points decide."""
HULLS = 4
"""Hulls over staggered stretches of the window, one begun every ``window / HULLS``: the oldest gives the estimate.

When it goes, the next one has ``(HULLS - 1) / HULLS`` of the window: the estimate never drops to few frames."""
DELAY_WINDOW = 1000
"""Frames whose arrival delays :meth:`DeviceClock.delays` keeps."""


class _LowerHull:
    """Lower convex hull of points ``(x, y)`` added with non-decreasing ``x``, and the mean ``x`` of all of them."""

    def __init__(self) -> None:
        self.x: list[float] = []
        self.y: list[float] = []
        self.count = 0
        self._sum_x = 0.0

    def add(self, x: float, y: float) -> None:
        self.count += 1
        self._sum_x += x
        if self.x and x == self.x[-1]:
            if y >= self.y[-1]:
                return
            self.x.pop()
            self.y.pop()
        # Drop the last vertex while it is not strictly below the segment from the one before it to the new point.
        while len(self.x) >= 2 and ((self.y[-1] - self.y[-2]) * (x - self.x[-2])
                                    >= (y - self.y[-2]) * (self.x[-1] - self.x[-2])):
            self.x.pop()
            self.y.pop()
        self.x.append(x)
        self.y.append(y)

    def span(self) -> float:
        return self.x[-1] - self.x[0] if self.x else 0.0

    def line(self, max_slope: float) -> tuple[float, float]:
        """``(intercept, slope)`` of the line below every point with the least mean vertical distance to them.

        That line runs along the hull edge over the points' mean ``x``; its
        slope is bounded to ``±max_slope``.
        """
        if len(self.x) == 1:
            return self.y[0], 0.0
        mean_x = self._sum_x / self.count
        right = min(max(bisect.bisect_right(self.x, mean_x), 1), len(self.x) - 1)
        slope = (self.y[right] - self.y[right - 1]) / (self.x[right] - self.x[right - 1])
        if abs(slope) <= max_slope:
            return self.y[right] - slope * self.x[right], slope
        slope = float(np.clip(slope, -max_slope, max_slope))
        return min(y - slope * x for x, y in zip(self.x, self.y, strict=True)), slope


class DeviceClock:
    """Online estimate of the host time at which the device's clock read a given value.

    Parameters
    ----------
    window : float
        Seconds of device time the estimate looks back over, at most (at least 3/4 of it once that much has passed).
    resync : float
        Seconds by which arrivals may disagree with the estimate before it starts over (see the module docstring).

    Attributes
    ----------
    restarts : int
        Times the estimate started over after its first frame (device restarts and clock jumps).
    """

    def __init__(self, window: float = 60.0, resync: float = 1.0) -> None:
        if not window > 0 or not resync > 0:
            raise ValueError(f"window and resync must be positive seconds, got {window}, {resync}")
        self._window = window
        self._resync = resync
        self._delays: deque[float] = deque(maxlen=DELAY_WINDOW)
        self.restarts = 0
        self._origin: tuple[int, int] | None = None
        self._last_device_us: int | None = None
        self._forget()

    def _forget(self) -> None:
        """No points, no line."""
        self._hulls = [_LowerHull()]
        self._line = (0.0, 0.0)
        self._late_since: float | None = None

    def _start(self, device_time_us: int, arrival_ns: int) -> None:
        """Forget every point: the estimate starts from this frame, the origin of its coordinates."""
        if self._origin is not None:
            self.restarts += 1
        self._origin = (device_time_us, arrival_ns)
        self._forget()

    def stamp(self, device_time_us: int, arrival_ns: int) -> int:
        """The host time, ns on the arrival clock, at which the device clock read ``device_time_us``.

        ``arrival_ns`` is when the frame carrying it was read (ns, host clock).
        Frames come in the device's order (duplicates and late frames already
        dropped, :class:`sonar_ring.frames.FrameSequence`).  The result is
        never after ``arrival_ns``.
        """
        if self._origin is None or device_time_us < self._last_device_us:
            self._start(device_time_us, arrival_ns)  # the first frame, or the device restarted
        x, y = self._point(device_time_us, arrival_ns)
        if y < self._fired(x) - self._resync:
            self._start(device_time_us, arrival_ns)  # the device's time leapt ahead, or the host clock went back
            x, y = 0.0, 0.0
        self._add(x, y)
        if self._persistently_late(x, y - self._fired(x)):
            self._start(device_time_us, arrival_ns)  # the host clock was stepped forward
            x, y = 0.0, 0.0
            self._add(x, y)
        self._last_device_us = device_time_us
        fired = self._fired(x)
        self._delays.append(y - fired)
        return self._origin[1] + round((x + fired) * 1e9)

    def _point(self, device_time_us: int, arrival_ns: int) -> tuple[float, float]:
        """Device seconds since the origin, and arrival minus device time relative to the origin's, s."""
        origin_device_us, origin_arrival_ns = self._origin
        device_ns = (device_time_us - origin_device_us) * 1000
        return device_ns * 1e-9, ((arrival_ns - origin_arrival_ns) - device_ns) * 1e-9

    def _fired(self, x: float) -> float:
        """The estimated firing time minus the device time at ``x``, s, relative to the origin's."""
        intercept, slope = self._line
        return intercept + slope * x

    def _add(self, x: float, y: float) -> None:
        for hull in self._hulls:
            hull.add(x, y)
        if self._hulls[-1].span() >= self._window / HULLS:
            self._hulls = [*self._hulls[1 - HULLS:], _LowerHull()]
        self._line = self._hulls[0].line(MAX_DRIFT)

    def _persistently_late(self, x: float, delay: float) -> bool:
        """Whether every frame for ``resync`` seconds of device time arrived more than ``resync`` late."""
        if delay <= self._resync:
            self._late_since = None
            return False
        if self._late_since is None:
            self._late_since = x
        return x - self._late_since >= self._resync

    @property
    def drift(self) -> float:
        """How much faster the device clock runs than the host's, s/s (50e-6: 50 ppm fast); 0 before two frames."""
        slope = self._line[1]
        return -slope / (1.0 + slope)

    @property
    def offset(self) -> float:
        """Host time minus device time at the device's latest frame, s (nan before the first frame)."""
        if self._origin is None:
            return float("nan")
        origin_device_us, origin_arrival_ns = self._origin
        x = (self._last_device_us - origin_device_us) * 1e-6
        return (origin_arrival_ns - origin_device_us * 1000) * 1e-9 + self._fired(x)

    def delays(self) -> np.ndarray:
        """Arrival minus estimated firing time of the recent frames, s, oldest first (at most the last 1000)."""
        return np.asarray(self._delays)
