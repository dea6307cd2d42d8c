"""Graph benchmark: ping -> markers latency and the highest sustained ping rate of the running nodes.

The nodes run as the ``graph`` executable does (one process, one executor,
composed so a ping is one callback; ``source:=topic``, fixed pose) in a child
process; this process plays the sensor and RViz, as lightly as it can (the
same two cores run both): each ping -- 48 pairs of the Browne ring, 3 echoes
per pair -- is serialized once, and goes to the driver's ``tof_in`` with the
wall clock at sending written into its stamp; a ping's
latency is the time from that stamp until the middleware here received its
markers (which carry the same stamp), so it includes both DDS hops, the
graph's executor, the driver's checks, the localiser and the marker
message, but not this process's own executor.

The graph runs twice: on one CPU (the last this process may use), as the
launch file's ``cpus`` argument runs it, for the latency and the rate ladder;
then on any CPU, as the scheduler places it, for the latency again.  On one
CPU its middleware threads hand a ping to its executor without waking the
other core, and no migration leaves its code in the other core's cache.
Then the nodes run once more, each in its own process, as the launch file
starts them by default (:func:`_latency_on_any_cpu`): every hop crosses DDS.
Needs ROS 2 (rclpy and the built ``sonar_ring`` messages).
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass

import numpy as np

from sonar_ring.echoes import EchoArrays
from sonar_ring.geometry import Layout, load_layout

LAYOUT = "browne_ring"
ECHO_RANGES = (1.0, 2.2, 3.5)
"""Distances of the three poles in front of every pair, m."""
SIGMA_TOF = 1e-6
SPEED_OF_SOUND = 343.0
LATENCY_RATE = 30.0
"""Hz: the ring's nominal ping rate, for the latency figures."""
SUSTAINED_SHARE = 0.99
"""A rate is sustained when at least this share of its pings come out as markers."""


@dataclass(frozen=True)
class Plan:
    """How long each part runs: pings at the nominal rate, and the rate ladder."""

    latency_pings: int
    ladder: tuple[float, ...]
    seconds_per_rate: float


FULL = Plan(latency_pings=600, ladder=(60, 100, 150, 200, 300, 400, 500, 700, 1000), seconds_per_rate=4.0)
QUICK = Plan(latency_pings=60, ladder=(30, 100), seconds_per_rate=1.0)


def benchmark_echoes(layout: Layout, rng: np.random.Generator) -> EchoArrays:
    """One ping with three pole echoes per pair, on the pair's axis at :data:`ECHO_RANGES`.

    Paths are exact for a vertical pole: ``sqrt((|P - T| + |P - R|)^2 + dz^2)``
    (unfolded), with Gaussian TOF noise of :data:`SIGMA_TOF`.

    Returns
    -------
    EchoArrays
        ``3 G`` rows (G groups, K = 2 receivers), sensor frame, no amplitudes.
    """
    groups = np.repeat(np.arange(layout.n_groups), len(ECHO_RANGES))
    yaw = layout.group_yaw()[groups]
    facing = np.stack([np.cos(yaw), np.sin(yaw)], axis=-1)
    centre = layout.group_centre()[groups, :2]
    pole = centre + np.tile(ECHO_RANGES, layout.n_groups)[:, None] * facing
    transmitter = layout.group_transmitters[groups, 0]
    tx = layout.transmitters[transmitter]
    receivers = layout.receivers[layout.groups[groups]]  # (N, K, 3)
    horizontal = (np.linalg.norm(pole - tx[:, :2], axis=-1)[:, None]
                  + np.linalg.norm(pole[:, None, :] - receivers[..., :2], axis=-1))
    dz = tx[:, None, 2] - receivers[..., 2]
    tof = np.sqrt(horizontal**2 + dz**2) / SPEED_OF_SOUND + rng.normal(0.0, SIGMA_TOF, horizontal.shape)
    return EchoArrays(layout.name, SPEED_OF_SOUND, groups.astype(np.uint16), transmitter.astype(np.uint8), tof,
                      np.empty((len(groups), 0)), np.empty((len(groups), 0)))


def _percentiles(latencies_ms: list[float]) -> tuple[float, float]:
    if not latencies_ms:
        return float("nan"), float("nan")
    return float(np.median(latencies_ms)), float(np.percentile(latencies_ms, 99))


