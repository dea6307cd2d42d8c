"""Faults while running: the driver's device resets or drops frames, a node restarts mid-run, a subscriber joins late.

Also the driver's hardware stamps: when the transmitter fired, from the device clock estimate.
"""

import os
import socket
import struct
import time

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from ros_harness import MAP_QOS, spin_until, start_node, stop_nodes
from sonar_ring.msg import Echoes, LandmarkArray
from test_device_clock import frames
from test_transport import frame, free_port, ring_ping, send_frames

from sonar_ring.device_clock import DeviceClock
from sonar_ring.frames import FrameDecoder
from sonar_ring.ros.convert import landmarks_from_msg
from sonar_ring.ros.driver import HARDWARE_QUEUE, Driver
from sonar_ring.ros.inputs import stamp_ns

pytestmark = pytest.mark.ros


def test_driver_keeps_publishing_across_a_tcp_reset_of_its_device(ros):
    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(10)
    port = server.getsockname()[1]
    driver = Driver(parameter_overrides=[Parameter("source", value="hardware"),
                                         Parameter("device", value=f"tcp://127.0.0.1:{port}")])
    listener = rclpy.create_node("device_listener")
    published = []
    listener.create_subscription(Echoes, "echoes", published.append, qos_profile_sensor_data)
    executor = SingleThreadedExecutor()
    for node in (driver, listener):
        executor.add_node(node)

    def delivered(connection, sequence):
        """Send frame ``sequence`` until the driver publishes its ping."""
        group = ring_ping(sequence, n=1).group.tolist()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            connection.sendall(frame(sequence))
            if spin_until(executor, lambda: any(list(m.group) == group for m in published), 0.1):
                return True
        return False

    with server:
        connection, _ = server.accept()
        corrupted = bytearray(frame(7))
        corrupted[-1] ^= 0xFF
        connection.sendall(b"junk" + bytes(corrupted))  # dropped and counted; the next frame decodes
        assert delivered(connection, 1)
        connection.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        connection.close()  # RST: what a device does when it reboots
        connection, _ = server.accept()  # the driver reconnects by itself
        with connection:
            assert delivered(connection, 2)
            connection.sendall(frame(2))  # the same frame again: dropped
            assert spin_until(executor, lambda: driver.health.problems["duplicate_frame"] >= 1, timeout=5)
    assert driver.health.problems["device lost: ConnectionResetError"] == 1
    assert driver.health.problems["frame_bad_crc"] == 1 and driver.health.problems["frame_garbage"] >= 4
    assert driver.health.notes["device connected"] == 2
    for node in (driver, listener):
        node.destroy_node()


def test_restarted_localiser_rejoins_and_a_late_subscriber_gets_the_map(ros):
    namespace = f"/faults_{os.getpid()}"

    def start(name):
        return start_node(name, namespace, "source:=simulator", "map_rate:=5.0")

    processes = {name: start(name) for name in ("driver", "localiser", "mapper")}
    observer = rclpy.create_node("fault_observer", namespace=namespace)
    landmarks, published_maps = [], []
    observer.create_subscription(LandmarkArray, "landmarks", landmarks.append, qos_profile_sensor_data)
    observer.create_subscription(LandmarkArray, "map/landmarks", published_maps.append, MAP_QOS)
    executor = SingleThreadedExecutor()
    executor.add_node(observer)
    try:
        assert spin_until(executor, lambda: len(landmarks) >= 10, timeout=40)
        assert stop_nodes([processes["localiser"]]) == [0]
        spin_until(executor, lambda: False, timeout=0.5)
        landmarks.clear()
        spin_until(executor, lambda: False, timeout=1.0)
        assert not landmarks, "without a localiser nothing is labelled"
        processes["localiser"] = start("localiser")
        assert spin_until(executor, lambda: len(landmarks) >= 10, timeout=40), "the new localiser rejoined"
        # SLAM maps a landmark once it is decided and seen from several poses: wait for a map with one.
        assert spin_until(executor, lambda: published_maps and landmarks_from_msg(published_maps[-1]).position.size,
                          timeout=60)

        assert stop_nodes([processes["driver"]]) == [0]  # no more pings: the map stops changing,
        spin_until(executor, lambda: False, timeout=1.0)  # and the mapper stops publishing it
        late = rclpy.create_node("late_map_subscriber", namespace=namespace)
        maps = []
        late.create_subscription(LandmarkArray, "map/landmarks", maps.append, MAP_QOS)
        executor.add_node(late)
        assert spin_until(executor, lambda: maps, timeout=10), "transient local: the latest map, at once"
        assert len(landmarks_from_msg(maps[0])) > 0
    finally:
        codes = stop_nodes(processes.values())
    assert codes == [0, 0, 0]


