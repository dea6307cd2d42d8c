"""Tests of the numba kernels' mechanics (sonar_ring.compiled); their numbers are tested with their modules."""

import dataclasses
import subprocess
import sys

import numba
import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from sonar_ring import confidence, localise, mapping, pipeline, ring_consistency, solvers
from sonar_ring import echoes as echoes_module
from sonar_ring.compiled import _DISPATCHERS
from sonar_ring.echoes import screen_ping
from sonar_ring.geometry import load_layout
from sonar_ring.simulate import Noise, Simulator, load_scene


def test_a_kernel_becomes_its_dispatcher_and_matches_its_python_source():
    matrices = np.array([[[2.0, 1.0], [1.0, 3.0]], [[4.0, -1.0], [-1.0, 0.5]]])
    inverse = mapping._inverse(matrices)
    assert_allclose(inverse @ matrices, np.broadcast_to(np.eye(2), (2, 2, 2)), atol=1e-15)
    # Every kernel of every module is now the compiled dispatcher itself, and the
    # machine code gives exactly what the Python source gives.
    for function in (mapping._inverse, mapping._sandwich, solvers.solve_rows):
        assert isinstance(function, numba.core.registry.CPUDispatcher)
    assert_array_equal(mapping._inverse(matrices), mapping._inverse.py_func(matrices))


def test_kernels_call_kernels():
    """_match_walls calls _inverse, _sandwich, _line_floor and _mahalanobis2 as compiled code."""
    anchor = np.array([[0.0, 1.0], [0.5, 1.01]])
    line = np.zeros((2, 2))
    information = np.tile(np.diag([1e4, 1e6]), (2, 1, 1))
    normal = np.tile([0.0, 1.0], (2, 1))
    tangent = np.tile([-1.0, 0.0], (2, 1))
    extent = np.array([[-0.2, 0.2], [-0.2, 0.2]])
    keep, other = np.array([0]), np.array([1])
    compiled = mapping._match_walls(keep, other, anchor, line, information, normal, tangent, extent, 0.001)
    python = mapping._match_walls.py_func(keep, other, anchor, line, information, normal, tangent, extent, 0.001)
    for a, b in zip(compiled, python, strict=True):
        assert_array_equal(a, b)
    assert_allclose(compiled[2], [[0.0, 0.01]], atol=1e-15)  # innovation: same angle, 1 cm apart


def test_error_handling():
    # IEEE division, as numpy: a singular matrix gives inf and NaN, not ZeroDivisionError.
    inverse = mapping._inverse(np.zeros((1, 2, 2)))
    assert np.all(~np.isfinite(inverse))
    # Arguments of the wrong kind are refused by the type checker, with the kernel named.
    with pytest.raises(numba.core.errors.TypingError, match="_inverse"):
        mapping._inverse("not an array")


def _read_only(arrays, fortran=False):
    """``arrays`` (a dataclass of numpy arrays) with every array a read-only view, as decoded from a message.

    ``fortran``: the 2-D ones in Fortran order, as a caller of the core may hand
    them (another type to numba).
    """
    views = {}
    for field in dataclasses.fields(arrays):
        value = getattr(arrays, field.name)
        if isinstance(value, np.ndarray):
            value = (np.asfortranarray(value) if fortran and value.ndim == 2 else value).view()
            value.flags.writeable = False
        views[field.name] = value
    return type(arrays)(**views)


@pytest.mark.parametrize("layout_name", ["browne_ring", "barshan_kuc_pair", "kreczmer_triad"])
def test_load_kernels_leaves_nothing_to_compile_at_the_first_ping(layout_name):
    """After the modules' load_kernels, a ping through the nodes' steps compiles no new signature.

    A signature compiled at the first ping stalls that ping for seconds; a read-only
    array (a view of a message's buffer) is another type to numba than a writable one.
    """
    for module in (echoes_module, localise, confidence, ring_consistency, pipeline, mapping):
        module.load_kernels()
    layout = load_layout(layout_name)
    scene = load_scene("barshan_kuc_bench" if layout.kind == "pair" else "room")
    times, poses = scene.trajectory.poses(layout.ping_rate)
    ping = Simulator(scene, layout).run(poses[:1], times[:1], noise=Noise(tof=1e-6), rng=np.random.default_rng(0))[0]
    # the simulator is the test's source, not a node's step: what it compiles does not count
    compiled = {key: len(dispatcher.signatures) for key, dispatcher in _DISPATCHERS.items()}
    received = _read_only(ping.echoes, fortran=True)
    screened = screen_ping(received, layout).echoes
    hypotheses = pipeline.localise_ping(layout, _read_only(screened, fortran=True))
    labelled = pipeline.classify_ping(layout, _read_only(screened, fortran=True),
                                      _read_only(hypotheses.select(hypotheses.valid)))
    landmark_map = mapping.LandmarkMap()
    landmark_map.update(_read_only(labelled), (0.0, 0.0, 0.0))
    landmark_map.update(_read_only(labelled), (0.01, 0.0, 0.0))
    assert len(labelled) > 0
    grown = {key: (compiled.get(key, 0), len(dispatcher.signatures)) for key, dispatcher in _DISPATCHERS.items()
             if len(dispatcher.signatures) != compiled.get(key, 0)}
    assert grown == {}, f"compiled at the first ping (kernel: signatures before, after): {grown}"


_SLAM_MAPPER_FIRST_PINGS = """
import numpy as np
from sonar_ring import pipeline
from sonar_ring.benchmark import worlds
from sonar_ring.compiled import _DISPATCHERS
from sonar_ring.explain import EchoTests
from sonar_ring.geometry import load_layout
from sonar_ring.landmarks import Landmarks
from sonar_ring.map_builder import MapBuilder, MapperSettings
from sonar_ring.ping_stage import Counts, PingStage

recorded = worlds.simulate_run("realistic", 0, laps=1, pings=70)
layout = load_layout(worlds.LAYOUT)
stage = PingStage(layout, pipeline.Settings(sigma_speed=pipeline.ROBOT_SIGMA_SPEED))
labelled = [stage.label(echoes)[1] if echoes is not None else Landmarks.empty() for echoes in recorded.echoes]
builder = MapBuilder(MapperSettings(slam=True, pose_history=None, layout=layout, echo_tests=EchoTests()), Counts())
builder.load_kernels()
compiled = {key: len(dispatcher.signatures) for key, dispatcher in _DISPATCHERS.items()}
for k, (landmarks, pose) in enumerate(zip(labelled, recorded.odometry, strict=True)):
    stamp = int(round(1e9 * (1.0 + k / layout.ping_rate)))
    builder.add_odometry(stamp, pose)
    builder.add_ping(stamp, landmarks)
    builder.snapshot()
assert builder.health.notes["multipath explained"] > 0 and len(builder.snapshot()) > 0
print({key: (compiled.get(key, 0), len(dispatcher.signatures)) for key, dispatcher in _DISPATCHERS.items()
       if len(dispatcher.signatures) != compiled.get(key, 0)})
"""


def test_load_kernels_leaves_nothing_to_compile_for_the_slam_mapper():
    """After the mapper node's load_kernels (the map's and the echo tests'), mapping with SLAM compiles nothing.

    The realistic room's first 70 pings: the map's first entries, SLAM's first keyframes and
    confirmations, and the echo tests against the first confirmed map, explained sightings included.  In
    an interpreter of its own, as a node starts: here, earlier tests have compiled kernels already.
    """
    done = subprocess.run([sys.executable, "-c", _SLAM_MAPPER_FIRST_PINGS], capture_output=True, text=True,
                          timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "{}", f"compiled while mapping: {done.stdout.strip()}"
