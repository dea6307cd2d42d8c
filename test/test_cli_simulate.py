"""``sonar-ring simulate``: run in-process, outputs checked against the simulator itself."""

import json
import math

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from sonar_ring.cli import OUTPUT_FORMAT, build_parser, main
from sonar_ring.geometry import load_layout
from sonar_ring.simulate import CLASS_NAMES, PING_ROW_FIELDS, Noise, Simulator, load_scene


def test_npz_output_holds_the_simulators_ping_with_its_header(tmp_path, capsys):
    out = tmp_path / "wall.npz"
    assert main(["simulate", "single_wall", "--out", str(out), "--sigma-a", "0"]) == 0
    expected = Simulator(load_scene("single_wall"), load_layout("browne_ring")).ping([0, 0, 0])
    with np.load(out) as data:
        assert str(data["format"]) == OUTPUT_FORMAT
        assert str(data["scene"]) == "single_wall" and str(data["layout"]) == "browne_ring"
        assert int(data["receivers_per_group"]) == 2
        assert data["class_names"].tolist() == list(CLASS_NAMES)
        for name in PING_ROW_FIELDS:
            assert_allclose(data[name], getattr(expected, name), rtol=0, atol=0, equal_nan=True)
        assert_array_equal(data["ping"], np.zeros(expected.n_echoes, dtype=int))
        assert_allclose(data["pose"], [[0.0, 0.0, 0.0]])
        assert_allclose(data["speed_of_sound"], [expected.speed_of_sound])
    printed = capsys.readouterr().out
    assert "single_wall / browne_ring (ideal world): 1 ping(s), 3 echoes (plane 3)" in printed
    assert printed.count(" wall ") == 3  # one table line per echo


def test_the_realistic_world_and_single_effects(tmp_path, capsys):
    out = tmp_path / "room.npz"
    assert main(["simulate", "room", "--trajectory", "--world", "realistic", "--realism", "multipath_gain=0",
                 "--out", str(out)]) == 0
    with np.load(out) as data:
        assert str(data["world"]) == "realistic"
        origins = set(data["truth_origin"].tolist())
        assert 1 not in origins and 2 in origins  # no multipath, clutter
        drift = np.hypot(*(data["odometry"][-1, :2] - data["pose"][-1, :2]))
        assert drift > 0.01  # the wheel odometry drifted
    assert "of no reflector: spurious" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        build_parser().parse_args(["simulate", "room", "--realism", "fading_db"])
    assert main(["simulate", "room", "--realism", "fading=1"]) == 1
    assert "--realism: unknown field 'fading'" in capsys.readouterr().err


def test_json_output_and_pose_in_degrees(tmp_path):
    out = tmp_path / "triad.json"
    assert main(["simulate", "room", "--layout", "kreczmer_triad", "--pose", "2.0", "1.0", "30",
                 "--out", str(out), "--sigma-a", "0"]) == 0
    data = json.loads(out.read_text())
    assert data["format"] == OUTPUT_FORMAT and data["receivers_per_group"] == 3
    (record,) = data["pings"]
    assert_allclose(record["pose"], [2.0, 1.0, math.radians(30)], rtol=1e-15)
    expected = Simulator(load_scene("room"), load_layout("kreczmer_triad")).ping([2.0, 1.0, math.radians(30)])
    assert expected.n_echoes > 0
    for name in PING_ROW_FIELDS:
        decoded = np.array(record[name], dtype=float).reshape(getattr(expected, name).shape)
        assert_allclose(decoded, getattr(expected, name), rtol=1e-15, equal_nan=True)  # null <-> NaN


def test_trajectory_with_noise_is_reproducible_by_seed(tmp_path):
    runs = []
    for name, seed in (("a", 4), ("b", 4), ("c", 5)):
        out = tmp_path / f"{name}.npz"
        assert main(["simulate", "barshan_kuc_bench", "--layout", "barshan_kuc_pair", "--trajectory",
                     "--sigma-t", "1e-6", "--timer", "0.33e-6", "--seed", str(seed), "--out", str(out)]) == 0
        with np.load(out) as data:
            runs.append({key: data[key] for key in ("tof", "amplitude", "pose", "ping")})
    scene, layout = load_scene("barshan_kuc_bench"), load_layout("barshan_kuc_pair")
    times, poses = scene.trajectory.poses(layout.ping_rate)
    assert_allclose(runs[0]["pose"], poses)
    assert_array_equal(runs[0]["tof"], runs[1]["tof"])
    assert not np.array_equal(runs[0]["amplitude"], runs[2]["amplitude"])
    expected = Simulator(scene, layout).run(poses, times, noise=Noise(tof=1e-6, amplitude=0.02, timer=0.33e-6),
                                            rng=np.random.default_rng(4))
    assert_allclose(runs[0]["tof"], np.concatenate([p.tof for p in expected]), rtol=0, equal_nan=True)
    ticks = runs[0]["tof"][np.isfinite(runs[0]["tof"])] / 0.33e-6
    assert_allclose(ticks, np.round(ticks), atol=1e-6)


def test_png_picture_is_written(tmp_path, capsys):
    out = tmp_path / "room.png"
    assert main(["simulate", "room", "--png", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert out.stat().st_size > 20_000
    assert f"wrote {out}" in capsys.readouterr().out


def test_subcommands_are_registered_for_extension():
    parser = build_parser()
    args = parser.parse_args(["simulate", "room"])
    assert args.command == "simulate" and callable(args.handler)
    assert args.layout == "browne_ring" and args.seed == 0 and args.sigma_a == 0.02


def test_error_handling(tmp_path, capsys):
    assert main(["simulate", "no_such_scene"]) == 1
    assert "sonar-ring simulate: error:" in capsys.readouterr().err
    assert main(["simulate", "single_wall", "--layout", "no_such_layout"]) == 1
    assert "no_such_layout" in capsys.readouterr().err
    assert main(["simulate", "single_wall", "--trajectory"]) == 1
    assert "no 'trajectory'" in capsys.readouterr().err
    assert main(["simulate", "single_wall", "--out", str(tmp_path / "x.txt")]) == 1
    assert ".npz or .json" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("reflectors: [{type: wall, from: [0, 0]}]\n")
    assert main(["simulate", str(bad)]) == 1
    assert f"{bad}: reflectors[0]: field 'to'" in capsys.readouterr().err
    for argv in (["simulate"], ["simulate", "room", "--sigma-t", "-1"], ["simulate", "room", "--pose", "1", "2"],
                 ["simulate", "room", "--pose", "1", "2", "3", "--trajectory"], []):
        with pytest.raises(SystemExit) as info:
            main(argv)
        assert info.value.code == 2
    capsys.readouterr()