def run(quick: bool = False) -> dict:
    """Start the graph, measure, stop it -- on one CPU, then on any; return the figures.

    Returns
    -------
    dict
        With the graph on one CPU (``cpu``, its index: the last this process
        may use):
        ``latency_median_ms``, ``latency_p99_ms`` (ping -> markers at
        :data:`LATENCY_RATE`), ``rate_hz`` (that rate), ``pings`` (sent at it),
        ``dropped`` (of those, pings whose markers never came),
        ``max_sustained_rate_hz`` (highest rate of the ladder with at least
        :data:`SUSTAINED_SHARE` of pings through; 0 when none), ``ladder``
        (per rate: sent, received, latency median and p99), ``node_latency_ms``
        (each node's median compute time per message from ``/diagnostics``);
        ``any_cpu``: the latency figures (the same first five keys) with the
        graph on any CPU, ``{"error": why}`` if that run failed, or None when
        this process may use one CPU only; ``separate``: the same figures with
        one process per node (:func:`_latency_on_any_cpu`), or ``{"error": why}``;
        ``rows_per_ping`` and ``note`` (what was measured).
    """
    plan = QUICK if quick else FULL
    layout = load_layout(LAYOUT)
    echoes = benchmark_echoes(layout, np.random.default_rng(0))
    allowed = sorted(os.sched_getaffinity(0))
    cpu = allowed[-1]
    domain = 100 + os.getpid() % 99  # apart from other graphs on this machine; each later run on the next one
    pinned = _session(echoes, plan, cpu, ladder=True, domain=domain)
    any_cpu = _latency_on_any_cpu(echoes, plan, domain + 1) if len(allowed) > 1 else None
    separate = _latency_on_any_cpu(echoes, plan, domain + 2, separate=True)
    placement = f"on CPU {cpu}" + (", then on any CPU" if len(allowed) > 1 else " (the only one it may use)")
    return {
        **pinned, "cpu": cpu, "any_cpu": any_cpu, "separate": separate, "rows_per_ping": echoes.n_echoes,
        "note": (f"{layout.n_groups} pairs x {len(ECHO_RANGES)} pole echoes ({echoes.n_echoes} rows) per ping, "
                 f"sigma_t {SIGMA_TOF * 1e6:g} us; the graph executable in its own process (source:=topic, fixed "
                 f"pose), {placement}; latency from the ping's stamp to its markers arriving in another process"),
    }


def _latency_on_any_cpu(echoes: EchoArrays, plan: Plan, domain: int, separate: bool = False) -> dict:
    """The latency figures of :func:`_session` on any CPU (:func:`run`'s ``any_cpu`` keys), or ``{"error": why}``.

    ``separate``: one process per node, as the launch file starts them by
    default, so the pings cross DDS between the nodes too.
    """
    try:
        result = _session(echoes, plan, None, ladder=False, domain=domain, separate=separate)
    except Exception as exc:  # the pinned figures stand on their own
        return {"error": f"failed: {exc}"}
    return {key: result[key] for key in ("latency_median_ms", "latency_p99_ms", "rate_hz", "pings", "dropped")}


