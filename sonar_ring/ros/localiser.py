"""localiser: each ping's echoes to landmark hypotheses, labelled, and drawn for RViz.

Subscribes ``echoes`` (sonar_ring/Echoes); publishes ``markers``
(visualization_msgs/MarkerArray) and ``landmarks`` (sonar_ring/LandmarkArray:
one labelled landmark per echo, class, confidence; on a ring an echo several
pairs heard is fitted over all their receivers), ``landmarks/pairs`` (one per
echo row, its pair's closed form: independent sightings, the mapper's input),
``landmarks/raw`` (every valid hypothesis: plane / corner / edge per echo row)
-- one message each per ping, in the echoes' frame -- and ``/diagnostics``
(refused inputs, and invalid hypotheses counted by reason: a receiver that
missed the echo, no real solution, ...).

The work on a ping is the core's :class:`~sonar_ring.ping_stage.PingStage`:
Browne's localisation, then the layout's evidence (Barshan & Kuc's amplitude
rules, the ring's consistency test) picks one hypothesis per echo row, and
:meth:`~sonar_ring.ping_stage.PingStage.publishable` makes one landmark of each
echo.  All run here, on the ping they need, so the echoes are decoded and
checked once.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
from rclpy.qos import qos_profile_sensor_data
from rclpy.subscription import MessageInfo
from visualization_msgs.msg import MarkerArray

from sonar_ring import localise, pipeline, ring_consistency
from sonar_ring.echoes import EchoArrays
from sonar_ring.geometry import load_layout
from sonar_ring.msg import Echoes, LandmarkArray
from sonar_ring.ping_stage import PingStage, check_ping
from sonar_ring.ros.convert import AnyHeader, serialize_landmarks
from sonar_ring.ros.diagnostics import NodeHealth
from sonar_ring.ros.inputs import EXPECTED_FRAME, FUTURE_TOLERANCE, TopicCheck, node_clock, stamp_ns
from sonar_ring.ros.markers import landmark_markers, serialize_markers
from sonar_ring.ros.node import SonarNode
from sonar_ring.ros.params import Param, declare
from sonar_ring.ros.run import spin


def _models_problem(models) -> str | None:
    try:
        pipeline.Settings(models=tuple(models))
    except ValueError as error:
        return str(error)
    return None


PARAMS = [
    Param("layout", "browne_ring", "sensor layout: a name in config/layouts or a YAML path", read_only=True),
    Param("models", ["plane", "corner", "edge"], "localisation models to run: plane, corner, edge",
          check=_models_problem),
    Param("vertical_correction", True, "use the exact horizontal path sqrt(d^2 - dz^2) (vertically extruded "
          "reflectors)"),
    Param("sigma_tof", 1e-6, "time-of-flight noise for covariances and the consistency test, s", low=1e-9, high=1e-3),
    Param("sigma_speed", pipeline.ROBOT_SIGMA_SPEED, "speed-of-sound uncertainty for covariances, m/s (the "
          "default: the air's temperature known to about 2 K)", low=0.0, high=20.0),
    Param("triad_eps", 0.0, "triads: Kreczmer eq 6 tolerance (0: from his robustness procedure for the layout)",
          low=0.0, high=1.0),
    Param("triad_max_angle", 50.0, "triads: largest azimuth accepted, deg", low=1.0, high=90.0),
    Param("sigma_amplitude", 0.02, "amplitude noise relative to A_max (Barshan & Kuc rules)", low=1e-4,
          high=0.16),
    Param("consistency_z", ring_consistency.CONSISTENCY_Z, "significance of the edge/specular consistency test, "
          "standard deviations", low=1.0, high=10.0),
    Param("marker_lifetime", 0.5, "seconds before a ping's markers vanish", low=0.0, high=60.0),
    EXPECTED_FRAME,
    FUTURE_TOLERANCE,
]


def settings_from(values: dict) -> pipeline.Settings:
    """The pipeline settings the localiser's parameters describe."""
    return pipeline.Settings(
        models=tuple(values.get("models", pipeline.Settings.models)),
        vertical_correction=bool(values.get("vertical_correction", True)),
        sigma_tof=float(values["sigma_tof"]),
        sigma_speed=float(values.get("sigma_speed", 0.0)),
        sigma_amplitude=float(values.get("sigma_amplitude", pipeline.Settings.sigma_amplitude)),
        consistency_z=float(values.get("consistency_z", pipeline.Settings.consistency_z)),
        triad_eps=float(values.get("triad_eps", pipeline.Settings.triad_eps)),
        triad_max_angle=float(np.radians(values.get("triad_max_angle", 50.0))),
    )


