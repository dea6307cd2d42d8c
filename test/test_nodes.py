"""The nodes with real rclpy and Fast DDS on loopback: accuracy, markers, map, parameters, bad input."""

import os

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from rclpy.serialization import serialize_message
from ros_harness import MAP_QOS, spin_until, start_node, stop_nodes
from sonar_ring.msg import LandmarkArray
from visualization_msgs.msg import Marker, MarkerArray

from sonar_ring.landmarks import CLASS_NAMES
from sonar_ring.ros.convert import echoes_from_cdr, landmarks_from_msg
from sonar_ring.ros.driver import Driver
from sonar_ring.ros.graph import NODES, compose
from sonar_ring.ros.localiser import Localiser
from sonar_ring.ros.mapper import Mapper
from sonar_ring.ros.params import ParameterError
from sonar_ring.ros.run import _interrupted
from sonar_ring.simulate import load_scene

pytestmark = pytest.mark.ros

CHI2_2DOF_3SIGMA = 11.83  # P(chi2_2 <= 11.83) = 99.73 %, the 2-D "3 sigma"

def stamp_key(msg):
    return msg.header.stamp.sec, msg.header.stamp.nanosec


class Listener:
    """Collects the graph's outputs by ping stamp."""

    def __init__(self, namespace=""):
        self.node = rclpy.create_node("test_listener", namespace=namespace)
        self.landmarks, self.truth, self.markers, self.maps = {}, {}, [], []
        sub = self.node.create_subscription
        sub(LandmarkArray, "landmarks", lambda m: self.landmarks.__setitem__(stamp_key(m), m), qos_profile_sensor_data)
        sub(LandmarkArray, "truth", lambda m: self.truth.__setitem__(stamp_key(m), m), 10)
        sub(MarkerArray, "markers", self.markers.append, 10)
        sub(LandmarkArray, "map/landmarks", self.maps.append, MAP_QOS)

    def paired(self):
        return [(landmarks_from_msg(self.landmarks[k]), landmarks_from_msg(self.truth[k]))
                for k in sorted(self.landmarks) if k in self.truth]


def mahalanobis_squared(landmarks, truth):
    """Of the landmarks of real reflectors (not multipath, clutter or late echoes)."""
    real = landmarks.select(truth.valid[landmarks.echo])
    error = real.position - truth.position[real.echo]
    return np.einsum("ni,nij,nj->n", error, np.linalg.inv(real.covariance), error)


def assert_markers_valid(marker_array):
    assert marker_array.markers
    for marker in marker_array.markers:
        assert marker.header.frame_id
        assert marker.scale.x > 0 and (marker.type == Marker.LINE_LIST or marker.scale.y > 0)
        assert len(marker.colors) in (0, len(marker.points))  # per point only where alphas differ
        assert marker.color.a > 0 and all(colour.a > 0 for colour in marker.colors)
        assert marker.ns.startswith("landmarks/")


def _run_graph(overrides, pings=60):
    nodes = [cls(parameter_overrides=overrides) for cls in NODES]
    compose(nodes)
    listener = Listener()
    executor = SingleThreadedExecutor()
    for node in [*nodes, listener.node]:
        executor.add_node(node)
    assert spin_until(executor, lambda: len(listener.paired()) >= pings and listener.maps, timeout=30)
    return nodes, listener


def test_graph_in_one_process_matches_ground_truth(ros):
    """In the realistic world: the landmarks of real reflectors lie within their covariance of the truth."""
    nodes, listener = _run_graph([])
    assert nodes[0].realism.effects() and nodes[1].params["sigma_speed"] > 1.0  # the air is 2 K off
    d2 = np.concatenate([mahalanobis_squared(found, truth) for found, truth in listener.paired()])
    assert d2.size > 500  # one landmark per echo: the pairs that heard it fitted together
    assert np.mean(d2 <= CHI2_2DOF_3SIGMA) >= 0.99
    assert_markers_valid(listener.markers[-1])
    assert {m.ns for m in listener.markers[-1].markers} == {f"landmarks/{c}" for c in CLASS_NAMES}
    for node in [*nodes, listener.node]:
        node.destroy_node()


def test_graph_in_one_process_maps_the_ideal_world(ros):
    nodes, listener = _run_graph([Parameter("world", value="ideal")])
    mapper = nodes[-1]
    counts = mapper.map.counts
    assert counts.fused > 5 * counts.created, "repeated sightings must fuse into existing entries"
    scene = load_scene("room")
    true_points = np.vstack([scene.corner_point, scene.edges])
    snapshot = mapper.map.snapshot(min_observations=5)
    points = snapshot.position[snapshot.landmark_class >= 2]
    nearest = np.min(np.linalg.norm(points[:, None, :] - true_points[None, :, :], axis=-1), axis=1)
    assert points.size and np.median(nearest) < 0.05
    for node in [*nodes, listener.node]:
        node.destroy_node()


