"""Bad messages at every node: counted per reason on /diagnostics, and the valid rest of a ping still used."""

import math
from dataclasses import replace

import numpy as np
import pytest
import rclpy
from nav_msgs.msg import Odometry
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from rclpy.serialization import serialize_message
from rclpy.time import Time
from ros_harness import spin_until
from sonar_ring.msg import Echoes, LandmarkArray
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

from sonar_ring.echoes import EchoArrays
from sonar_ring.geometry import load_layout
from sonar_ring.ros.convert import echoes_to_msg, landmarks_from_msg, landmarks_to_msg
from sonar_ring.ros.diagnostics import NodeHealth
from sonar_ring.ros.driver import Driver
from sonar_ring.ros.inputs import TopicCheck, node_clock
from sonar_ring.ros.localiser import Localiser
from sonar_ring.ros.mapper import Mapper
from sonar_ring.simulate import Simulator, load_scene

pytestmark = pytest.mark.ros

LAYOUT = load_layout("browne_ring")


def wall_ping() -> EchoArrays:
    """A noise-free ping of the single-wall scene: every row gives valid hypotheses."""
    ping = Simulator(load_scene("single_wall"), LAYOUT).ping(load_scene("single_wall").sensor_pose)
    return replace(ping.echoes, layout=LAYOUT.name)


def with_rows(echoes: EchoArrays, group, transmitter, tof) -> EchoArrays:
    """``echoes`` with extra rows appended (amplitudes 0.5)."""
    tof = np.asarray(tof, dtype=float).reshape(-1, 2)
    return replace(echoes, group=np.concatenate([echoes.group, np.asarray(group, np.uint16)]),
                   transmitter=np.concatenate([echoes.transmitter, np.asarray(transmitter, np.uint8)]),
                   tof=np.vstack([echoes.tof, tof]),
                   amplitude=np.vstack([echoes.amplitude, np.full(tof.shape, 0.5, np.float32)]))


class Bench:
    """One node under test and a peer that publishes to it and collects what it publishes."""

    def __init__(self, node, in_topic, in_type, out_topic, out_type):
        self.node = node
        self.peer = rclpy.create_node("bad_input_peer")
        self.publisher = self.peer.create_publisher(in_type, in_topic, qos_profile_sensor_data)
        self.out = []
        self.peer.create_subscription(out_type, out_topic, self.out.append, qos_profile_sensor_data)
        self.executor = SingleThreadedExecutor()
        for n in (node, self.peer):
            self.executor.add_node(n)
        assert spin_until(self.executor, lambda: self.publisher.get_subscription_count() > 0
                          and self.peer.count_publishers(out_topic) > 0, timeout=10)
        self._stamp = self.peer.get_clock().now().nanoseconds

    def header(self, frame_id="sonar_ring", seconds_ahead=None):
        """A header with a fresh stamp after the previous one (or ``seconds_ahead`` of the clock)."""
        self._stamp += 10**6
        stamp = self._stamp if seconds_ahead is None else self.peer.get_clock().now().nanoseconds \
            + int(seconds_ahead * 1e9)
        header = Header(frame_id=frame_id)
        header.stamp.sec, header.stamp.nanosec = divmod(stamp, 10**9)
        return header

    def send(self, msg):
        """Publish ``msg`` and spin until the node has taken it."""
        before = self.node.health.received_count
        self.publisher.publish(msg)
        assert spin_until(self.executor, lambda: self.node.health.received_count > before, timeout=5)
        return msg

    def outputs_settle(self, count):
        return spin_until(self.executor, lambda: len(self.out) >= count, timeout=5)

    def close(self):
        for n in (self.node, self.peer):
            n.destroy_node()


def problems(node):
    return {reason: n for reason, n in node.health.problems.items() if n}


def diagnostics_values(node):
    return {value.key: value.value for value in node.health.status().values}


