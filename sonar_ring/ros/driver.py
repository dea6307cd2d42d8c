"""driver: echoes from the hardware, a topic or the scene simulator, one message per ping.

Publishes
    ``echoes`` (sonar_ring/Echoes, sensor-data QoS) -- every ping;
    ``range/group_NN`` (sensor_msgs/Range) -- per group, the nearest echo (REP 117), for Nav2,
    and the groups' frames on ``/tf_static`` (:mod:`sonar_ring.ros.ranges`);
    ``odom`` (nav_msgs/Odometry), ``truth/pose`` (nav_msgs/Odometry) and ``truth``
    (sonar_ring/LandmarkArray) -- ``source:=simulator`` only: what the robot's
    wheel odometry reports in ``odom`` (:mod:`sonar_ring.realism`), the true
    pose in the scene's ``world`` frame (for scoring, never for the mapper) and,
    per echo row, the true reflector class and position in the sensor frame
    (``valid`` false for an echo of no reflector: multipath, clutter, a late echo);
    ``/diagnostics``.
Subscribes
    ``tof_in`` (sonar_ring/Echoes) -- ``source:=topic`` only.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque
from dataclasses import replace

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.qos import qos_profile_sensor_data
from rclpy.subscription import MessageInfo
from rclpy.time import Time
from std_msgs.msg import Header

from sonar_ring.device_clock import DeviceClock
from sonar_ring.echoes import FASTEST_SPEED_OF_SOUND, SLOWEST_SPEED_OF_SOUND, EchoArrays
from sonar_ring.echoes import load_kernels as load_screening_kernels
from sonar_ring.frames import EchoFrame
from sonar_ring.geometry import load_layout, speed_of_sound
from sonar_ring.landmarks import make_landmarks
from sonar_ring.msg import Echoes
from sonar_ring.msg import LandmarkArray as LandmarkArrayMsg
from sonar_ring.ping_stage import check_ping
from sonar_ring.realism import DESCRIPTIONS, PROFILES, RANGES, World, scene_realism
from sonar_ring.ros.convert import AnyHeader, MessageHeader, as_message_types, echoes_to_msg, landmarks_to_msg
from sonar_ring.ros.diagnostics import NodeHealth
from sonar_ring.ros.inputs import FUTURE_TOLERANCE, TopicCheck, node_clock, stamp_ns
from sonar_ring.ros.node import SonarNode
from sonar_ring.ros.params import Param, declare
from sonar_ring.ros.ranges import RangeOutput, publish_group_frames
from sonar_ring.ros.run import spin
from sonar_ring.simulate import DIRECT, Noise, load_scene

SOURCES = ("hardware", "topic", "simulator")
STAMPS = ("device", "arrival")
DEFAULT_SPEED_OF_SOUND = float(speed_of_sound(20.0))
"""m/s in dry air at 20 degC, for sources that report none."""
REALISM_PREFIX = "realism."
"""The simulator's effect parameters: ``realism.<field>`` of :class:`sonar_ring.realism.Realism`."""
BASE_FRAME = "base_link"
"""The simulated robot's frame: the odometry's child (REP 105); the sensor sits at its origin."""
WORLD_FRAME = "world"
"""Frame of the simulator's true poses (``truth/pose``): the scene's."""
HARDWARE_QUEUE = 64
"""Decoded frames waiting to be published; older ones are dropped (and counted) beyond this."""

def _speed_of_sound_problem(value: float) -> str | None:
    if value == 0.0 or SLOWEST_SPEED_OF_SOUND <= value <= FASTEST_SPEED_OF_SOUND:
        return None
    return (f"speed_of_sound must be 0 or {SLOWEST_SPEED_OF_SOUND:g}..{FASTEST_SPEED_OF_SOUND:g} m/s (the pings "
            f"would all be refused as bad_speed_of_sound), got {value:g}")


