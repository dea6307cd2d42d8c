"""A malformed layout or scene: one message naming the file, the field and the expected value; exit status 1."""

import re
import subprocess

import pytest
from ros_harness import executable

from sonar_ring.cli import main
from sonar_ring.geometry import LayoutError, config_path, load_layout
from sonar_ring.simulate import SceneError, load_scene

RING = config_path("layouts", "browne_ring").read_text()
ROOM = config_path("scenes", "room").read_text()

PAIRS = r"ring: field 'pairs' must be an integer in 1\.\.1024, got "
# (what is wrong, file text, the message after "<file>: ")
LAYOUT_CASES = [
    ("wrong type", RING.replace("frequency_hz: 50000.0", "frequency_hz: fifty kHz"),
     r"field 'frequency_hz' must be a finite number > 0, got 'fifty kHz'"),
    ("missing field", RING.replace("max_range:", "# max_range:"), r"missing field 'max_range' \(a finite number > 0\)"),
    ("out of range", RING.replace("pairs: 48", "pairs: 0"), PAIRS + "0"),
    ("too many", RING.replace("pairs: 48", "pairs: 1000000000"), PAIRS + "1000000000"),
    ("not a number", RING.replace("pairs: 48", "pairs: .nan"), PAIRS + "nan"),
    ("unknown field", RING.replace("max_range: 6.0", "max_range: 6.0\nmax_range_m: 8.0"),
     r"unknown field 'max_range_m' \(expected some of \['aperture_radius', "),
    ("unknown nested field", RING.replace("separation:", "spacing: 0.04\n  separation:", 1),
     r"ring: unknown field 'spacing' \(expected some of \['emitter_height', 'pairs', 'separation', 'tiers'\]\)"),
    ("unknown field with a line break", RING + '"odd\\nkey": 1\n', r"unknown field 'odd\\nkey' \(expected some of "),
    ("not YAML", "kind: ring\n  frequency_hz: [40000\n", r"not valid YAML \(.*line 2"),
    ("not a mapping", "- kind\n- ring\n", r"expected a mapping of fields at the top level, got list"),
]
SCENE_CASES = [
    ("wrong type", ROOM.replace("temperature_c: 22.0", "temperature_c: warm"),
     r"field 'temperature_c' must be a number, got 'warm'"),
    ("missing field", ROOM.replace("from: [0.0, 0.0], to: [6.0, 0.0]", "from: [0.0, 0.0]"),
     r"reflectors\[0\]: field 'to' must be \[x, y\] in m, got None"),
    ("out of range", ROOM.replace("relative_humidity: 45.0", "relative_humidity: 145.0"),
     r"field 'relative_humidity' must be a number >= 0.0 and <= 100.0, got 145.0"),
    ("corner of a wall too short for a float", ROOM.replace("from: [0.0, 4.5], to: [0.0, 0.0]",
                                                           "from: [1.0e-200, 0.0], to: [0.0, 0.0]"),
     r"reflectors\[\d+\]: field 'walls': 'south' and 'west' must have lengths a float can hold, got 6.0 and 0.0 m"),
    ("endless lap", ROOM.replace("speed: 0.3", "speed: 1.0e-9"),
     r"trajectory: field 'speed' must make one lap last at most 3600 s \(the path is 12.4 m long\), got 1e-09"),
    ("unknown fields of two types", ROOM + "5: five\nzz: z\n", r"unknown field 5 \(expected some of "),
    ("not YAML", "reflectors: [{type: wall\n", r"not valid YAML"),
    ("not a mapping", "just a sentence\n", r"expected a mapping of fields at the top level, got str"),
]


def test_the_cases_damage_the_shipped_files():
    assert all(text not in (RING, ROOM) for _, text, _ in LAYOUT_CASES + SCENE_CASES)


@pytest.mark.parametrize(("load", "error", "text", "message"),
                         [(load_layout, LayoutError, text, message) for _, text, message in LAYOUT_CASES]
                         + [(load_scene, SceneError, text, message) for _, text, message in SCENE_CASES],
                         ids=[f"layout {c[0]}" for c in LAYOUT_CASES] + [f"scene {c[0]}" for c in SCENE_CASES])
def test_errors_name_file_field_and_expected_value(tmp_path, load, error, text, message):
    path = tmp_path / "damaged.yaml"
    path.write_text(text)
    with pytest.raises(error, match=f"^{path}: {message}") as raised:
        load(path)
    assert "\n" not in str(raised.value)


@pytest.mark.parametrize(("argument", "cases"), [("--layout", LAYOUT_CASES[:1]), ("scene", SCENE_CASES[:1])])
def test_the_command_line_prints_one_line_and_exits_1(tmp_path, capsys, argument, cases):
    (_, text, message), = cases
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    argv = ["simulate", "room", "--layout", str(path)] if argument == "--layout" else ["simulate", str(path)]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"sonar-ring simulate: error: {path}: ")


@pytest.mark.ros
@pytest.mark.parametrize(("node", "setting", "expected"), [
    ("localiser", "layout:={bad}", r"{bad}: field 'frequency_hz' must be a finite number > 0"),
    ("driver", "scene:={bad_scene}", r"{bad_scene}: field 'temperature_c' must be a number"),
    ("driver", "device:=usb://ring", r"device 'usb://ring': scheme must be serial://, udp:// or tcp://"),
    ("mapper", "gate_chi2:=1000.0", r"parameter gate_chi2: .*out of range"),
    ("localiser", "models:=[plane,wall]", r"parameter models must be a non-empty subset of .*got \['plane', 'wall'\]"),
], ids=["layout", "scene", "device", "range", "choice"])
def test_a_node_refuses_to_start_with_one_log_line_and_status_1(tmp_path, node, setting, expected):
    bad, bad_scene = tmp_path / "bad.yaml", tmp_path / "bad_scene.yaml"
    bad.write_text(LAYOUT_CASES[0][1])
    bad_scene.write_text(SCENE_CASES[0][1])
    argv = [executable(node), "--ros-args", "-p", setting.format(bad=bad, bad_scene=bad_scene)]
    if node == "driver" and "device" in setting:
        argv += ["-p", "source:=hardware"]
    result = subprocess.run(argv, capture_output=True, text=True, timeout=60)
    assert result.returncode == 1
    lines = [line for line in result.stderr.splitlines() if "cannot start" in line]
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    assert lines[0].startswith("[FATAL]") and f"[{node}]: cannot start: " in lines[0]
    assert re.search(expected.format(bad=bad, bad_scene=bad_scene), lines[0]), lines[0]