def test_driver_topic_source_drops_bad_values_rows_and_messages_and_keeps_the_rest(ros):
    bench = Bench(Driver(parameter_overrides=[Parameter("source", value="topic")]), "tof_in", Echoes, "echoes",
                  Echoes)
    good = wall_ping()
    n = good.n_echoes
    bad_rows = with_rows(good, group=[60, 3, 4, 5, 6, 7], transmitter=[0, 9, 0, 0, 0, 0],
                         tof=[[0.01, 0.01], [0.01, 0.01], [np.inf, 0.01], [-0.01, 0.01], [1e9, 0.01],
                              [np.nan, np.nan]])
    bench.send(echoes_to_msg(bad_rows, bench.header()))
    assert bench.outputs_settle(1)
    kept = bench.out[-1]
    # the five good rows, and the three rows that lost one bad TOF but kept the other
    assert len(kept.group) == n + 3 and list(kept.group[n:]) == [4, 5, 6]
    tof = np.asarray(kept.tof).reshape(-1, 2)
    assert np.all(np.isnan(tof[n:, 0])) and np.all(tof[n:, 1] == 0.01)
    assert problems(bench.node) == {"unknown_group": 1, "unknown_transmitter": 1, "not_finite_tof": 1,
                                    "not_positive_tof": 1, "tof_too_long": 1, "empty_row": 1}

    malformed = echoes_to_msg(good, bench.header())
    malformed.tof = malformed.tof[:3]
    bench.send(malformed)
    three_receivers = replace(good, tof=np.hstack([good.tof, good.tof[:, :1]]), amplitude=np.empty((n, 0)))
    bench.send(echoes_to_msg(three_receivers, bench.header()))
    bench.send(echoes_to_msg(replace(good, speed_of_sound=np.nan), bench.header()))
    bench.send(echoes_to_msg(replace(good, speed_of_sound=-343.0), bench.header()))
    last_good = bench.send(echoes_to_msg(good, bench.header()))
    bench.send(last_good)  # the same ping twice
    older = bench.header()
    bench.send(echoes_to_msg(good, bench.header()))
    bench.send(echoes_to_msg(good, older))
    bench.send(echoes_to_msg(good, bench.header(seconds_ahead=30.0)))
    empty = replace(good, group=good.group[:0], transmitter=good.transmitter[:0], tof=good.tof[:0],
                    amplitude=good.amplitude[:0])
    bench.send(echoes_to_msg(empty, bench.header()))
    assert bench.outputs_settle(4)  # the bad-rows ping, the good one, the newer one and the empty one
    assert [len(m.group) for m in bench.out] == [n + 3, n, n, 0]
    found = problems(bench.node)
    assert {reason: found[reason] for reason in ("malformed_message", "wrong_receivers_per_group",
                                                 "bad_speed_of_sound", "duplicate_stamp", "out_of_order_stamp",
                                                 "future_stamp")} == {
        "malformed_message": 1, "wrong_receivers_per_group": 1, "bad_speed_of_sound": 2, "duplicate_stamp": 1,
        "out_of_order_stamp": 1, "future_stamp": 1}
    assert bench.node.health.notes["empty ping"] == 1
    values = diagnostics_values(bench.node)
    assert values["problems: future_stamp"] == "1" and values["problems: unknown_group"] == "1"
    assert bench.node.health.status().level == bench.node.health.status().WARN
    bench.close()


def test_localiser_uses_the_valid_rows_of_a_ping_and_refuses_bad_headers(ros):
    localiser = Localiser(parameter_overrides=[Parameter("frame_id", value="sonar_ring")])
    bench = Bench(localiser, "echoes", Echoes, "landmarks/raw", LandmarkArray)
    good = wall_ping()
    mixed = with_rows(good, group=[60, 2], transmitter=[0, 5], tof=[[0.01, 0.01], [0.01, 0.01]])
    mixed = replace(mixed, tof=np.vstack([[np.inf, 0.01], mixed.tof[1:]]))  # row 0 loses a receiver
    bench.send(echoes_to_msg(mixed, bench.header()))
    assert bench.outputs_settle(1)
    hypotheses = landmarks_from_msg(bench.out[-1])
    assert set(hypotheses.group) == set(good.group[1:].tolist())
    assert set(hypotheses.echo) == set(range(1, good.n_echoes)), "row 0 (one TOF left) gives no pair hypothesis"
    assert problems(localiser) == {"unknown_group": 1, "unknown_transmitter": 1, "not_finite_tof": 1}

    bench.send(serialize_message(echoes_to_msg(good, bench.header()))[:100])  # cut short: not a message
    bench.send(echoes_to_msg(good, bench.header(frame_id="")))
    bench.send(echoes_to_msg(good, bench.header(frame_id="base_link")))
    bench.send(echoes_to_msg(replace(good, layout="kreczmer_triad"), bench.header()))
    duplicate = bench.send(echoes_to_msg(good, bench.header()))
    bench.send(duplicate)
    assert bench.outputs_settle(2)
    assert {reason: n for reason, n in problems(localiser).items() if "frame" in reason or "layout" in reason
            or "stamp" in reason or "malformed" in reason} == {"malformed_message": 1, "empty_frame_id": 1,
                                                               "wrong_frame_id": 1, "layout_mismatch": 1,
                                                               "duplicate_stamp": 1}
    result = localiser.set_parameters([Parameter("future_tolerance", value=-1.0)])[0]
    assert not result.successful and localiser.get_parameter("future_tolerance").value == 1.0
    bench.close()


