"""localiser: each ping's echoes to plane / corner / edge hypotheses with covariance.

Subscribes ``echoes`` (sonar_ring/Echoes); publishes ``landmarks/raw``
(sonar_ring/LandmarkArray, one message per ping, valid hypotheses only, in the
echoes' frame) and ``/diagnostics`` (invalid hypotheses counted by reason: a
receiver that missed the echo, no real solution, ...).
"""

from __future__ import annotations

import time

import numpy as np
from rclpy.qos import qos_profile_sensor_data
from rclpy.subscription import MessageInfo

from sonar_ring import localise, pipeline
from sonar_ring.echoes import EchoArrays
from sonar_ring.echoes import load_kernels as load_screening_kernels
from sonar_ring.geometry import load_layout
from sonar_ring.msg import Echoes, LandmarkArray
from sonar_ring.ros.convert import AnyHeader, serialize_landmarks
from sonar_ring.ros.diagnostics import NodeHealth
from sonar_ring.ros.inputs import EXPECTED_FRAME, FUTURE_TOLERANCE, InputGate, check_echoes, take_echoes
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
    Param("sigma_tof", 1e-6, "time-of-flight noise for covariances, s", low=1e-9, high=1e-3),
    Param("sigma_speed", pipeline.ROBOT_SIGMA_SPEED, "speed-of-sound uncertainty for covariances, m/s (the "
          "default: the air's temperature known to about 2 K)", low=0.0, high=20.0),
    Param("triad_eps", 0.0, "triads: Kreczmer eq 6 tolerance (0: from his robustness procedure for the layout)",
          low=0.0, high=1.0),
    Param("triad_max_angle", 50.0, "triads: largest azimuth accepted, deg", low=1.0, high=90.0),
    EXPECTED_FRAME,
    FUTURE_TOLERANCE,
]


def settings_from(values: dict) -> pipeline.Settings:
    """The pipeline settings the localiser and classifier parameters describe."""
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
    """Echoes in, landmark hypotheses out, one message per ping."""

    def __init__(self, **kwargs) -> None:
        super().__init__("localiser", **kwargs)
        self.params = declare(self, PARAMS, self._on_change)
        self.layout = load_layout(self.params["layout"])
        self.settings = settings_from(self.params)
        load_screening_kernels()  # now, or the first ping would wait for numba to load them
        if self.layout.kind != "triad":
            localise.load_kernels()
        self.health = NodeHealth(self, hardware_id=self.layout.name)
        self._publisher = self.create_publisher(LandmarkArray, "landmarks/raw", qos_profile_sensor_data)
        self._gate = InputGate(self, self.health, "echoes", self.params)
        self.ping_inputs = (self.create_subscription(Echoes, "echoes", self._on_echoes, qos_profile_sensor_data,
                                                     raw=True),)

    def _on_change(self, changed: dict) -> None:
        self.settings = settings_from(self.params)

    def _on_echoes(self, data: bytes, info: MessageInfo) -> None:
        started = time.perf_counter()
        self.health.received()
        taken = take_echoes(data, info, self._gate, self.health)
        if taken is None:
            return
        header, echoes = taken
        usable = check_echoes(header, echoes, self.layout, self.health)
        if usable is not None:
            self._localise(header, usable, started)

    def on_ping(self, header: AnyHeader, echoes: EchoArrays) -> None:
        """A ping from the driver in this process: the header it publishes and the screened arrays."""
        started = time.perf_counter()
        self.health.received()
        if self._gate.admit(header):
            self._localise(header, echoes, started)

    def _localise(self, header: AnyHeader, echoes: EchoArrays, started: float) -> None:
        hypotheses = pipeline.localise_ping(self.layout, echoes, self.settings)
        # The labelled landmarks, not these hypotheses, are what a ping is for: in one process they go first.
        # The classifier labels from the valid ones only, so the invalid ones need not be taken out first.
        downstream = self.pass_on(header, echoes, hypotheses)
        invalid = hypotheses.reason[~hypotheses.valid]
        for code, count in zip(*np.unique(invalid, return_counts=True), strict=True):
            self.health.note(f"invalid hypothesis: {localise.REASONS[int(code)]}", int(count))
        self._publisher.publish(serialize_landmarks(hypotheses.select(hypotheses.valid), header))
        self.health.processed(time.perf_counter() - started - downstream)


def main(args=None) -> None:
    """Run the localiser until Ctrl-C or shutdown."""
    spin(Localiser, args=args)


if __name__ == "__main__":
    main()