PARAMS = [
    Param("source", "simulator", "where echoes come from", choices=SOURCES, read_only=True),
    Param("layout", "browne_ring", "sensor layout: a name in config/layouts or a YAML path", read_only=True),
    Param("frame_id", "sonar_ring", "frame of the echoes (sensor frame at the ring centre); the range frames hang "
          "from it on /tf_static", read_only=True),
    Param("device", "udp://0.0.0.0:5600", "hardware: serial:///dev/ttyUSB0?baud=921600, udp://HOST:PORT or "
          "tcp://HOST:PORT", read_only=True),
    Param("silence_timeout", 2.0, "hardware: seconds without bytes before the device is reported silent (and a TCP "
          "device is probed for life)", low=0.1, high=60.0, read_only=True),
    Param("stamp", "device", "hardware: a ping's stamp: `device` (when its transmitter fired: the frame's device "
          "time on the node clock, estimated online) or `arrival` (when its frame was read); a frame without "
          "device time is stamped on arrival", choices=STAMPS, read_only=True),
    Param("scene", "room", "simulator: a name in config/scenes or a YAML path", read_only=True),
    Param("world", "realistic", "simulator: the world's effects, a profile (realism.* parameters and the scene's "
          "realism block replace single fields)", choices=tuple(PROFILES), read_only=True),
    Param("ping_rate", 0.0, "simulator: pings per second (0: the layout's rate)", low=0.0, high=2000.0),
    Param("sigma_tof", 1e-6, "simulator: time-of-flight noise, s", low=0.0, high=1e-3),
    Param("sigma_amplitude", 0.02, "simulator: amplitude noise relative to A_max", low=0.0, high=1.0),
    Param("seed", 0, "simulator: noise seed", low=0, high=2**31 - 1, read_only=True),
    Param("loops", 0, "simulator: laps of the scene trajectory before stopping (0: forever)", low=0, high=10**6,
          read_only=True),
    Param("speed_of_sound", 0.0, f"m/s to use when the source gives none: 0 (20 degC dry air) or "
          f"{SLOWEST_SPEED_OF_SOUND:g}..{FASTEST_SPEED_OF_SOUND:g}, what the echo screening accepts",
          low=0.0, high=FASTEST_SPEED_OF_SOUND, check=_speed_of_sound_problem),
    Param("publish_range", True, "publish one sensor_msgs/Range per group on `range/group_NN`", read_only=True),
    FUTURE_TOLERANCE,
]