def test_stamp_order_restarts_when_simulated_time_jumps_back(ros):
    # Simulated time, set here as /clock would set it.
    node = rclpy.create_node("gate_owner", parameter_overrides=[Parameter("use_sim_time", value=True)])
    health = NodeHealth(node)
    clock = node.get_clock()
    forgotten = []
    gate = TopicCheck(node_clock(node), health, "echoes", {"frame_id": "", "future_tolerance": 1.0},
                      on_clock_jump=lambda: forgotten.append(True))

    def header(seconds):
        h = Header(frame_id="sonar_ring")
        h.stamp.sec = seconds
        return h

    assert gate.admit(header(100)), "a zero clock (no /clock yet) checks no stamp for the future"
    clock.set_ros_time_override(Time(seconds=101))
    assert gate.admit(header(101)) and not gate.admit(header(101)) and not gate.admit(header(99))
    assert not gate.admit(header(103))
    clock.set_ros_time_override(Time(seconds=5))  # the bag starts again
    assert gate.admit(header(5)) and gate.admit(header(6)) and forgotten == [True]
    assert health.problems == {"duplicate_stamp": 1, "out_of_order_stamp": 1, "future_stamp": 1}
    assert health.notes == {"clock jumped back": 1}
    node.destroy_node()


def test_warnings_are_throttled_per_reason_and_every_problem_counted(ros, capfd):
    node = rclpy.create_node("throttled")
    health = NodeHealth(node)
    for _ in range(100):
        health.problem("flood", "the same again")
    health.problem("other", "something else")
    logged = capfd.readouterr().err
    assert logged.count("flood (1 so far): the same again") == 1 and "flood (2 so far)" not in logged
    assert logged.count("other (1 so far): something else") == 1, "a flood of one kind hides no other"
    assert health.problems == {"flood": 100, "other": 1}
    node.destroy_node()


def test_a_burst_beyond_the_queue_is_dropped_and_counted_not_queued(ros):
    localiser = Localiser()
    bench = Bench(localiser, "echoes", Echoes, "landmarks/raw", LandmarkArray)
    good = wall_ping()
    bench.send(echoes_to_msg(good, bench.header()))
    burst = 50
    for _ in range(burst):  # faster than the node takes them: nothing spins meanwhile
        bench.publisher.publish(echoes_to_msg(good, bench.header()))
    spin_until(bench.executor, lambda: False, timeout=1.0)
    taken = localiser.health.received_count - 1
    assert taken <= 10, "the subscription queue holds a few pings, not the burst"
    assert problems(localiser) == {"dropped_input (echoes)": burst - taken}
    bench.close()


def test_mapper_integrates_a_ping_once_and_refuses_stale_and_future_ones(ros):
    mapper = Mapper(parameter_overrides=[Parameter("use_odometry", value=False)])
    bench = Bench(mapper, "landmarks/pairs", LandmarkArray, "map/landmarks", LandmarkArray)
    landmarks = landmarks_from_msg(_one_ping_of_landmarks())
    first = bench.send(landmarks_to_msg(landmarks, bench.header()))
    bench.send(first)
    older = bench.header()
    bench.send(landmarks_to_msg(landmarks, bench.header()))
    bench.send(landmarks_to_msg(landmarks, older))
    bench.send(landmarks_to_msg(landmarks, bench.header(seconds_ahead=5.0)))
    bench.send(landmarks_to_msg(landmarks, bench.header(frame_id="")))
    malformed = landmarks_to_msg(landmarks, bench.header())
    malformed.position = malformed.position[:-1]
    bench.send(malformed)
    assert mapper.map.counts.pings == 2
    assert problems(mapper) == {"duplicate_stamp": 1, "out_of_order_stamp": 1, "future_stamp": 1,
                                "empty_frame_id": 1, "malformed_message": 1}
    bench.close()