def test_driver_drops_and_counts_frames_beyond_its_queue(ros):
    """A burst from the device faster than the executor drains it: the oldest frames go, counted."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    driver = Driver(parameter_overrides=[Parameter("source", value="hardware"),
                                         Parameter("device", value=f"udp://127.0.0.1:{port}")])
    decoded = FrameDecoder().feed(b"".join(frame(sequence) for sequence in range(100)))
    for one in decoded:  # what the reader thread hands over while the executor is busy elsewhere
        driver._on_frame(one, time.time_ns())
    driver._drain_frames()
    assert driver.pings_published == HARDWARE_QUEUE
    assert driver.health.problems["dropped_queue_full"] == 100 - HARDWARE_QUEUE
    driver.destroy_node()


def hardware_driver(**parameters):
    """A driver reading a UDP device on a free port of 127.0.0.1, with ``parameters`` besides; and the port."""
    port = free_port(socket.SOCK_DGRAM)
    overrides = [Parameter("source", value="hardware"), Parameter("device", value=f"udp://127.0.0.1:{port}"),
                 *(Parameter(name, value=value) for name, value in parameters.items())]
    return Driver(parameter_overrides=overrides), port


def test_driver_stamps_each_ping_when_its_transmitter_fired(ros):
    """``stamp:=device`` publishes the device clock estimate's stamps, ``stamp:=arrival`` the arrival times;
    a frame without device time is stamped on arrival either way (and counted)."""
    fired, device_us, arrival = frames(rate=30, seconds=4, start=1.0)
    device_us[-1] = 0  # this device's last frame comes without its time
    decoded = FrameDecoder().feed(b"".join(frame(i, int(d)) for i, d in enumerate(device_us)))
    clock = DeviceClock()
    estimated = [clock.stamp(int(d), int(a)) for d, a in zip(device_us[:-1], arrival[:-1], strict=True)]
    for source, expected in (("device", [*estimated, arrival[-1]]), ("arrival", list(arrival))):
        driver, _ = hardware_driver(stamp=source)
        stamps = []
        driver.handoff = lambda header, echoes, stamps=stamps: stamps.append(stamp_ns(header))
        for one, arrival_ns in zip(decoded, arrival, strict=True):
            driver._on_frame(one, int(arrival_ns))  # as the reader thread hands them over
            driver._drain_frames()
        assert stamps == expected, source
        assert driver.health.notes["stamped on arrival (no device time)"] == 1
        values = {value.key: value.value for value in driver.health.status().values}
        assert abs(float(values["device clock drift (ppm)"]) - 50.0) < 100.0  # 4 s of 10 ms jitter: roughly
        assert float(values["arrival delay median (ms)"]) > 0.0 and values["device clock restarts"] == "0"
        driver.destroy_node()


def test_driver_reports_frames_lost_input_rate_and_last_frame_age_on_diagnostics(ros):
    driver, port = hardware_driver()
    listener = rclpy.create_node("diagnostics_listener")
    reports = []
    listener.create_subscription(DiagnosticArray, "/diagnostics", lambda message: reports.extend(
        {value.key: value.value for value in status.values} for status in message.status
        if status.name.endswith("/driver")), 10)
    executor = SingleThreadedExecutor()
    for node in (driver, listener):
        executor.add_node(node)
    assert spin_until(executor, driver.reader.connected.is_set, timeout=5)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        send_frames(lambda data: udp.sendto(data, ("127.0.0.1", port)), [*range(20), *range(25, 40)], spacing=0.005)
    assert spin_until(executor, lambda: reports and reports[-1].get("problems: frames_lost") == "5", timeout=10)
    assert driver.pings_published == 35
    values = reports[-1]
    assert float(values["input rate (Hz)"]) > 0.0 and float(values["last frame age (s)"]) >= 0.0
    assert {"device clock offset (s)", "device clock drift (ppm)", "arrival delay median (ms)",
            "arrival delay p99 (ms)"} <= set(values)
    for node in (driver, listener):
        node.destroy_node()