def _session(echoes: EchoArrays, plan: Plan, cpu: int | None, ladder: bool, domain: int,
             separate: bool = False) -> dict:
    """One run of the graph process (``separate``: of one process per node), on ``cpu`` (None: any).

    Its latency, and the rate ladder if asked.  The graph and this process
    meet in ROS ``domain``.  Returns the keys of :func:`run` up to
    ``node_latency_ms``.
    """
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import qos_profile_sensor_data
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Header
    from visualization_msgs.msg import MarkerArray

    from sonar_ring.msg import Echoes
    from sonar_ring.ros.convert import echoes_to_msg

    environment = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    # Set before rclpy starts: the middleware's threads, made later, inherit it.
    placement = "" if cpu is None else f"import os; os.sched_setaffinity(0, {{{cpu}}}); "
    from sonar_ring.ros.graph import NODES

    modules = [node.__module__ for node in NODES] if separate else ["sonar_ring.ros.graph"]
    errors = tempfile.TemporaryFile(mode="w+")
    # cwd "/": a source checkout as cwd would shadow the built package (which holds sonar_ring.msg)
    processes = [subprocess.Popen([sys.executable, "-c", placement + f"from {module} import main; main()",
                                   "--ros-args", "-p", "source:=topic", "-p", f"layout:={LAYOUT}",
                                   "-p", "use_odometry:=false", "--log-level", "error"],
                                  cwd="/", env=environment, stdout=subprocess.DEVNULL, stderr=errors, text=True)
                 for module in modules]
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    arrived: dict[int, int] = {}
    node_latency: dict[str, float] = {}
    try:
        node = rclpy.create_node("graph_benchmark", context=context)
        sender = node.create_publisher(Echoes, "tof_in", qos_profile_sensor_data)
        ping = bytearray(serialize_message(echoes_to_msg(echoes, Header(frame_id="sonar_ring"))))

        def on_markers(raw: bytes, info) -> None:
            # The middleware's reception time: this process's executor delay is not the graph's latency.
            # The stamp is read from the bytes (after the encapsulation and the marker count, the first
            # marker's header): this process plays the sensor and RViz on a 2-core machine, and decoding
            # every MarkerArray in Python would take CPU time from the graph it measures.
            if len(raw) >= 16 and struct.unpack_from("<I", raw, 4)[0]:
                sec, nanosec = struct.unpack_from("<iI", raw, 8)
                arrived.setdefault(sec * 10**9 + nanosec, info["received_timestamp"])

        def on_diagnostics(message) -> None:
            for status in message.status:
                values = {pair.key: pair.value for pair in status.values}
                if values.get("latency median (ms)", "n/a") != "n/a":
                    node_latency[status.name.rsplit("/", 1)[-1]] = float(values["latency median (ms)"])

        from diagnostic_msgs.msg import DiagnosticArray

        node.create_subscription(MarkerArray, "markers", on_markers, 100, raw=True)
        node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        deadline = time.monotonic() + 30.0
        while sender.get_subscription_count() < 1 or node.count_publishers("markers") < 1:
            if any(process.poll() is not None for process in processes) or time.monotonic() > deadline:
                errors.seek(0)
                raise RuntimeError(f"the graph did not start: {errors.read().strip() or 'no output'}")
            executor.spin_once(timeout_sec=0.1)

        def send(rate: float, count: int) -> list[int]:
            """Send ``count`` pings at ``rate``; return their stamps (ns), after waiting for stragglers."""
            stamps = []
            period = 1.0 / rate
            start = time.perf_counter()
            for index in range(count):
                while (wait := start + index * period - time.perf_counter()) > 0:
                    executor.spin_once(timeout_sec=wait)
                stamp = time.time_ns()
                struct.pack_into("<iI", ping, 4, *divmod(stamp, 10**9))  # the header's stamp, after the encapsulation
                sender.publish(bytes(ping))
                stamps.append(stamp)
            settle = time.monotonic() + 0.5
            while time.monotonic() < settle:
                executor.spin_once(timeout_sec=0.02)
            return stamps

        def figures(stamps: list[int]) -> tuple[int, list[float]]:
            latencies = [(arrived[s] - s) * 1e-6 for s in stamps if s in arrived]
            return len(latencies), latencies

        send(LATENCY_RATE, 30)  # warm-up: discovery of every topic, first-call costs
        stamps = send(LATENCY_RATE, plan.latency_pings)
        received, latencies = figures(stamps)
        median, p99 = _percentiles(latencies)
        steps = []
        sustained = 0.0
        for rate in plan.ladder if ladder else ():
            sent = send(rate, int(rate * plan.seconds_per_rate))
            through, rate_latencies = figures(sent)
            steps.append({"rate_hz": rate, "sent": len(sent), "received": through,
                          "latency_median_ms": _percentiles(rate_latencies)[0],
                          "latency_p99_ms": _percentiles(rate_latencies)[1]})
            if through < SUSTAINED_SHARE * len(sent):
                break
            sustained = rate
    finally:
        context.try_shutdown()
        for process in processes:
            process.terminate()
        for process in processes:
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()
        errors.close()
    return {"latency_median_ms": median, "latency_p99_ms": p99, "rate_hz": LATENCY_RATE, "pings": len(stamps),
            "dropped": len(stamps) - received, "max_sustained_rate_hz": sustained, "ladder": steps,
            "node_latency_ms": node_latency}