def test_mapper_drops_odometry_that_places_nothing_and_goes_on(ros):
    """A position not finite, an orientation left all zeros, one with a huge component (whose yaw raised), a
    position beyond 10^6 m (whose odometry noise raised OverflowError); a covariance that is not one is counted,
    its pose kept."""
    mapper = Mapper()
    peer = rclpy.create_node("odometry_peer")
    publisher = peer.create_publisher(Odometry, "odom", 10)
    executor = SingleThreadedExecutor()
    for node in (mapper, peer):
        executor.add_node(node)
    assert spin_until(executor, lambda: publisher.get_subscription_count() > 0, timeout=10)
    start = peer.get_clock().now().nanoseconds - 10**9
    stamps = [start + k * 10**7 for k in range(9)]
    unit, planar = (0.0, 0.0, 0.0, 1.0), np.diag([1e-4, 1e-4, 0.0, 0.0, 0.0, 1e-3])
    broken, skewed = planar.copy(), planar.copy()
    broken[5, 5], skewed[0, 1] = math.inf, 1e-5
    sent = [(0.0, unit, None), (math.nan, unit, None), (0.1, (0.0, 0.0, 0.0, 0.0), None),
            (0.2, (0.0, 0.0, 1e200, 1.0), None), (1e300, unit, None), (0.3, unit, None),
            (0.4, unit, broken), (0.5, unit, skewed), (0.6, unit, planar)]
    for stamp, (x, orientation, covariance) in zip(stamps, sent, strict=True):
        message = Odometry(child_frame_id="base_link")
        message.header.frame_id = "odom"
        message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp, 10**9)
        message.pose.pose.position.x = x
        (message.pose.pose.orientation.x, message.pose.pose.orientation.y, message.pose.pose.orientation.z,
         message.pose.pose.orientation.w) = orientation
        if covariance is not None:
            message.pose.covariance = covariance.ravel().tolist()
        publisher.publish(message)
    assert spin_until(executor, lambda: len(mapper.builder.history) == 5
                      and problems(mapper).get("bad_odometry_pose") == 4, timeout=10), problems(mapper)
    assert problems(mapper) == {"bad_odometry_pose": 4, "bad_odometry_covariance": 2}
    np.testing.assert_array_equal(mapper.builder.history.at(stamps[5]), [0.3, 0.0, 0.0])
    assert mapper.builder.history.covariance_at(stamps[5]) is None  # all zeros: unknown
    assert mapper.builder.history.covariance_at(stamps[6]) is None and mapper.builder.history.at(stamps[7])[0] == 0.5
    np.testing.assert_array_equal(mapper.builder.history.covariance_at(stamps[8]), np.diag([1e-4, 1e-4, 1e-3]))
    for node in (mapper, peer):
        node.destroy_node()


def test_localiser_labels_the_rows_it_localised_once_per_ping(ros):
    localiser = Localiser()
    bench = Bench(localiser, "echoes", Echoes, "landmarks/pairs", LandmarkArray)
    raw, markers, published = [], [], []
    bench.peer.create_subscription(LandmarkArray, "landmarks/raw", raw.append, qos_profile_sensor_data)
    bench.peer.create_subscription(MarkerArray, "markers", markers.append, 10)
    bench.peer.create_subscription(LandmarkArray, "landmarks", published.append, qos_profile_sensor_data)
    assert spin_until(bench.executor, lambda: bench.peer.count_publishers("landmarks/raw") > 0
                      and bench.peer.count_publishers("markers") > 0
                      and bench.peer.count_publishers("landmarks") > 0, timeout=10)
    good = wall_ping()
    mixed = with_rows(good, group=[60, 2], transmitter=[0, 5], tof=[[0.01, 0.01], [0.01, 0.01]])
    ping = bench.send(echoes_to_msg(mixed, bench.header()))
    bench.send(ping)  # the same ping again: refused, nothing published twice
    assert bench.outputs_settle(1)
    assert spin_until(bench.executor, lambda: raw and markers and published, timeout=5)
    assert (len(bench.out), len(raw), len(markers), len(published)) == (1, 1, 1, 1)
    labelled, hypotheses = landmarks_from_msg(bench.out[0]), landmarks_from_msg(raw[0])
    assert len(labelled) == good.n_echoes and set(labelled.echo) == set(hypotheses.echo)
    # the wall's echo, heard by three pairs, is one landmark on ``landmarks``: their joint fit
    assert len(landmarks_from_msg(published[0])) == 1
    for row, position in zip(labelled.echo, labelled.position, strict=True):  # one of the row's hypotheses
        assert np.min(np.abs(hypotheses.position[hypotheses.echo == row] - position).max(axis=1)) == 0.0
    assert problems(localiser) == {"unknown_group": 1, "unknown_transmitter": 1, "duplicate_stamp": 1}
    bench.close()


def _one_ping_of_landmarks():
    """The localiser's hypotheses for the single-wall ping, as a message."""
    from sonar_ring import pipeline

    hypotheses = pipeline.localise_ping(LAYOUT, wall_ping())
    return landmarks_to_msg(hypotheses.select(hypotheses.valid), Header(frame_id="sonar_ring"))