class Localiser(SonarNode):
    """Echoes in; markers, landmarks, the pairs' landmarks and hypotheses out, one message each per ping."""

    def __init__(self, **kwargs) -> None:
        super().__init__("localiser", **kwargs)
        self.params = declare(self, PARAMS, self._on_change)
        self.layout = load_layout(self.params["layout"])
        self.stage = PingStage(self.layout, settings_from(self.params))
        self.stage.load_kernels()  # now, or the first ping would wait for numba to load them
        self.health = NodeHealth(self, hardware_id=self.layout.name)
        self._markers = self.create_publisher(MarkerArray, "markers", 10)
        self._landmarks = self.create_publisher(LandmarkArray, "landmarks", qos_profile_sensor_data)
        self._pairs = self.create_publisher(LandmarkArray, "landmarks/pairs", qos_profile_sensor_data)
        self._hypotheses = self.create_publisher(LandmarkArray, "landmarks/raw", qos_profile_sensor_data)
        self._check = TopicCheck(node_clock(self), self.health, "echoes", self.params)
        self.ping_inputs = (self.create_subscription(Echoes, "echoes", self._on_echoes, qos_profile_sensor_data,
                                                     raw=True),)

    def _on_change(self, changed: dict) -> None:
        self.stage = replace(self.stage, settings=settings_from(self.params))

    def _on_echoes(self, data: bytes, info: MessageInfo) -> None:
        started = time.perf_counter()
        self.health.received()
        taken = self._check.take_echoes(data, info)
        if taken is None:
            return
        header, echoes = taken
        usable = check_ping(echoes, self.layout, self.health, stamp_ns(header))
        if usable is not None:
            self._label(header, usable, started)

    def on_ping(self, header: AnyHeader, echoes: EchoArrays) -> None:
        """A ping from the driver in this process: the header it publishes and the arrays it checked."""
        started = time.perf_counter()
        self.health.received()
        if self._check.admit(header):
            self._label(header, echoes, started)

    def _label(self, header: AnyHeader, echoes: EchoArrays, started: float) -> None:
        hypotheses, labelled, published = self.stage.label_and_publish(echoes)
        # Markers first: RViz shows a ping as soon as it can; then the landmarks, the mapper's input, the hypotheses.
        self._markers.publish(serialize_markers(landmark_markers(published, "landmarks",
                                                                 self.params["marker_lifetime"]), header))
        self._landmarks.publish(serialize_landmarks(published, header))
        self._pairs.publish(serialize_landmarks(labelled, header))
        downstream = self.pass_on(header, labelled)
        invalid = hypotheses.reason[~hypotheses.valid]
        for code, count in zip(*np.unique(invalid, return_counts=True), strict=True):
            self.health.note(f"invalid hypothesis: {localise.REASONS[int(code)]}", int(count))
        self._hypotheses.publish(serialize_landmarks(hypotheses.select(hypotheses.valid), header))
        self.health.processed(time.perf_counter() - started - downstream, published=4)


def main(args=None) -> None:
    """Run the localiser until Ctrl-C or shutdown."""
    spin(Localiser, args=args)


if __name__ == "__main__":
    main()
