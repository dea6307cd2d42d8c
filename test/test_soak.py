"""Soak: ten times the ring's ping rate for a lap of the room on loopback -- every ping accounted for, queues
bounded, memory flat, whatever the load on the machine.

The driver (simulator source, room scene) publishes 300 pings/s, ten times the
Browne ring's 30 Hz, from its own process, for one lap of the room's trajectory
(``loops``: 14,200 pings, 47 s at that rate; ``SONAR_RING_SOAK_LAPS`` changes
the laps) in the ideal world (the realistic one's multipath alone costs the
simulator several milliseconds a ping; this test loads the graph) and then
stops; localiser and mapper share one executor in this process,
each with its own subscriptions (not composed as in the ``graph``
executable), so every ping crosses DDS queues.  When they fall behind
(two callbacks and message decoding per ping on a shared core, and whatever
else the machine runs), the nodes must drop what they cannot take -- from their
depth-5 subscription queues and the mapper's bounded pending pings (waiting
for their odometry) -- and count it, instead of queueing without bound.

Checked, at any load: every ping the driver published is taken by the
localiser or counted as ``dropped_input (echoes)``, exactly, once the driver has
stopped and the graph has drained (apart from the pings published before the
localiser heard the driver at all, which no subscriber can count: the first
ping's sequence number tells how many); the mapper's pending pings never
exceed their limit; resident memory of both processes grows less than 5 % (and 10 MiB)
after the first quarter (warm-up: imports, DDS discovery, the map filling).
Not checked: how many pings per second the graph keeps up with, which depends
on the machine and what else runs on it -- ``sonar-ring bench`` measures the
running graph's sustained rate (BENCHMARKS.md, "graph").  Reported (printed;
``pytest -s test/test_soak.py``): pings, drops by reason, memory, and the
latency from a ping's stamp to its labelled landmarks (median, p99).
"""

import os
import re
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import qos_profile_sensor_data
from ros_harness import spin_until, start_node, stop_nodes
from sonar_ring.msg import LandmarkArray

from sonar_ring import map_builder
from sonar_ring.geometry import load_layout
from sonar_ring.ros.inputs import TopicCheck, stamp_ns
from sonar_ring.ros.localiser import Localiser
from sonar_ring.ros.mapper import Mapper
from sonar_ring.simulate import load_scene

pytestmark = pytest.mark.ros

LAPS = int(os.environ.get("SONAR_RING_SOAK_LAPS", "1"))
RATE = 10 * load_layout("browne_ring").ping_rate
PINGS = LAPS * len(load_scene("room").trajectory.poses(RATE)[1])
"""What the driver publishes: ``LAPS`` laps of the room's trajectory, one ping per pose at ``RATE``."""
HUNG_SECONDS = 30 + 20 * PINGS / RATE
"""Last resort against a hung process, not a throughput limit: twenty times the run's nominal length."""
GROWTH_LIMIT = 0.05
GROWTH_FLOOR_MIB = 10.0


def rss_mib(pid="self"):
    """Resident set size of a process, MiB (VmRSS of /proc/PID/status)."""
    status = Path(f"/proc/{pid}/status").read_text()
    return int(re.search(r"VmRSS:\s+(\d+) kB", status).group(1)) / 1024


class Observer:
    """The ping-to-landmarks latency, and the driver's latest counts from /diagnostics."""

    def __init__(self, namespace):
        self.node = rclpy.create_node("soak_observer", namespace=namespace)
        self.latency = []
        self.driver_values = {}
        self.node.create_subscription(LandmarkArray, "landmarks", self._on_landmarks, qos_profile_sensor_data)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 50)

    def _on_landmarks(self, msg):
        self.latency.append((self.node.get_clock().now().nanoseconds - stamp_ns(msg.header)) * 1e-9)

    def _on_diagnostics(self, msg):
        for status in msg.status:
            if status.name.endswith(f"{self.node.get_namespace()}/driver"):
                self.driver_values = {value.key: value.value for value in status.values}

    @property
    def driver_published(self):
        return int(self.driver_values.get("published", 0))


