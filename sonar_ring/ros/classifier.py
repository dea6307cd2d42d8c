"""classifier: labels each ping's hypotheses and draws them for RViz.

Subscribes ``echoes`` and ``landmarks/raw`` and pairs them by stamp (the
hypotheses of a ping carry its echoes' header).  Publishes ``landmarks``
(sonar_ring/LandmarkArray: one labelled landmark per echo, class, confidence),
``markers`` (visualization_msgs/MarkerArray) and ``/diagnostics``.
"""

from __future__ import annotations

import time
from collections import OrderedDict

import numpy as np
from rclpy.qos import qos_profile_sensor_data
from visualization_msgs.msg import MarkerArray

from sonar_ring import pipeline, ring_consistency
from sonar_ring.echoes import EchoArrays
from sonar_ring.echoes import load_kernels as load_screening_kernels
from sonar_ring.geometry import load_layout
from sonar_ring.landmarks import EDGE, Landmarks
from sonar_ring.msg import Echoes, LandmarkArray
from sonar_ring.ros.convert import AnyHeader, MessageError, landmarks_from_msg, serialize_landmarks
from sonar_ring.ros.diagnostics import NodeHealth
from sonar_ring.ros.inputs import EXPECTED_FRAME, FUTURE_TOLERANCE, InputGate, check_echoes, take_echoes
from sonar_ring.ros.localiser import settings_from
from sonar_ring.ros.markers import landmark_markers, serialize_markers
from sonar_ring.ros.node import SonarNode
from sonar_ring.ros.params import Param, declare
from sonar_ring.ros.run import spin

PENDING_LIMIT = 32
"""Pings waiting for their other half; the oldest is dropped (and counted) beyond this."""

PARAMS = [
    Param("layout", "browne_ring", "sensor layout: a name in config/layouts or a YAML path", read_only=True),
    Param("sigma_tof", 1e-6, "time-of-flight noise for the consistency test, s", low=1e-9, high=1e-3),
    Param("sigma_amplitude", 0.02, "amplitude noise relative to A_max (Barshan & Kuc rules)", low=1e-4,
          high=0.16),
    Param("consistency_z", ring_consistency.CONSISTENCY_Z, "significance of the edge/specular consistency test, "
          "standard deviations", low=1.0, high=10.0),
    Param("marker_lifetime", 0.5, "seconds before a ping's markers vanish", low=0.0, high=60.0),
    EXPECTED_FRAME,
    FUTURE_TOLERANCE,
]


class Classifier(SonarNode):
    """Hypotheses and echoes in, labelled landmarks and markers out, one message each per ping."""

    def __init__(self, **kwargs) -> None:
        super().__init__("classifier", **kwargs)
        self.params = declare(self, PARAMS, self._on_change)
        self.layout = load_layout(self.params["layout"])
        self.settings = settings_from(self.params)
        load_screening_kernels()  # now, or the first ping would wait for numba to load them
        pipeline.load_kernels()
        if self.layout.kind == "ring":
            ring_consistency.load_kernels()
        self.health = NodeHealth(self, hardware_id=self.layout.name)
        self._pending: OrderedDict[tuple, dict] = OrderedDict()
        self._landmarks = self.create_publisher(LandmarkArray, "landmarks", qos_profile_sensor_data)
        self._markers = self.create_publisher(MarkerArray, "markers", 10)
        self._gates = {kind: InputGate(self, self.health, topic, self.params)
                       for kind, topic in (("echoes", "echoes"), ("raw", "landmarks/raw"))}
        self.ping_inputs = (
            self.create_subscription(Echoes, "echoes", self._echoes_arrived, qos_profile_sensor_data, raw=True),
            self.create_subscription(LandmarkArray, "landmarks/raw", self._hypotheses_arrived,
                                     qos_profile_sensor_data))

    def _on_change(self, changed: dict) -> None:
        self.settings = settings_from(self.params)

    def _echoes_arrived(self, data: bytes, info) -> None:
        taken = take_echoes(data, info, self._gates["echoes"], self.health)
        if taken is not None:
            self._arrived("echoes", *taken)

    def _hypotheses_arrived(self, msg: LandmarkArray, info) -> None:
        if self._gates["raw"].admit(msg.header, info):
            self._arrived("raw", msg.header, msg)

    def _arrived(self, kind: str, header: AnyHeader, value) -> None:
        key = (header.stamp.sec, header.stamp.nanosec, header.frame_id)
        halves = self._pending.setdefault(key, {})
        halves[kind] = value
        if len(halves) == 2:
            del self._pending[key]
            self._classify(header, halves["echoes"], halves["raw"])
        while len(self._pending) > PENDING_LIMIT:
            _, dropped = self._pending.popitem(last=False)
            self.health.problem("unpaired_" + "_".join(sorted(dropped)), "no matching ping arrived")

    def _classify(self, header: AnyHeader, echoes: EchoArrays, raw_msg: LandmarkArray) -> None:
        started = time.perf_counter()
        self.health.received()
        echoes = check_echoes(header, echoes, self.layout, self.health)
        if echoes is None:
            return
        try:
            hypotheses = landmarks_from_msg(raw_msg)
        except MessageError as error:
            self.health.problem("malformed_message", str(error))
            return
        stray = (hypotheses.echo >= echoes.n_echoes) | (hypotheses.landmark_class > EDGE)
        if stray.any():  # left out by classify_ping; the rest of the ping is labelled
            self.health.problem("stray_hypothesis", "landmarks/raw names an echo row or class this ping does not have",
                                int(np.count_nonzero(stray)))
        self._label(header, echoes, hypotheses, started)

    def on_ping(self, header: AnyHeader, echoes: EchoArrays, hypotheses: Landmarks) -> None:
        """A ping from the localiser in this process: its echoes' header, screened arrays and hypotheses.

        The hypotheses may include invalid ones: :func:`sonar_ring.pipeline.classify_ping`
        labels from the valid ones only, as it does for ``landmarks/raw``, which holds those alone.
        """
        started = time.perf_counter()
        self.health.received()
        if self._gates["echoes"].admit(header):
            self._label(header, echoes, hypotheses, started)

    def _label(self, header, echoes: EchoArrays, hypotheses: Landmarks, started: float) -> None:
        labelled = pipeline.classify_ping(self.layout, echoes, hypotheses, self.settings)
        # Markers first: RViz shows a ping as soon as it can.
        self._markers.publish(serialize_markers(landmark_markers(labelled, "landmarks", self.params["marker_lifetime"]),
                                                header))
        self._landmarks.publish(serialize_landmarks(labelled, header))
        downstream = self.pass_on(header, labelled)
        self.health.processed(time.perf_counter() - started - downstream, published=2)


def main(args=None) -> None:
    """Run the classifier until Ctrl-C or shutdown."""
    spin(Classifier, args=args)


if __name__ == "__main__":
    main()
