"""What every node checks of an input message's header before it uses it: frame, order, losses.

One :class:`TopicCheck` per subscribed topic and node.  It refuses, counting
each by reason on ``/diagnostics`` (:meth:`NodeHealth.problem`, warning
throttled):

* ``empty_frame_id`` -- a header without a frame;
* ``wrong_frame_id`` -- a frame other than the one the node expects
  (parameter ``frame_id``; empty: any frame, i.e. the driver's);
* ``future_stamp`` -- a stamp more than ``future_tolerance`` seconds ahead of
  the node clock (not checked while that clock reads zero: simulated time
  before the first ``/clock``);
* ``duplicate_stamp`` -- the stamp of the last accepted message again (a ping
  published twice: the mapper must not integrate it twice);
* ``out_of_order_stamp`` -- older than the last accepted message.

When the node clock jumps backwards (a bag replayed in a loop with
``use_sim_time``) the order starts afresh (counted as ``clock jumped back``).
It also counts ``dropped_input (<topic>)``: messages a publisher sent that the
node never took, found from gaps in the publishers' sequence numbers -- pings that arrived
faster than the node works are dropped by the bounded subscription queue
(depth 5, sensor-data QoS), never queued without bound, and this is where they
are counted.

The clock is a function giving integer ns, so ``sonar-ring process`` checks
headers against bag time with the same class (:func:`node_clock` gives a
node's).  The nodes subscribe to ``Echoes`` serialized:
:meth:`TopicCheck.take_echoes` decodes a message
(:func:`~sonar_ring.ros.convert.echoes_from_cdr`; bytes that are not a whole
message count as ``malformed_message``) and checks its header; what is usable
of its arrays is then :func:`sonar_ring.ping_stage.check_ping`'s to say, the
one check of a ping's arrays.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable

from sonar_ring.echoes import EchoArrays
from sonar_ring.ros.convert import MessageError, MessageHeader, echoes_from_cdr
from sonar_ring.ros.diagnostics import NodeHealth
from sonar_ring.ros.params import Param

EXPECTED_FRAME = Param("frame_id", "", "frame that incoming pings must carry (empty: any frame, the driver's)")
FUTURE_TOLERANCE = Param("future_tolerance", 1.0, "largest lead of an input stamp over this node's clock, s; "
                         "messages stamped later are dropped", low=0.0, high=3600.0)
PUBLISHERS_TRACKED = 16
"""Publishers whose sequence numbers are followed per topic (a restarted publisher is a new one)."""


def stamp_ns(header) -> int:
    """A header's stamp (:data:`~sonar_ring.ros.convert.AnyHeader`) in integer nanoseconds."""
    return header.stamp.sec * 10**9 + header.stamp.nanosec


def node_clock(node) -> Callable[[], int]:
    """The reading of ``node``'s clock (ROS time or ``/clock``), integer ns, as a function.

    The clock's own reading: ``Clock.now()`` builds a Time object around it, and
    a ping's checks read it once per topic.
    """
    handle = node.get_clock().handle
    return lambda: handle.get_now().nanoseconds


class TopicCheck:
    """The header checks and loss count of one input topic of one node.

    Parameters
    ----------
    clock : callable
        The node clock's time, integer ns (:func:`node_clock`; bag time offline).
    health : NodeHealth or Counts
        Where refusals and losses are counted.
    topic : str
        Input topic, for the log lines.
    params : dict
        The node's live parameter values (:func:`sonar_ring.ros.params.declare`);
        ``future_tolerance`` and, if given, ``frame_param`` are read at every message.
    frame_param : str or None
        Parameter naming the frame the messages must carry (empty value: any
        non-empty frame); None: the frame is not checked (the driver's
        ``tof_in``, which it restamps with its own ``frame_id``).
    on_clock_jump : callable, optional
        Called when the node clock jumped backwards, for state kept in stamp
        order (the mapper's odometry history).
    """

    def __init__(self, clock: Callable[[], int], health: NodeHealth, topic: str, params: dict,
                 frame_param: str | None = EXPECTED_FRAME.name, on_clock_jump: Callable[[], None] | None = None
                 ) -> None:
        self._clock = clock
        self._health = health
        self._topic = topic
        self._params = params
        self._frame_param = frame_param
        self._on_clock_jump = on_clock_jump
        self._last_stamp: int | None = None
        self._last_clock = 0
        self._sequences: OrderedDict[bytes, int] = OrderedDict()

    def admit(self, header, info=None) -> bool:
        """True if a message with ``header`` may be used; otherwise count why not.

        ``info`` is the ``MessageInfo`` rclpy passes to a two-argument
        subscription callback; with it, messages lost before this one are counted.
        """
        self.count_lost(info)
        reason, detail = self._refusal(header)
        if reason:
            self._health.problem(reason, f"{self._topic}: {detail}")
            return False
        return True

    def _refusal(self, header) -> tuple[str, str]:
        if self._frame_param is not None:
            expected = self._params[self._frame_param]
            if not header.frame_id:
                return "empty_frame_id", "message without a frame_id"
            if expected and header.frame_id != expected:
                return "wrong_frame_id", f"frame {header.frame_id!r}, expected {expected!r}"
        stamp = stamp_ns(header)
        now = self._clock()
        if now < self._last_clock:
            self._health.note("clock jumped back")
            self._last_stamp = None
            if self._on_clock_jump:
                self._on_clock_jump()
        self._last_clock = now
        lead = (stamp - now) * 1e-9
        if now > 0 and lead > self._params[FUTURE_TOLERANCE.name]:
            return "future_stamp", f"stamp {lead:.3f} s ahead of the node clock"
        if self._last_stamp is not None and stamp <= self._last_stamp:
            if stamp == self._last_stamp:
                return "duplicate_stamp", f"stamp {stamp} ns again"
            return "out_of_order_stamp", f"stamp {(self._last_stamp - stamp) * 1e-9:.3f} s older than the last"
        self._last_stamp = stamp
        return "", ""

    def count_lost(self, info) -> None:
        """Count the messages lost before the one ``info`` (its ``MessageInfo``, or None) came with."""
        if info is None:
            return
        sequence = info.get("publication_sequence_number")
        publisher = info.get("publisher_gid")
        if sequence is None or publisher is None:
            return
        key = bytes(publisher["data"])
        last = self._sequences.pop(key, None)
        self._sequences[key] = sequence
        if len(self._sequences) > PUBLISHERS_TRACKED:
            self._sequences.popitem(last=False)
        if last is not None and sequence > last + 1:
            self._health.problem(f"dropped_input ({self._topic})", f"{sequence - last - 1} messages arrived faster "
                                 "than this node works", count=sequence - last - 1)

    def take_echoes(self, data: bytes, info) -> tuple[MessageHeader, EchoArrays] | None:
        """A serialized Echoes message decoded and its header admitted, or None after counting why not.

        ``info`` is the message's ``MessageInfo`` (or None); the messages lost before
        it are counted even when it does not decode.
        """
        try:
            header, echoes = echoes_from_cdr(data)
        except MessageError as error:
            self.count_lost(info)
            self._health.problem("malformed_message", str(error))
            return None
        return (header, echoes) if self.admit(header, info) else None
