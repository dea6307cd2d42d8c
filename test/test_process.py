"""``sonar-ring record-sim`` and ``sonar-ring process``: bags in, bags out, the live graph's messages exactly.

The live comparison runs the demo (all three nodes and the recorder process) for
a few tens of pings, processes its echo bag offline and compares every
per-ping output message field by field, and the final map.
"""

import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from numpy.testing import assert_array_equal
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import PointCloud2
from sonar_ring.msg import Echoes, LandmarkArray
from visualization_msgs.msg import MarkerArray

from sonar_ring.cli import main
from sonar_ring.ros import demo, offline
from sonar_ring.ros.bag import TOPIC, BagWriter
from sonar_ring.ros.convert import echoes_from_cdr, landmarks_from_msg
from sonar_ring.ros.offline import SIM_START_NS

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]
PINGS = 40
OUTPUTS = ["/landmarks/raw", "/landmarks", "/landmarks/pairs", "/markers", "/map/landmarks", "/map/markers",
           "/map/points", "/slam/pose", "/tf", "/tf_static"]


def read_bag(path):
    """Topic -> type, and topic -> [(bag time, serialized message)], in bag order."""
    types, messages = {}, {}
    with Reader(path) as reader:
        for connection in reader.connections:
            types[connection.topic] = connection.msgtype
        for connection, time_ns, raw in reader.messages():
            messages.setdefault(connection.topic, []).append((time_ns, bytes(raw)))
    return types, messages


def stamp_ns(header):
    return header.stamp.sec * 10**9 + header.stamp.nanosec


def by_stamp(messages, kind):
    """Decoded messages by header stamp (a MarkerArray by its first marker's)."""
    decoded = [deserialize_message(raw, kind) for _, raw in messages]
    if kind is MarkerArray:
        return {stamp_ns(m.markers[0].header): m for m in decoded}
    return {stamp_ns(m.header): m for m in decoded}


def transforms_in(path) -> dict:
    """``(parent, child) -> [stamp ns, ...]`` of every transform on /tf and /tf_static, decoded by rosbags."""
    store = get_typestore(Stores.ROS2_KILTED)
    frames = {}
    with Reader(path) as reader:
        connections = [c for c in reader.connections if c.topic in ("/tf", "/tf_static")]
        for connection, _, data in reader.messages(connections=connections):
            assert connection.msgtype == "tf2_msgs/msg/TFMessage"
            for transform in store.deserialize_cdr(data, connection.msgtype).transforms:
                stamp = transform.header.stamp.sec * 10**9 + transform.header.stamp.nanosec
                frames.setdefault((transform.header.frame_id, transform.child_frame_id), []).append(stamp)
    return frames


def assert_same_landmarks(got, expected):
    a, b = landmarks_from_msg(got), landmarks_from_msg(expected)
    for field in ("landmark_class", "position", "normal", "covariance", "confidence", "segment", "observations",
                  "group", "echo", "valid", "reason"):
        assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
    assert_array_equal(np.asarray(got.bearing), np.asarray(expected.bearing))