def first_sequence_number(node):
    """The publication sequence number of the first message each topic check of ``node`` took, as they come.

    Pings published before a subscription heard its publisher at all are lost
    to it without a gap to count; the first one's sequence number tells how many.
    """
    first = {}
    for check in (value for value in vars(node).values() if isinstance(value, TopicCheck)):
        def count_lost(info, check=check, count_lost=check.count_lost):
            if info is not None and check not in first:
                first[check] = info.get("publication_sequence_number")
            count_lost(info)
        check.count_lost = count_lost
    return first


def drops(node):
    return {reason: n for reason, n in node.health.problems.items()
            if reason.startswith("dropped_input") or reason == "no_odometry"}


def test_ten_times_the_ping_rate_for_a_lap_of_the_room(ros):
    namespace = f"/soak_{os.getpid()}"
    nodes = [cls(namespace=namespace) for cls in (Localiser, Mapper)]
    localiser, mapper = nodes
    first = first_sequence_number(localiser)
    observer = Observer(namespace)
    executor = SingleThreadedExecutor()
    for node in [*nodes, observer.node]:
        executor.add_node(node)
    driver = start_node("driver", namespace, "source:=simulator", f"ping_rate:={RATE}", f"loops:={LAPS}",
                        "publish_range:=false", "world:=ideal")
    accounted = lambda: (localiser.health.received_count  # noqa: E731
                         + localiser.health.problems["dropped_input (echoes)"]
                         + sum(sequence - 1 for sequence in first.values()))
    try:
        assert spin_until(executor, lambda: observer.latency, timeout=HUNG_SECONDS), "the graph must start"
        started = time.monotonic()
        samples = []  # (seconds, graph MiB, driver MiB)
        pending = []
        while observer.driver_published < PINGS:
            spin_until(executor, lambda: False, timeout=1.0)
            samples.append((time.monotonic() - started, rss_mib(), rss_mib(driver.pid)))
            pending.append(mapper.pending_pings)
            assert time.monotonic() - started < HUNG_SECONDS, "the driver must finish its laps"
        # Drained: the localiser has taken or counted every ping, or nothing has changed for a while.
        last, quiet_since = None, time.monotonic()
        while accounted() < PINGS and time.monotonic() - quiet_since < 5.0:
            spin_until(executor, lambda: False, timeout=0.5)
            pending.append(mapper.pending_pings)
            if accounted() != last:
                last, quiet_since = accounted(), time.monotonic()
    finally:
        driver_code, = stop_nodes([driver])
    assert driver_code == 0

    seconds, graph_mib, driver_mib = np.array(samples).T
    after_warm_up = seconds >= seconds[-1] / 4
    report = {"duration_s": float(seconds[-1]), "rate_hz": RATE, "driver_published": observer.driver_published,
              "heard_from_ping": list(first.values()), "localiser_taken": localiser.health.received_count,
              "mapped_pings": mapper.map.counts.pings,
              "drops": {node.get_name(): drops(node) for node in nodes}}
    for name, mib in (("graph", graph_mib), ("driver", driver_mib)):
        base = mib[after_warm_up][0]
        growth = mib[after_warm_up].max() - base
        report[f"{name}_rss_mib"] = {"start": float(mib[0]), "after_warm_up": float(base), "end": float(mib[-1]),
                                     "growth_after_warm_up": float(growth)}
        assert growth < max(GROWTH_LIMIT * base, GROWTH_FLOOR_MIB), f"{name} memory grows: {report}"
    latency = np.array(observer.latency) * 1e3
    report["latency_ms"] = {"median": float(np.median(latency)), "p99": float(np.percentile(latency, 99)),
                            "max": float(latency.max())}
    report["node_compute_p99_ms"] = {node.get_name(): float(np.percentile(node.health.latencies(), 99) * 1e3)
                                     for node in nodes}
    print(f"\nsoak report: {report}")

    assert max(pending) <= map_builder.PENDING_LIMIT
    assert observer.driver_published == PINGS
    assert accounted() == PINGS, f"pings lost without a count: {report}"
    for node in nodes:
        node.destroy_node()
    observer.node.destroy_node()