def test_driver_hands_on_the_arrays_its_message_carries(ros):
    """Composed nodes see what separate ones decode (float32 amplitudes), so both give the same landmarks."""
    driver = Driver(parameter_overrides=[Parameter("layout", value="barshan_kuc_pair"),
                                         Parameter("scene", value="barshan_kuc_bench"),
                                         Parameter("ping_rate", value=50.0)])
    handed, published = [], []
    driver.handoff = lambda header, echoes: handed.append((header, echoes))
    publish = driver._echo_publisher.publish
    driver._echo_publisher.publish = lambda message: (published.append(message), publish(message))
    executor = SingleThreadedExecutor()
    executor.add_node(driver)
    assert spin_until(executor, lambda: len(published) >= 3, timeout=10)
    for (header, echoes), message in zip(handed, published, strict=False):
        assert header == message.header
        decoded = echoes_from_cdr(serialize_message(message))[1]
        assert echoes.n_echoes > 0 and echoes.amplitude.dtype == np.float32
        for name in ("group", "transmitter", "tof", "amplitude", "phase_delay"):
            assert np.array_equal(getattr(echoes, name), getattr(decoded, name), equal_nan=True), name
            assert getattr(echoes, name).dtype == getattr(decoded, name).dtype, name
    driver.destroy_node()


def test_composing_nodes_of_different_layouts_is_refused(ros):
    nodes = [Driver(), Localiser(parameter_overrides=[Parameter("layout", value="barshan_kuc_pair")]), Mapper()]
    with pytest.raises(ParameterError, match="share one layout"):
        compose(nodes)
    for node in nodes:
        node.destroy_node()


def test_graph_as_separate_processes_publishes_and_exits_cleanly(ros):
    namespace = f"/separate_{os.getpid()}"
    processes = [start_node(name, namespace, "source:=simulator") for name in ("driver", "localiser", "mapper")]
    try:
        listener = Listener(namespace)
        executor = SingleThreadedExecutor()
        executor.add_node(listener.node)
        # the map publishes an entry once it has persisted over pings and travel
        assert spin_until(executor, lambda: len(listener.paired()) >= 20 and listener.maps
                          and len(landmarks_from_msg(listener.maps[-1])) > 0, timeout=60)
        d2 = np.concatenate([mahalanobis_squared(found, truth) for found, truth in listener.paired()])
        assert np.mean(d2 <= CHI2_2DOF_3SIGMA) >= 0.99
        listener.node.destroy_node()
    finally:
        codes = stop_nodes(processes)
    assert codes == [0, 0, 0]


def test_ctrl_c_inside_nested_compiled_kernels_is_an_interrupt():
    # numba wraps the pending KeyboardInterrupt once per compiled call it passes through.
    def wrapped(depth):
        try:
            if depth == 0:
                raise KeyboardInterrupt
            wrapped(depth - 1)
        except BaseException as error:
            raise SystemError("returned a result with an exception set") from error

    for depth in (0, 3):
        with pytest.raises(SystemError) as caught:
            wrapped(depth)
        assert _interrupted(caught.value)
    assert not _interrupted(SystemError("a real fault"))
    assert not _interrupted(SystemError("wrapped").with_traceback(None))


def test_invalid_parameter_changes_are_refused_and_the_old_value_kept(ros):
    localiser, driver = Localiser(), Driver()
    result = localiser.set_parameters([Parameter("models", value=["plane", "wall"])])[0]
    assert not result.successful and "models must be a non-empty subset" in result.reason
    assert localiser.get_parameter("models").value == ["plane", "corner", "edge"]
    result = localiser.set_parameters([Parameter("sigma_tof", value=-1.0)])[0]
    assert not result.successful
    assert localiser.get_parameter("sigma_tof").value == 1e-6
    result = driver.set_parameters([Parameter("source", value="topic")])[0]
    assert not result.successful and "read-only" in result.reason
    assert localiser.set_parameters([Parameter("models", value=["corner"])])[0].successful
    assert localiser.stage.settings.models == ("corner",)
    # the driver's fallback speed of sound: 0 (the default) or what the echo screening accepts
    result = driver.set_parameters([Parameter("speed_of_sound", value=200.0)])[0]
    assert not result.successful and "250..450 m/s" in result.reason
    assert driver.set_parameters([Parameter("speed_of_sound", value=420.0)])[0].successful
    assert driver.set_parameters([Parameter("speed_of_sound", value=0.0)])[0].successful
    for node in (localiser, driver):
        node.destroy_node()


def test_graph_nodes_add_no_qos_event_waitables_to_the_executor(ros):
    """Every waitable is visited on every executor wait; the default QoS event handlers were 40 of them."""
    nodes = [cls(parameter_overrides=[Parameter("source", value="topic")]) for cls in NODES]
    assert [len(list(node.waitables)) for node in nodes] == [0, 0, 0]
    assert len(list(nodes[0].publishers)) > 48  # echoes and one Range topic per group, all without handlers
