"""Classifier measurements: Barshan & Kuc's amplitude rules on their bench, the ring's consistency test.

* :func:`confusion` -- the simulated bench of Barshan & Kuc's section V: the
  ``barshan_kuc_pair`` layout in front of the ``barshan_kuc_bench`` scene's plane
  or corner at 200-1600 mm and -15..15 deg, amplitude noise 2 % of A_max.
* :func:`ring_decisions` -- :func:`sonar_ring.ring_consistency.ring_consistency` on
  stacked ring pings: which rows it calls EDGE, which specular.
* :func:`amplitude_rule_times` -- the speed of :func:`sonar_ring.amplitude_rules.classify_amplitudes`.
"""

from __future__ import annotations

import math

import numpy as np

from sonar_ring import amplitude_rules, ring_consistency, simulate
from sonar_ring.benchmark.timing import best_time
from sonar_ring.geometry import load_layout
from sonar_ring.landmarks import CORNER, EDGE, PLANE

MM = 1e-3
SIGMA_REL = 0.02
"""Amplitude noise relative to A_max (Barshan & Kuc measured 2 %)."""
BENCH_SIGMA_TOF = 1e-6
RANGES_MM = np.arange(200, 1601, 100)
INCLINATIONS_DEG = np.arange(-15.0, 15.1, 2.5)


def bench_scene():
    """The shipped bench scene and, per class, (reflector index, the point ranges are measured to)."""
    scene = simulate.load_scene("barshan_kuc_bench")
    names = scene.reflector_names
    plane_x = scene.walls[scene.kind_index[names.index("plane")]][0, 0]
    apex = scene.corner_point[scene.kind_index[names.index("corner")]]
    # Sensor poses putting the pair centre at range R from the reflector, turned by -theta so
    # that the plane's normal (or the apex) lies at +theta in the sensor frame.
    targets = {PLANE: (names.index("plane"), np.array([plane_x, 0.0])),
               CORNER: (names.index("corner"), apex)}
    return scene, targets


def poses_at(target_point, range_m, inclination, trials):
    """``trials`` copies of the pose at ``range_m`` from ``target_point`` seeing it at ``inclination``, (P, 3)."""
    return np.tile([target_point[0] - range_m, target_point[1], -inclination], (trials, 1))


def pair_measurements(simulator, poses, reflector, noise, rng):
    """Amplitudes and path lengths (m) of one reflector's echoes, shape (P, G, M, K).

    Indexed ``[ping, group, transmitter slot, receiver]``; NaN where not heard.
    """
    table = simulate.stack_pings(simulator.run(poses, noise=noise, rng=rng))
    layout = simulator.layout
    n_pings, n_groups = len(poses), layout.n_groups
    slots = layout.group_transmitters.shape[1]
    amplitude = np.full((n_pings, n_groups, slots, layout.receivers_per_group), np.nan)
    path = np.full_like(amplitude, np.nan)
    mine = table["truth_reflector"] == reflector
    group = table["group"][mine]
    slot = np.argmax(layout.group_transmitters[group] == table["transmitter"][mine][:, None], axis=1)
    amplitude[table["ping"][mine], group, slot] = table["amplitude"][mine]
    speed = table["speed_of_sound"][table["ping"][mine]][:, None]
    path[table["ping"][mine], group, slot] = table["tof"][mine] * speed
    return amplitude, path


def confusion(trials, rng):
    """Decision counts on the simulated bench, and the beam half-angle theta0 (rad).

    Returns
    -------
    counts : ndarray of int, shape (4, R, I, 4)
        ``[truth class, range, inclination, decided class]`` over
        :data:`RANGES_MM` and :data:`INCLINATIONS_DEG`, ``trials`` pings per cell.
    theta0 : float
    """
    scene, targets = bench_scene()
    simulator = simulate.Simulator(scene, load_layout("barshan_kuc_pair"))
    noise = simulate.Noise(tof=BENCH_SIGMA_TOF, amplitude=SIGMA_REL)
    counts = np.zeros((4, RANGES_MM.size, INCLINATIONS_DEG.size, 4), dtype=int)
    for cls, (reflector, point) in targets.items():
        for i, range_mm in enumerate(RANGES_MM):
            for j, inclination in enumerate(INCLINATIONS_DEG):
                poses = poses_at(point, range_mm * MM, math.radians(inclination), trials)
                amplitude, _ = pair_measurements(simulator, poses, reflector, noise, rng)
                codes = amplitude_rules.classify_amplitudes(amplitude[:, 0], SIGMA_REL).cls
                counts[cls, i, j] = np.bincount(codes, minlength=4)
    return counts, simulator.half_angle


def ring_decisions(layout, table, sigma_tof):
    """Per echo row of stacked ring pings: truth is edge, decided EDGE, decided specular (three (N,) bool)."""
    speed = table["speed_of_sound"][table["ping"]][:, None]
    result = ring_consistency.ring_consistency(layout, table["group"], speed * table["tof"],
                                       float(np.mean(table["speed_of_sound"])) * sigma_tof, ping=table["ping"])
    return table["truth_class"] == EDGE, result.cls == EDGE, result.specular


def amplitude_rule_times(rng, batch: int, ping_rows: int, calls: int, repeats: int) -> tuple[float, float]:
    """Seconds per echo of :func:`amplitude_rules.classify_amplitudes` in a batch, and per call of ``ping_rows`` echoes.

    Random amplitudes in [0, 1): the rule's cost does not depend on the values.
    """
    amplitude = rng.uniform(0, 1, (batch, 2, 2))
    per_echo = best_time(lambda: amplitude_rules.classify_amplitudes(amplitude, SIGMA_REL), repeats) / batch
    ping = amplitude[:ping_rows]

    def per_ping():
        for _ in range(calls):
            amplitude_rules.classify_amplitudes(ping, SIGMA_REL)

    return per_echo, best_time(per_ping, repeats) / calls