def run_cli(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def sim_bag(tmp_path_factory):
    bag = tmp_path_factory.mktemp("sim") / "room"
    assert main(["record-sim", "room", str(bag), "--pings", str(PINGS), "--quiet"]) == 0
    return bag


def test_record_sim_writes_the_drivers_topics_on_trajectory_time(sim_bag):
    types, messages = read_bag(sim_bag)
    ranges = {f"/range/group_{group:02d}": "sensor_msgs/msg/Range" for group in range(48)}
    assert types == {"/echoes": "sonar_ring/msg/Echoes", "/odom": "nav_msgs/msg/Odometry",
                     "/truth/pose": "nav_msgs/msg/Odometry", "/truth": "sonar_ring/msg/LandmarkArray", **ranges}
    times = [t for t, _ in messages["/echoes"]]
    assert len(times) == PINGS
    assert times[0] == SIM_START_NS
    assert np.allclose(np.diff(times), 1e9 / 30.0, atol=1)  # browne_ring pings at 30 Hz
    assert all([t for t, _ in messages[topic]] == times for topic in [*ranges, "/odom", "/truth/pose", "/truth"])
    # The realistic world by default: the odometry drifts away from the true pose, which starts it.
    odometry, true_pose = ([deserialize_message(data, Odometry).pose.pose.position for _, data in messages[topic]]
                           for topic in ("/odom", "/truth/pose"))
    assert (odometry[0].x, odometry[0].y) == (true_pose[0].x, true_pose[0].y)
    assert (odometry[-1].x, odometry[-1].y) != (true_pose[-1].x, true_pose[-1].y)
    assert deserialize_message(messages["/truth/pose"][0][1], Odometry).header.frame_id == "world"
    first = deserialize_message(messages["/echoes"][0][1], Echoes)
    assert first.header.frame_id == "sonar_ring" and first.layout == "browne_ring"
    assert first.header.stamp.sec * 10**9 + first.header.stamp.nanosec == SIM_START_NS
    assert echoes_from_cdr(messages["/echoes"][0][1])[1].n_echoes > 10


def test_process_of_a_simulated_bag_finds_the_true_reflectors(sim_bag, tmp_path, capsys):
    out = tmp_path / "out"
    code, printed, _ = run_cli(capsys, "process", str(sim_bag), str(out), "--quiet", "--scene", "room")
    assert code == 0
    assert f"processed {PINGS} pings" in printed and "refused: nothing" in printed
    # the final map scored against the scene the bag was recorded in
    score_line = next(line for line in printed.splitlines() if line.startswith("  map score against room (/echoes):"))
    assert "plane: " in score_line and "heard mapped" in score_line
    types, messages = read_bag(out)
    assert sorted(types) == sorted(OUTPUTS)
    _, source = read_bag(sim_bag)
    echo_times = [t for t, _ in source["/echoes"]]
    for topic in ("/landmarks/raw", "/landmarks", "/landmarks/pairs", "/markers"):
        assert [t for t, _ in messages[topic]] == echo_times  # one per ping, at the echoes' bag time
    map_times = [t for t, _ in messages["/map/landmarks"]]
    period = 10**9 // 2  # map_rate 2 Hz in bag time, the first tick half a second after the first ping
    assert map_times == [echo_times[0] + k * period for k in range(1, len(map_times) + 1)]
    assert map_times[-1] > echo_times[-1]  # the last pings are in a map
    landmarks = by_stamp(messages["/landmarks"], LandmarkArray)
    truth = by_stamp(source["/truth"], LandmarkArray)
    errors = []
    for stamp, message in landmarks.items():
        found, true = landmarks_from_msg(message), landmarks_from_msg(truth[stamp])
        real = true.valid[found.echo]  # not multipath, clutter or a late echo
        errors.append(np.linalg.norm(found.position[real] - true.position[found.echo[real]], axis=1))
    assert np.median(np.concatenate(errors)) < 0.05
    final_map = deserialize_message(messages["/map/landmarks"][-1][1], LandmarkArray)
    assert final_map.header.frame_id == "map" and len(landmarks_from_msg(final_map)) >= 3
    # tf, read by the bag library itself: what a viewer needs to place the map and the sensor-frame markers
    frames = transforms_in(out)
    assert {("map", "odom"), ("odom", "base_link"), ("base_link", "sonar_ring"),
            ("sonar_ring", "sonar_ring/group_00"), ("sonar_ring", "sonar_ring/group_47")} <= set(frames)
    assert len(frames[("odom", "base_link")]) == PINGS and len(frames[("map", "odom")]) >= PINGS - 2


def test_sqlite3_and_mcap_inputs_and_any_jobs_give_the_same_landmarks(sim_bag, tmp_path):
    sqlite = tmp_path / "sqlite"
    assert main(["record-sim", "room", str(sqlite), "--pings", "12", "--storage", "sqlite3", "--no-range",
                 "--quiet"]) == 0
    assert list(sqlite.glob("*.db3"))
    # One in this process, one with two workers: where a ping is worked on does not change its output.
    assert main(["process", str(sqlite), str(tmp_path / "from_sqlite"), "--quiet", "--storage", "sqlite3",
                 "--jobs", "1"]) == 0
    assert main(["process", str(sim_bag), str(tmp_path / "from_mcap"), "--quiet", "--jobs", "2"]) == 0
    from_sqlite = by_stamp(read_bag(tmp_path / "from_sqlite")[1]["/landmarks"], LandmarkArray)
    from_mcap = by_stamp(read_bag(tmp_path / "from_mcap")[1]["/landmarks"], LandmarkArray)
    assert len(from_sqlite) == 12
    for stamp, message in from_sqlite.items():
        assert_same_landmarks(message, from_mcap[stamp])


def test_where_the_mapper_and_the_localiser_run_does_not_change_a_byte(sim_bag, tmp_path):
    # --jobs 1: everything here; 2: the mapper in a process of its own; 3: and a localiser worker.
    outputs = {}
    for jobs in (1, 2, 3):
        assert main(["process", str(sim_bag), str(tmp_path / str(jobs)), "--quiet", "--jobs", str(jobs)]) == 0
        outputs[jobs] = read_bag(tmp_path / str(jobs))[1]
    here = outputs[1]
    assert set(OUTPUTS) <= set(here) and len(here["/map/landmarks"]) >= 2 and len(here["/slam/pose"]) >= PINGS - 2
    for jobs in (2, 3):
        assert set(outputs[jobs]) == set(here)
        for topic, messages in here.items():
            got = outputs[jobs][topic]
            assert [time for time, _ in got] == [time for time, _ in messages], topic
            if topic == "/map/points":  # rclpy leaves the padding after the header's frame id unset
                for (_, a), (_, b) in zip(got, messages, strict=True):
                    a, b = deserialize_message(a, PointCloud2), deserialize_message(b, PointCloud2)
                    assert a.header == b.header and bytes(a.data) == bytes(b.data) and a.width == b.width
            else:
                assert got == messages, topic


def test_two_echoes_topics_map_apart_in_one_mapper_process(sim_bag, tmp_path):
    # The same recording under two namespaces: each one's outputs are those of the recording alone.
    _, source = read_bag(sim_bag)
    both = tmp_path / "both"
    with BagWriter(both) as writer:
        written = []
        for namespace in ("/left", "/right"):
            echoes = writer.connection(f"{namespace}/echoes", TOPIC["echoes"].message, TOPIC["echoes"].qos)
            odom = writer.connection(f"{namespace}/odom", TOPIC["odom"].message, TOPIC["odom"].qos)
            written += [(t, echoes, raw) for t, raw in source["/echoes"]]
            written += [(t, odom, raw) for t, raw in source["/odom"]]
        for time_ns, connection, raw in sorted(written, key=lambda item: item[0]):
            writer.write(connection, time_ns, raw)
    assert main(["process", str(sim_bag), str(tmp_path / "alone"), "--quiet", "--jobs", "1"]) == 0
    alone = read_bag(tmp_path / "alone")[1]
    for jobs in (1, 2):
        assert main(["process", str(both), str(tmp_path / f"both_{jobs}"), "--quiet", "--jobs", str(jobs)]) == 0
        outputs = read_bag(tmp_path / f"both_{jobs}")[1]
        for namespace in ("/left", "/right"):
            for topic in ("/landmarks", "/slam/pose", "/map/landmarks", "/map/markers"):
                assert outputs[namespace + topic] == alone[topic], (jobs, namespace, topic)


def test_a_mapper_failing_in_its_process_fails_the_run_and_leaves_no_output(sim_bag, tmp_path, monkeypatch):
    def fail(self, pings):
        raise ValueError("the mapper broke")

    monkeypatch.setattr(offline.MappingWork, "outputs", fail)  # forked: the mapper's process has it too
    with pytest.raises(ValueError, match="the mapper broke"):
        offline.process_bag(sim_bag, tmp_path / "out", jobs=2, progress=False)
    assert not (tmp_path / "out").exists()


def test_process_of_the_demo_bag_gives_the_live_graphs_messages(tmp_path):
    figures = demo.run("room", "browne_ring", laps=1, seed=0, out=tmp_path, pings=PINGS)
    demo.write_outputs(figures, tmp_path)
    assert (tmp_path / "map.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "position error: median" in (tmp_path / "summary.txt").read_text()
    assert main(["process", str(tmp_path / "bag"), str(tmp_path / "processed"), "--quiet"]) == 0
    _, live = read_bag(tmp_path / "bag")
    _, offline = read_bag(tmp_path / "processed")
    assert len(live["/echoes"]) == PINGS
    assert all(len(live[f"/range/group_{group:02d}"]) == PINGS for group in range(48))  # the recorder keeps up
    compared = 0
    for topic, kind in (("/landmarks/raw", LandmarkArray), ("/landmarks", LandmarkArray),
                        ("/landmarks/pairs", LandmarkArray), ("/markers", MarkerArray)):
        expected, got = by_stamp(live[topic], kind), by_stamp(offline[topic], kind)
        assert len(got) == PINGS
        assert len(set(expected) & set(got)) >= PINGS - 2  # best effort may drop the odd live message
        for stamp in set(expected) & set(got):
            if kind is LandmarkArray:
                assert_same_landmarks(got[stamp], expected[stamp])
            else:
                assert got[stamp] == expected[stamp]
            compared += 1
    assert compared >= 4 * (PINGS - 2)
    # record-sim with the demo's seed gives the demo driver's echoes and odometry, in order (its stamps are
    # trajectory time, the driver's the clock's), in the realistic world with every effect drawing its numbers.
    assert figures["world"] == "realistic" and figures["effects"]
    assert main(["record-sim", "room", str(tmp_path / "recorded"), "--pings", str(PINGS), "--quiet"]) == 0
    _, recorded = read_bag(tmp_path / "recorded")
    assert len(live["/odom"]) == len(recorded["/odom"]) == len(recorded["/echoes"]) == PINGS
    for (_, live_data), (_, recorded_data) in zip(live["/odom"], recorded["/odom"], strict=True):
        live_odometry, recorded_odometry = (deserialize_message(data, Odometry) for data in (live_data, recorded_data))
        assert live_odometry.pose == recorded_odometry.pose
    for (_, live_data), (_, recorded_data) in zip(live["/echoes"], recorded["/echoes"], strict=True):
        live_echoes, recorded_echoes = (echoes_from_cdr(data)[1] for data in (live_data, recorded_data))
        assert live_echoes.speed_of_sound == recorded_echoes.speed_of_sound
        for name in ("group", "transmitter", "tof", "amplitude", "phase_delay"):  # NaN: a receiver heard nothing
            assert_array_equal(getattr(live_echoes, name), getattr(recorded_echoes, name), err_msg=name)
    # The final maps: the same sightings with the same poses give the same map (the stamp is the publication time).
    live_map = deserialize_message(live["/map/landmarks"][-1][1], LandmarkArray)
    offline_map = deserialize_message(offline["/map/landmarks"][-1][1], LandmarkArray)
    assert len(landmarks_from_msg(live_map)) == sum(figures["map"].values()) > 0
    assert_same_landmarks(offline_map, live_map)


def test_the_demo_runs_a_layout_with_its_shipped_parameters_as_process_and_record_sim_do(tmp_path):
    """kreczmer_two_triads: its parameters (sigma_tof 0.33 us, not the nodes' default 1 us) in the live graph too,
    so the localiser's landmarks and the map are those ``sonar-ring process`` makes of the same bag, and
    ``record-sim`` records the driver's echoes."""
    figures = demo.run("room", "kreczmer_two_triads", laps=1, seed=0, out=tmp_path, pings=PINGS)
    assert main(["process", str(tmp_path / "bag"), str(tmp_path / "processed"), "--quiet"]) == 0
    _, live = read_bag(tmp_path / "bag")
    _, offline = read_bag(tmp_path / "processed")
    expected, got = by_stamp(live["/landmarks"], LandmarkArray), by_stamp(offline["/landmarks"], LandmarkArray)
    common = set(expected) & set(got)
    assert len(common) >= PINGS - 2  # best effort may drop the odd live message
    assert set(np.concatenate([landmarks_from_msg(got[stamp]).group for stamp in common]).tolist()) == {0, 1}
    for stamp in common:
        assert_same_landmarks(got[stamp], expected[stamp])
    live_map = deserialize_message(live["/map/landmarks"][-1][1], LandmarkArray)
    offline_map = deserialize_message(offline["/map/landmarks"][-1][1], LandmarkArray)
    assert len(landmarks_from_msg(live_map)) == sum(figures["map"].values())
    assert_same_landmarks(offline_map, live_map)
    assert main(["record-sim", "room", str(tmp_path / "recorded"), "--layout", "kreczmer_two_triads",
                 "--pings", str(PINGS), "--quiet"]) == 0
    _, recorded = read_bag(tmp_path / "recorded")
    for (_, live_data), (_, recorded_data) in zip(live["/echoes"], recorded["/echoes"], strict=True):
        assert_array_equal(echoes_from_cdr(live_data)[1].tof, echoes_from_cdr(recorded_data)[1].tof)


def test_process_reports_unknown_and_wrong_topics_and_goes_on(sim_bag, tmp_path, capsys):
    code, printed, err = run_cli(capsys, "process", str(sim_bag), str(tmp_path / "out"), "--quiet",
                                 "--echoes-topic", "/nothing", "--echoes-topic", "/odom", "--echoes-topic", "echoes",
                                 "--odom-topic", "/missing_odom")
    assert code == 0, err
    assert "sonar-ring process: warning: /nothing: not in the bag" in err
    assert "sonar-ring process: warning: /odom: type nav_msgs/msg/Odometry, not sonar_ring/msg/Echoes" in err
    assert "/missing_odom: not in the bag" in err and "map at fixed_pose [0.0, 0.0, 0.0]" in err
    assert f"processed {PINGS} pings" in printed


def test_malformed_and_misfit_messages_are_counted_not_fatal(sim_bag, tmp_path, capsys):
    bag = tmp_path / "bad"
    _, source = read_bag(sim_bag)
    wrong_layout = deserialize_message(source["/echoes"][1][1], Echoes)
    wrong_layout.layout = "kreczmer_triad"
    with BagWriter(bag) as writer:
        echoes = writer.connection("/echoes", TOPIC["echoes"].message, TOPIC["echoes"].qos)
        odom = writer.connection("/odom", TOPIC["odom"].message, TOPIC["odom"].qos)
        for k, (time_ns, raw) in enumerate(source["/echoes"][:6]):
            if k == 1:
                raw = serialize_message(wrong_layout)
            writer.write(echoes, time_ns, raw[:20] if k == 3 else raw)
        unset = deserialize_message(source["/odom"][4][1], Odometry)
        unset.pose.pose.orientation.z, unset.pose.pose.orientation.w = 1e200, 0.0  # not a rotation: its yaw raised
        for k, (time_ns, raw) in enumerate(source["/odom"][:8]):
            writer.write(odom, time_ns, raw[:30] if k == 2 else serialize_message(unset) if k == 4 else raw)
    code, printed, err = run_cli(capsys, "process", str(bag), str(tmp_path / "out"), "--quiet",
                                 "--layout", "browne_ring")
    assert code == 0, err
    assert "processed 6 pings" in printed
    assert "refused: 1 bad_odometry_pose, 1 layout_mismatch, 1 malformed_message, 1 undecodable_odometry" \
        in printed, printed
    out = read_bag(tmp_path / "out")[1]
    assert len(out["/landmarks"]) == 4
    assert len(out["/slam/pose"]) == 4  # the odometry on either side of the lost ones places every ping


def test_the_odometrys_covariance_gives_its_noise_where_it_grows(sim_bag, tmp_path, capsys):
    """The odometry messages' pose covariance: a dead reckoning's (growing) is the odometry's noise, a fixed one
    is not (the parameters' noise, noted), a broken one is counted and its pose kept."""
    _, source = read_bag(sim_bag)
    odometry = [deserialize_message(raw, Odometry) for _, raw in source["/odom"]]
    growing, fixed, broken = tmp_path / "growing", tmp_path / "fixed", tmp_path / "broken"
    for bag in (growing, fixed, broken):
        with BagWriter(bag) as writer:
            echoes = writer.connection("/echoes", TOPIC["echoes"].message, TOPIC["echoes"].qos)
            odom = writer.connection("/odom", TOPIC["odom"].message, TOPIC["odom"].qos)
            for time_ns, raw in source["/echoes"]:
                writer.write(echoes, time_ns, raw)
            travelled = 0.0
            for k, ((time_ns, _), message) in enumerate(zip(source["/odom"], odometry, strict=True)):
                if k:
                    travelled += math.dist((message.pose.pose.position.x, message.pose.pose.position.y),
                                           (odometry[k - 1].pose.pose.position.x, odometry[k - 1].pose.pose.position.y))
                covariance = np.zeros(36)
                # x, y and yaw of a dead reckoning from a pose known to 10 um, 0.1 mm per sqrt(m) since (the
                # parameters': 2 cm; a straight drive, so it grows as a diagonal)
                covariance[[0, 7, 35]] = 1e-10 + 1e-8 * travelled if bag is growing else 1e-4
                if bag is broken and k == 5:
                    covariance[0] = math.nan
                message.pose.covariance = covariance.tolist()
                writer.write(odom, time_ns, serialize_message(message))
    printed = {}
    for bag in (sim_bag, growing, fixed, broken):
        code, printed[bag], err = run_cli(capsys, "process", str(bag), str(tmp_path / f"out_{bag.name}"), "--quiet")
        assert code == 0, err
    spread = {bag: [deserialize_message(raw, PoseWithCovarianceStamped).pose.covariance[0]
                    for _, raw in read_bag(tmp_path / f"out_{bag.name}")[1]["/slam/pose"]]
              for bag in (sim_bag, growing, fixed, broken)}
    # Between keyframes the pose's variance grows with the odometry's noise since the last one.
    assert np.median(np.diff(spread[growing])) < 1e-3 * np.median(np.diff(spread[sim_bag]))
    assert spread[fixed] == spread[sim_bag] == spread[broken]
    assert "odometry covariance not growing" in printed[fixed] and "bad_odometry_covariance" not in printed[fixed]
    assert "refused: 1 bad_odometry_covariance\n" in printed[broken], printed[broken]


def test_pings_the_odometry_does_not_cover_are_counted_not_mapped(sim_bag, tmp_path, capsys):
    """As the live mapper: a ping before the first odometry or after the last has no pose."""
    bag = tmp_path / "short_odometry"
    _, source = read_bag(sim_bag)
    echoes_times = [time_ns for time_ns, _ in source["/echoes"][:8]]
    with BagWriter(bag) as writer:
        echoes = writer.connection("/echoes", TOPIC["echoes"].message, TOPIC["echoes"].qos)
        odom = writer.connection("/odom", TOPIC["odom"].message, TOPIC["odom"].qos)
        # Odometry covers pings 2 to 5 only: ping 0 and 1 come before it, 6 and 7 after it.
        kept = [(t, raw) for t, raw in source["/odom"] if echoes_times[2] <= t <= echoes_times[5]]
        assert kept
        for time_ns, raw in sorted([(t, (echoes, raw)) for t, raw in source["/echoes"][:8]]
                                   + [(t, (odom, raw)) for t, raw in kept], key=lambda item: item[0]):
            writer.write(raw[0], time_ns, raw[1])
    code, printed, err = run_cli(capsys, "process", str(bag), str(tmp_path / "out"), "--quiet")
    assert code == 0, err
    assert "processed 8 pings" in printed
    assert "2 no_odometry" in printed and "2 pose_too_old" in printed, printed
    assert len(read_bag(tmp_path / "out")[1]["/landmarks"]) == 8  # labelled all the same


def one_line_error(err):
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("sonar-ring process: error: ")
    return lines[0]


def test_a_missing_bag_is_one_line(tmp_path, capsys):
    code, _, err = run_cli(capsys, "process", str(tmp_path / "nope"), str(tmp_path / "out"))
    assert code == 1
    assert "nope: no such file or directory" in one_line_error(err)
    assert not (tmp_path / "out").exists()


def test_a_bag_without_echoes_is_one_line(tmp_path, capsys):
    from nav_msgs.msg import Odometry

    bag = tmp_path / "odom_only"
    with BagWriter(bag) as writer:
        connection = writer.connection("/odom", Odometry, TOPIC["odom"].qos)
        writer.write(connection, 1, serialize_message(Odometry()))
    code, _, err = run_cli(capsys, "process", str(bag), str(tmp_path / "out"))
    assert code == 1
    line = one_line_error(err)
    assert "no usable echoes topic" in line and "/odom (nav_msgs/msg/Odometry)" in line
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("keep", [0.5, 0.98])
def test_a_truncated_bag_is_one_line(sim_bag, tmp_path, capsys, keep):
    bag = tmp_path / "cut"
    shutil.copytree(sim_bag, bag)
    (mcap,) = bag.glob("*.mcap")
    data = mcap.read_bytes()
    mcap.write_bytes(data[:math.floor(keep * len(data))])
    code, _, err = run_cli(capsys, "process", str(bag), str(tmp_path / "out"))
    assert code == 1
    assert "truncated or corrupt" in one_line_error(err)
    assert not (tmp_path / "out").exists()


def test_an_existing_output_or_a_bad_parameter_file_is_one_line(sim_bag, tmp_path, capsys):
    code, _, err = run_cli(capsys, "process", str(sim_bag), str(sim_bag))
    assert code == 1 and "exists already" in one_line_error(err)
    params = tmp_path / "params.yaml"
    params.write_text("/**/mapper:\n  ros__parameters:\n    map_rate: 500.0\n")
    code, _, err = run_cli(capsys, "process", str(sim_bag), str(tmp_path / "out"), "--params", str(params))
    assert code == 1 and "map_rate must be in [0.1, 50.0], got 500.0" in one_line_error(err)


def test_parameters_from_a_file_reach_the_nodes_functions(sim_bag, tmp_path, capsys):
    params = tmp_path / "params.yaml"
    params.write_text("/**/localiser:\n  ros__parameters:\n    marker_lifetime: 2.0\n"
                      "/**/mapper:\n  ros__parameters:\n    map_rate: 10.0\n")
    code, _, err = run_cli(capsys, "process", str(sim_bag), str(tmp_path / "out"), "--params", str(params), "--quiet")
    assert code == 0, err
    _, messages = read_bag(tmp_path / "out")
    markers = deserialize_message(messages["/markers"][0][1], MarkerArray)
    assert {m.lifetime.sec for m in markers.markers} == {2}
    assert np.diff([t for t, _ in messages["/map/landmarks"]]).min() == 10**8  # 10 Hz ticks


def test_without_ros_the_commands_say_what_to_set_up(tmp_path):
    # The source tree has no generated sonar_ring.msg: what a `pip install .` without ROS 2 gives.
    result = subprocess.run([sys.executable, "-c", "import sys; from sonar_ring.cli import main; "
                             "sys.exit(main(['process', 'in', 'out']))"],
                            cwd=ROOT, capture_output=True, text=True, env={"PATH": "/usr/bin:/bin"})
    assert result.returncode == 1, result.stderr
    assert result.stderr.startswith("sonar-ring process: error: needs ROS 2")
    assert "source tools/env.sh" in result.stderr and "Traceback" not in result.stderr


def test_in_a_log_the_bag_commands_write_no_progress_updates(tmp_path, capsys):
    """Without --quiet, stderr not a terminal (captured): no carriage-return redraws, only what the commands say."""
    code, _, err = run_cli(capsys, "record-sim", "room", str(tmp_path / "bag"), "--pings", "20")
    assert code == 0, err
    assert "\r" not in err and len(err.splitlines()) <= 2
    code, _, err = run_cli(capsys, "process", str(tmp_path / "bag"), str(tmp_path / "out"), "--jobs", "1")
    assert code == 0, err
    assert "\r" not in err and len(err.splitlines()) <= 2