class Driver(SonarNode):
    """Publishes each ping of the selected source as one Echoes message."""

    def __init__(self, **kwargs) -> None:
        super().__init__("driver", **kwargs)
        self.params = declare(self, PARAMS, self._on_change)
        self.layout = load_layout(self.params["layout"])
        load_screening_kernels()  # now, or the first ping would wait for numba to load them
        self.health = NodeHealth(self, hardware_id=f"{self.params['source']}:{self.layout.name}")
        self._echo_publisher = self.create_publisher(Echoes, "echoes", qos_profile_sensor_data)
        if self.params["publish_range"]:
            self._ranges = RangeOutput(self, self.layout)
            self._frames_publisher = publish_group_frames(self, self.layout, self.params["frame_id"])
        self.pings_published = 0
        self.reader = None
        source = self.params["source"]
        if source == "simulator":
            self._start_simulator()
        elif source == "topic":
            self._check = TopicCheck(node_clock(self), self.health, "tof_in", self.params, frame_param=None)
            self.create_subscription(Echoes, "tof_in", self._on_topic, qos_profile_sensor_data, raw=True)
        else:
            self._start_hardware()

    # ------------------------------------------------------------------ sources

    def _start_simulator(self) -> None:
        self.scene = load_scene(self.params["scene"])
        profile = scene_realism(self.scene, self.params["world"])
        # Declared now: their defaults are the world's profile with the scene's realism block.
        realism = declare(self, realism_params(profile))
        self.realism = scene_realism(self.scene, self.params["world"], {
            name.removeprefix(REALISM_PREFIX): value for name, value in realism.items()}, where="parameter realism")
        rate = self.params["ping_rate"] or self.layout.ping_rate
        self.world = World(self.scene, self.layout, self.realism, noise=self._noise(), seed=self.params["seed"],
                           ping_rate=rate)
        if self.scene.trajectory is not None:
            self._poses = self.scene.trajectory.poses(rate)[1]
        else:
            self._poses = self.scene.sensor_pose[None, :]
        self._pose_index = 0
        self.pings_simulated = 0
        self._laps_left = self.params["loops"] or -1
        self._odom_publisher = self.create_publisher(Odometry, "odom", 10)
        self._true_pose_publisher = self.create_publisher(Odometry, "truth/pose", 10)
        self._truth_publisher = self.create_publisher(LandmarkArrayMsg, "truth", 10)
        self._timer = self.create_timer(1.0 / rate, self._simulate_ping)

    def _noise(self) -> Noise:
        return Noise(tof=self.params["sigma_tof"], amplitude=self.params["sigma_amplitude"])

    @property
    def pings_per_lap(self) -> int:
        """Simulator: poses of one pass over the scene's trajectory (1 without one)."""
        return len(self._poses)

    def _simulate_ping(self) -> None:
        if self._laps_left == 0:
            return
        started = time.perf_counter()
        pose = self._poses[self._pose_index]
        self.world.noise = self._noise()
        ping = self.world.ping(pose, self.pings_simulated / self.world.ping_rate)
        odometry = self.world.odometry_pose(pose)
        self.pings_simulated += 1
        header = self._header()
        self.health.received()
        # First: a mapper in another process may have the pose when the ping's landmarks come (composed, they wait).
        self._odom_publisher.publish(odometry_message(odometry, header))
        self._true_pose_publisher.publish(odometry_message(pose, header, frame_id=WORLD_FRAME))
        self._truth_publisher.publish(truth_message(ping, header))
        downstream = self._publish(ping.echoes, header)
        self.health.processed(time.perf_counter() - started - downstream, published=1)
        self._pose_index += 1
        if self._pose_index == len(self._poses):
            self._pose_index = 0
            self._laps_left -= 1

    def _on_topic(self, data: bytes, info: MessageInfo) -> None:
        started = time.perf_counter()
        self.health.received()
        taken = self._check.take_echoes(data, info)
        if taken is None:
            return
        received, echoes = taken
        header = MessageHeader(received.stamp, self.params["frame_id"])
        downstream = self._publish(echoes, header)
        self.health.processed(time.perf_counter() - started - downstream)

    def _start_hardware(self) -> None:
        from sonar_ring.transport import HardwareReader

        self._frames: deque = deque()
        self._frames_lock = threading.Lock()
        self._frames_dropped = 0
        self._reader_reported: Counter[str] = Counter()
        self._next_reader_report = 0.0
        self.device_clock = DeviceClock()
        self._last_arrival_ns: int | None = None
        self.health.extra_values = self._device_values
        self.reader = HardwareReader(self.params["device"], self._on_frame,
                                     silence_timeout=self.params["silence_timeout"],
                                     clock=lambda: self.get_clock().now().nanoseconds)
        self.reader.start()
        self._timer = self.create_timer(0.002, self._drain_frames)

    def _on_frame(self, frame: EchoFrame, arrival_ns: int) -> None:
        """Reader thread: queue the frame with its arrival time (ns, node clock); drop the oldest when full.

        Only the executor thread touches :attr:`health`; drops are counted here
        and handed over in :meth:`_drain_frames`.
        """
        with self._frames_lock:
            if len(self._frames) >= HARDWARE_QUEUE:
                self._frames.popleft()
                self._frames_dropped += 1
            self._frames.append((arrival_ns, frame))

    def _drain_frames(self) -> None:
        with self._frames_lock:
            frames, self._frames = list(self._frames), deque()
            dropped, self._frames_dropped = self._frames_dropped, 0
        self.health.problem("dropped_queue_full", f"more than {HARDWARE_QUEUE} frames waiting", dropped)
        for arrival_ns, frame in frames:
            started = time.perf_counter()
            self.health.received()
            self._last_arrival_ns = arrival_ns
            header = Header(stamp=Time(nanoseconds=self._stamp(frame, arrival_ns)).to_msg(),
                            frame_id=self.params["frame_id"])
            published_before = self.pings_published
            downstream = self._publish(frame.echoes, header)
            self.health.processed(time.perf_counter() - started - downstream,
                                  published=self.pings_published - published_before)  # 0: the ping was refused
        # The reader's counters take its lock, which it holds while decoding: read them with the frames,
        # or once a second when none come (a lost device), not at every 2 ms tick.
        if frames or time.monotonic() >= self._next_reader_report:
            self._report_reader()

    def _stamp(self, frame: EchoFrame, arrival_ns: int) -> int:
        """The ping's stamp, ns on the node clock: its firing time from the device clock, or its arrival.

        Every frame with a device time goes through :attr:`device_clock`, so
        its estimate is on ``/diagnostics`` whichever stamp is published.
        """
        if frame.device_time_us == 0:
            self.health.note("stamped on arrival (no device time)")
            return arrival_ns
        fired_ns = self.device_clock.stamp(frame.device_time_us, arrival_ns)
        return fired_ns if self.params["stamp"] == "device" else arrival_ns

    def _device_values(self) -> dict[str, str]:
        """The hardware source's own ``/diagnostics`` values: the last frame's age and the device clock estimate."""
        if self._last_arrival_ns is None:
            return {"last frame age (s)": "n/a"}
        delays = self.device_clock.delays() * 1e3
        age = (self.get_clock().now().nanoseconds - self._last_arrival_ns) * 1e-9
        values = {"last frame age (s)": f"{age:.3f}"}
        if delays.size:
            values.update({"device clock offset (s)": f"{self.device_clock.offset:.6f}",
                           "device clock drift (ppm)": f"{self.device_clock.drift * 1e6:.2f}",
                           "device clock restarts": str(self.device_clock.restarts),
                           "arrival delay median (ms)": f"{np.median(delays):.3f}",
                           "arrival delay p99 (ms)": f"{np.percentile(delays, 99):.3f}"})
        return values

    def _report_reader(self) -> None:
        """The reader's connection events and the decoder's dropped bytes since the last call, on ``health``."""
        counts = self.reader.counts()
        for event, count in (counts - self._reader_reported).items():
            if event == "connected":
                self.health.note("device connected", count)
            else:
                self.health.problem(event, self.reader.address, count)
        self._reader_reported = counts
        self._next_reader_report = time.monotonic() + 1.0

    # ------------------------------------------------------------------ output

    def _publish(self, echoes: EchoArrays, header: AnyHeader) -> float:
        """Check a ping (:func:`sonar_ring.ping_stage.check_ping`) and publish what is usable of it.

        Returns the seconds the nodes that follow this one in this process took.
        """
        kept = usable_echoes(echoes, self.layout, self.health, stamp_ns(header),
                             self.params["speed_of_sound"] or DEFAULT_SPEED_OF_SOUND)
        if kept is None:
            return 0.0
        # The message's own types (float32 amplitudes, ...): what the next node would decode, so composed and
        # separate nodes, and `sonar-ring process`, give the same landmarks.
        downstream = self.pass_on(header, as_message_types(kept))
        # After the hand-off: the landmarks of a ping matter more than its echoes and ranges being first.
        self._echo_publisher.publish(echoes_to_msg(kept, header))
        self.pings_published += 1
        if self.params["publish_range"]:
            self._ranges.publish(kept, header)
        return downstream

    def _header(self) -> Header:
        return Header(stamp=self.get_clock().now().to_msg(), frame_id=self.params["frame_id"])

    def _on_change(self, changed: dict) -> None:
        if "ping_rate" in changed and self.params["source"] == "simulator":
            self._timer.cancel()
            rate = changed["ping_rate"] or self.layout.ping_rate
            self.world.ping_rate = rate
            self._timer = self.create_timer(1.0 / rate, self._simulate_ping)

    def destroy_node(self) -> None:
        """Stop the hardware reader thread before the node goes."""
        if self.reader is not None:  # None also when the device address was refused at start-up
            self.reader.stop()
        super().destroy_node()


def usable_echoes(echoes: EchoArrays, layout, counts, stamp: int, speed_of_sound: float) -> EchoArrays | None:
    """What the driver publishes of a ping stamped ``stamp`` (ns), or None when nothing of it is usable.

    The ping is the driver's layout's (hardware frames name none), with
    ``speed_of_sound`` (m/s) where the source gave none, then checked
    (:func:`sonar_ring.ping_stage.check_ping`: rejections counted on ``counts``).
    """
    echoes = replace(echoes, layout=layout.name, speed_of_sound=echoes.speed_of_sound or speed_of_sound)
    return check_ping(echoes, layout, counts, stamp)


def realism_params(realism) -> list[Param]:
    """The driver's ``realism.*`` parameters, read-only, with ``realism``'s values as their defaults."""
    return [Param(REALISM_PREFIX + name, float(value), f"simulator: {DESCRIPTIONS[name]}", low=RANGES[name][0],
                  high=RANGES[name][1], read_only=True) for name, value in vars(realism).items()]


def truth_message(ping, header: Header) -> LandmarkArrayMsg:
    """Ground truth of a simulated ping: per echo row, the true class and position (sensor frame, m).

    An echo of no reflector (multipath, clutter, a late echo) is UNKNOWN, at NaN, and not valid.
    """
    truth = make_landmarks(ping.truth_class, ping.truth_position, normal=np.nan_to_num(ping.truth_normal),
                           echo=np.arange(ping.n_echoes), group=ping.group, valid=ping.truth_origin == DIRECT)
    return landmarks_to_msg(truth, header)


def odometry_message(pose: np.ndarray, header: Header, frame_id: str = "odom") -> Odometry:
    """The simulated robot (:data:`BASE_FRAME`) at ``pose`` (x, y, yaw in ``frame_id``; m, rad), stamped ``header``."""
    message = Odometry(child_frame_id=BASE_FRAME)
    message.header.stamp = header.stamp
    message.header.frame_id = frame_id
    message.pose.pose.position.x, message.pose.pose.position.y = float(pose[0]), float(pose[1])
    message.pose.pose.orientation.z = float(np.sin(pose[2] / 2))
    message.pose.pose.orientation.w = float(np.cos(pose[2] / 2))
    return message


def main(args=None) -> None:
    """Run the driver until Ctrl-C or shutdown."""
    spin(Driver, args=args)


if __name__ == "__main__":
    main()
