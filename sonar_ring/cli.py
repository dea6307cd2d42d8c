"""The ``sonar-ring`` command line.

Each subcommand is a pair of functions: ``_add_<name>(subparsers)`` declares
its arguments and sets ``handler`` to ``_run_<name>(args) -> int``.  Add a
subcommand by writing such a pair and listing the ``_add_`` function in
:data:`SUBCOMMANDS`.

``sonar-ring simulate SCENE`` runs the scene simulator (:mod:`sonar_ring.simulate`,
with the realistic world's effects of :mod:`sonar_ring.realism` on request)
and writes the pings as ``.npz`` or ``.json`` (format in :func:`write_pings`)
and, on request, a PNG picture.  ``sonar-ring process IN_BAG OUT_BAG`` and
``sonar-ring record-sim SCENE OUT_BAG`` work on rosbag2 files
(:mod:`sonar_ring.ros.offline`); they need ROS 2 and import it only when run.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

import numpy as np

from sonar_ring.geometry import LayoutError, load_layout
from sonar_ring.realism import PROFILES, RANGES, World, scene_realism
from sonar_ring.score import score_map
from sonar_ring.simulate import (
    CLASS_NAMES,
    DEFAULT_THRESHOLD,
    DIRECT,
    ORIGIN_NAMES,
    PING_ROW_FIELDS,
    Noise,
    SceneError,
    load_scene,
    stack_pings,
)

OUTPUT_FORMAT = "sonar_ring.simulate/1"
"""Value of the ``format`` entry of every file ``simulate`` writes."""


def _non_negative(text: str) -> float:
    value = float(text)
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text!r}")
    return value


def _add_simulate(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="simulate the echoes a sensor would report in a scene",
        description="Simulate pings of a sensor layout in a scene (config/scenes/*.yaml) and write "
                    "the echoes with their ground truth.",
    )
    p.add_argument("scene", help="scene name (config/scenes/NAME.yaml) or path to a scene YAML file")
    p.add_argument("--layout", default="browne_ring",
                   help="layout name (config/layouts/NAME.yaml) or path (default: browne_ring)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--pose", nargs=3, type=float, metavar=("X", "Y", "YAW_DEG"),
                       help="one ping at this world pose: x, y in m, yaw in deg (default: the scene's sensor_pose)")
    where.add_argument("--trajectory", action="store_true",
                       help="one ping per pose of the scene's trajectory, at the layout's ping rate")
    p.add_argument("--out", type=Path, metavar="FILE",
                   help="write the pings to FILE.npz or FILE.json (format: see doc/CORE_API.md)")
    p.add_argument("--png", type=Path, metavar="FILE", help="draw the scene, sensor and echoes into FILE.png")
    p.add_argument("--seed", type=int, default=0, help="seed of the noise generator (default: 0)")
    p.add_argument("--sigma-t", type=_non_negative, default=0.0, metavar="S",
                   help="time-of-flight noise standard deviation, s (default: 0)")
    p.add_argument("--sigma-a", type=_non_negative, default=0.02, metavar="A",
                   help="amplitude noise standard deviation relative to A_max (default: 0.02, Barshan & Kuc)")
    p.add_argument("--sigma-phase", type=_non_negative, default=0.0, metavar="S",
                   help="zero-crossing jitter of the phase delays, s (default: 0)")
    p.add_argument("--timer", type=_non_negative, default=0.0, metavar="S",
                   help="timer tick that times are truncated to, s (e.g. 0.33e-6; default: 0, off)")
    p.add_argument("--threshold", type=float, default=DEFAULT_THRESHOLD, metavar="A",
                   help=f"detection threshold relative to A_max (default: {DEFAULT_THRESHOLD:.4f}, -30 dB)")
    _add_world_options(p, default="ideal")
    p.set_defaults(handler=_run_simulate)


def _add_world_options(p, default: str) -> None:
    """``--world`` and ``--realism``: the realistic world's effects (:mod:`sonar_ring.realism`)."""
    p.add_argument("--world", choices=tuple(PROFILES), default=default,
                   help=f"the world's effects: ideal (the forward model) or realistic (drifting odometry, "
                        f"missed, spurious, multipath and late echoes, the air's speed of sound) (default: {default})")
    p.add_argument("--realism", action="append", type=realism_field, default=[], metavar="FIELD=VALUE",
                   help="replace one field of the world's profile, e.g. multipath_gain=0 to switch multipath off; "
                        "repeat for several (fields: " + ", ".join(RANGES) + ")")


def realism_field(text: str) -> tuple[str, float]:
    """``FIELD=NUMBER`` of ``--realism`` as ``(field, number)`` (the field is checked by :mod:`sonar_ring.realism`)."""
    name, equals, value = text.partition("=")
    try:
        number = float(value)
    except ValueError:
        number = None
    if not equals or number is None:
        raise argparse.ArgumentTypeError(f"must be FIELD=NUMBER, got {text!r}")
    return name.strip(), number


def _run_simulate(args) -> int:
    scene = load_scene(args.scene)
    layout = load_layout(args.layout)
    if args.out is not None and args.out.suffix not in (".npz", ".json"):
        raise ValueError(f"--out must end in .npz or .json, got {str(args.out)!r}")
    if args.trajectory:
        if scene.trajectory is None:
            raise SceneError(f"scene {scene.name!r} has no 'trajectory' for --trajectory")
        times, poses = scene.trajectory.poses(layout.ping_rate)
    else:
        pose = scene.sensor_pose if args.pose is None else np.array([*args.pose[:2], math.radians(args.pose[2])])
        times, poses = np.zeros(1), pose[None, :]
    noise = Noise(tof=args.sigma_t, amplitude=args.sigma_a, phase=args.sigma_phase, timer=args.timer)
    world = World(scene, layout, scene_realism(scene, args.world, dict(args.realism), where="--realism"),
                  noise=noise, seed=args.seed, threshold=args.threshold)
    pings = [world.ping(pose, time) for pose, time in zip(poses, times, strict=True)]
    odometry = np.array([world.odometry_pose(pose) for pose in poses])

    _print_summary(scene, layout, pings, args.world)
    if args.out is not None:
        write_pings(args.out, pings, scene=scene.name, layout=layout.name, world=args.world, odometry=odometry)
        print(f"wrote {args.out}")
    if args.png is not None:
        from sonar_ring import plot  # matplotlib only when a picture is asked for

        plot.save_png(args.png, scene, layout, pings)
        print(f"wrote {args.png}")
    return 0


def _print_summary(scene, layout, pings, world: str) -> None:
    classes = np.concatenate([p.truth_class[p.truth_origin == DIRECT] for p in pings])
    origins = np.concatenate([p.truth_origin for p in pings])
    counts = ", ".join(f"{CLASS_NAMES[c]} {np.count_nonzero(classes == c)}" for c in np.unique(classes))
    others = ", ".join(f"{ORIGIN_NAMES[o]} {np.count_nonzero(origins == o)}" for o in np.unique(origins) if o != DIRECT)
    others = f", of no reflector: {others}" if others else ""
    print(f"{scene.name} / {layout.name} ({world} world): {len(pings)} ping(s), {origins.size} echoes "
          f"({counts or 'none'}{others}), c = {pings[0].speed_of_sound:.2f} m/s")
    if len(pings) != 1:
        return
    ping = pings[0]
    K = layout.receivers_per_group
    print(f"{'group':>5} {'tx':>3} {'reflector':<14} {'class':<7} "
          + " ".join(f"{f'tof{k} [ms]':>10}" for k in range(K)) + " "
          + " ".join(f"{f'amp{k}':>6}" for k in range(K)))
    for n in range(ping.n_echoes):
        tofs = " ".join(f"{t * 1e3:10.5f}" for t in ping.tof[n])
        amplitudes = " ".join(f"{a:6.3f}" for a in ping.amplitude[n])
        source = scene.reflector_names[ping.truth_reflector[n]] if ping.truth_origin[n] == DIRECT else \
            f"({ORIGIN_NAMES[ping.truth_origin[n]]})"
        print(f"{ping.group[n]:5d} {ping.transmitter[n]:3d} {source:<14} "
              f"{CLASS_NAMES[ping.truth_class[n]]:<7} {tofs} {amplitudes}")


def write_pings(path, pings, *, scene: str, layout: str, world: str, odometry) -> Path:
    """Write simulated pings as ``.npz`` or ``.json``.

    Both hold ``format`` (:data:`OUTPUT_FORMAT`), ``scene``, ``layout``,
    ``world`` (the profile), ``receivers_per_group`` (K), ``class_names``
    (index = class code) and ``origin_names`` (index = ``truth_origin`` code).

    * ``.npz``: the rows of all pings stacked (:func:`sonar_ring.simulate.stack_pings`):
      ``ping`` (N,), ``group`` (N,), ``transmitter`` (N,), ``tof`` (N, K) s,
      ``amplitude`` (N, K), ``phase_delay`` (N, K-1 or 0) s, ``truth_reflector``
      (N,; -1 for no reflector), ``truth_class`` (N,), ``truth_origin`` (N,),
      ``truth_position`` (N, 2) m, ``truth_normal`` (N, 2),
      ``truth_reflection_point`` (N, K, 2) m, and per ping ``time`` (P,) s,
      ``pose`` (P, 3) world x, y (m), yaw (rad), ``odometry`` (P, 3) what the
      wheel odometry reported (``odom``), ``speed_of_sound`` (P,) m/s.  NaN
      marks a receiver that did not hear an echo.
    * ``.json``: ``pings``, a list with, per ping, ``time``, ``pose``,
      ``odometry``, ``speed_of_sound`` and the same row fields as nested lists;
      NaN is ``null``.

    Returns
    -------
    Path
        The file written.
    """
    path = Path(path)
    header = dict(format=OUTPUT_FORMAT, scene=scene, layout=layout, world=world,
                  receivers_per_group=int(pings[0].tof.shape[1]), class_names=list(CLASS_NAMES),
                  origin_names=list(ORIGIN_NAMES))
    odometry = np.asarray(odometry, dtype=float).reshape(-1, 3)
    if path.suffix == ".npz":
        np.savez_compressed(path, **header, **stack_pings(pings), odometry=odometry)
    elif path.suffix == ".json":
        def plain(array):
            array = np.asarray(array)
            return np.where(np.isnan(array), None, array).tolist() if array.dtype.kind == "f" else array.tolist()

        records = [dict(time=p.time, pose=plain(p.pose), odometry=plain(o), speed_of_sound=p.speed_of_sound,
                        **{name: plain(getattr(p, name)) for name in PING_ROW_FIELDS})
                   for p, o in zip(pings, odometry, strict=True)]
        path.write_text(json.dumps(dict(header, pings=records)))
    else:
        raise ValueError(f"write_pings: {str(path)!r} must end in .npz or .json")
    return path


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}")
    return value


def _offline():
    """:mod:`sonar_ring.ros.offline`, imported only now: it needs ROS 2 (rclpy, the built messages) and rosbags."""
    try:
        from sonar_ring.ros import offline
    except ImportError as error:
        if error.name == "rosbags":
            raise ValueError("needs the rosbags library: pip install rosbags") from None
        raise ValueError(f"needs ROS 2 ({error}): source tools/env.sh in the repository, or your ROS 2 "
                         "workspace's install/setup.bash") from None
    return offline


def _add_output_options(p) -> None:
    """``--storage`` and ``--quiet``, for the commands that write a bag."""
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="output storage (default: mcap)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_process(subparsers) -> None:
    p = subparsers.add_parser(
        "process",
        help="run the localiser and mapper over the echoes of a rosbag2, faster than real time",
        description="Read the echoes (sonar_ring/msg/Echoes) of a rosbag2 (sqlite3 or MCAP), run them through the "
                    "localiser and mapper in bag time, and write landmarks/raw, landmarks, landmarks/pairs, markers, "
                    "map/landmarks, map/markers and map/points to a new bag: the messages the live graph publishes.",
    )
    p.add_argument("in_bag", metavar="IN_BAG", help="input rosbag2: a directory, .mcap or .db3 file")
    p.add_argument("out_bag", metavar="OUT_BAG", help="output rosbag2 directory (must not exist)")
    p.add_argument("--layout", help="layout name or YAML path (default: the layout the echoes name)")
    p.add_argument("--params", metavar="FILE", help="node parameters YAML, the format of config/params/<layout>.yaml "
                   "(default: that file for the layout)")
    p.add_argument("--echoes-topic", action="append", metavar="TOPIC",
                   help="echoes topic to process; repeat for several (default: every sonar_ring/msg/Echoes topic)")
    p.add_argument("--odom-topic", metavar="TOPIC", help="nav_msgs/Odometry for the mapper, relative to the echoes' "
                   "namespace (default: odom if the bag has it, else the mapper's fixed_pose)")
    p.add_argument("--jobs", type=_positive_int, metavar="N", help="processes in all: this one (reading, writing), "
                   "one mapping, and N - 2 workers localising and classifying batches of pings (with 2, this one "
                   "localises); 1: all in this one (default: one per CPU)")
    p.add_argument("--scene", metavar="SCENE", help="score each final map against this scene (name or YAML path) "
                   "with sonar_ring.score, the map's frame taken as the scene's world frame (as in a bag from "
                   "sonar-ring record-sim, whose odometry starts at the true pose); every reflector of the scene "
                   "counts as heard")
    _add_output_options(p)
    p.set_defaults(handler=_run_process)


def _run_process(args) -> int:
    offline = _offline()
    report = offline.process_bag(args.in_bag, args.out_bag, layout=args.layout, params_file=args.params,
                                 echoes_topics=args.echoes_topic, odom_topic=args.odom_topic, storage=args.storage,
                                 jobs=args.jobs, progress=not args.quiet)
    for skipped in report.skipped:
        print(f"sonar-ring process: warning: {skipped}", file=sys.stderr)
    speed = report.data_seconds / report.seconds if report.seconds else 0.0
    print(f"processed {report.pings} pings ({report.data_seconds:.1f} s of data, layout {report.layout}, "
          f"parameters {report.params_file}) in {report.seconds:.2f} s: {speed:.1f}x real time")
    print("  landmarks per class: " + _counts(report.per_class, CLASS_NAMES))
    print("  map: " + _counts(report.map_per_class, CLASS_NAMES))
    print("  refused: " + (", ".join(f"{n} {reason}" for reason, n in sorted(report.problems.items())) or "nothing"))
    if report.notes:
        print("  expected losses: " + ", ".join(f"{n} {reason}" for reason, n in sorted(report.notes.items())))
    if args.scene is not None:
        scene = load_scene(args.scene)
        for topic, final_map in report.maps.items():
            lines = score_map(final_map, scene).summary().splitlines()
            print(f"  map score against {scene.name} ({topic}): " + "; ".join(lines))
    print(f"wrote {offline.describe(args.out_bag)}")
    return 0


def _counts(counter, names) -> str:
    return ", ".join(f"{counter.get(name, 0)} {name}" for name in names)


def _add_record_sim(subparsers) -> None:
    p = subparsers.add_parser(
        "record-sim",
        help="write a rosbag2 of simulated echoes, as the driver's simulator source publishes them",
        description="Simulate the scene's trajectory and write /echoes, /odom, /truth and /range/group_NN to a new "
                    "rosbag2, stamped with trajectory time from 1 s: data in the hardware's format for ros2 bag play "
                    "and sonar-ring process.",
    )
    p.add_argument("scene", metavar="SCENE", help="scene name (config/scenes/NAME.yaml) or path to a scene YAML file")
    p.add_argument("out_bag", metavar="OUT_BAG", help="output rosbag2 directory (must not exist)")
    p.add_argument("--layout", default="browne_ring",
                   help="layout name (config/layouts/NAME.yaml) or path (default: browne_ring)")
    p.add_argument("--laps", type=_positive_int, default=1,
                   help="passes over the scene's trajectory; one ping each without a trajectory (default: 1)")
    p.add_argument("--pings", type=_positive_int, help="stop after this many pings (default: all of the laps)")
    p.add_argument("--seed", type=int, default=0, help="seed of the noise generator (default: 0)")
    p.add_argument("--sigma-t", type=_non_negative, metavar="S",
                   help="time-of-flight noise standard deviation, s (default: the driver's sigma_tof in the "
                        "layout's config/params file: 1e-6 for browne_ring, 0.33e-6 for a triad)")
    p.add_argument("--sigma-a", type=_non_negative, metavar="A",
                   help="amplitude noise standard deviation relative to A_max (default: the driver's "
                        "sigma_amplitude there, 0.02)")
    p.add_argument("--no-range", action="store_true",
                   help="leave out /range/group_NN (a sensor_msgs/Range topic per group)")
    _add_world_options(p, default="realistic")
    _add_output_options(p)
    p.set_defaults(handler=_run_record_sim)


def _run_record_sim(args) -> int:
    offline = _offline()
    report = offline.record_sim(args.scene, args.out_bag, layout=args.layout, laps=args.laps, pings=args.pings,
                                seed=args.seed, sigma_t=args.sigma_t, sigma_a=args.sigma_a, world=args.world,
                                realism=dict(args.realism), with_range=not args.no_range, storage=args.storage,
                                progress=not args.quiet)
    print(f"recorded {report.pings} pings ({report.data_seconds:.1f} s of data, {args.world} world) in "
          f"{report.seconds:.2f} s")
    if report.problems:
        print("  refused: " + ", ".join(f"{n} {reason}" for reason, n in sorted(report.problems.items())))
    print(f"wrote {offline.describe(args.out_bag)}")
    return 0


def _add_bench(subparsers) -> None:
    p = subparsers.add_parser(
        "bench",
        help="measure speed against error of every method and write BENCHMARKS.md with plots",
        description="Simulate the standard scenes, run every localisation, classification and azimuth method of "
                    "the package and the baselines on the same echoes at sigma_t = 0, 0.3, 1, 2 us, time them, and "
                    "write DIR/BENCHMARKS.md and DIR/bench/plots/*.png (2-3 minutes on 2 cores). Where "
                    "DIR/README.md has the report's markers, its main tables are replaced too. The least-squares "
                    "baseline needs scipy, the plots matplotlib, the graph row ROS 2.",
    )
    p.add_argument("--out", type=Path, default=Path("."), metavar="DIR",
                   help="directory of BENCHMARKS.md and bench/plots/ (default: the current directory)")
    p.add_argument("--quick", action="store_true",
                   help="small sizes: checks that the report is produced, in seconds; figures not for reading")
    p.add_argument("--seed", type=int, default=None, metavar="N", help="seed of every random stream (default: 0)")
    study = p.add_mutually_exclusive_group()
    study.add_argument("--map", action="store_true",
                       help="instead: the maps of the room in the ideal world, with each realistic effect alone and "
                            "in the realistic world, scored over 3 laps, 20 seeds in the realistic world and 3 in "
                            "each other (about an hour on 2 cores); "
                            "writes its section of DIR/BENCHMARKS.md and its table in DIR/README.md. With --quick: 2 "
                            "seeds of 200 pings in two worlds")
    study.add_argument("--slam-cost", action="store_true",
                       help="instead: what the mapper with SLAM costs, against its targets, on the room in the "
                            "realistic world: its update per ping over 3 laps (median, p99, the echo tests' and the "
                            "SLAM's shares), the resident memory of a 30-minute simulated run (growth after 5 minutes "
                            "of warm-up; stopped after 60 min of wall time), and the speed of the whole `sonar-ring "
                            "process` command on a recorded lap and on three (median of 5 runs each); writes its "
                            "section of DIR/BENCHMARKS.md. Needs ROS 2 for the process part. With --quick: 150 "
                            "pings, a 6-second run, one process run each of 60 and 120 pings")
    p.set_defaults(handler=_run_bench)


def _run_bench(args) -> int:
    if args.slam_cost:
        from sonar_ring.benchmark import slam_cost

        if args.seed is not None:
            raise ValueError("--slam-cost simulates seed 0; --seed is for the other tables")
        if args.quick:
            slam_cost.run(args.out, pings=150, minutes=0.1, warmup=0.05, sample_every=30, bag_pings=(60, 120), runs=1,
                          quick=True)
        else:
            slam_cost.run(args.out)
        return 0
    if args.map:
        from sonar_ring.benchmark import worlds

        if args.seed is not None:
            raise ValueError("--map runs seeds 0 to 19; --seed is for the other tables")
        if args.quick:
            worlds.run(args.out, seeds=2, laps=1, pings=200, worlds=("ideal", "realistic"), effect_seeds=2)
        else:
            worlds.run(args.out)
        return 0
    from sonar_ring.benchmark import report  # scipy and matplotlib only when benchmarking

    seed = report.DEFAULT_SEED if args.seed is None else args.seed
    report.run(args.out, quick=args.quick, seed=seed)
    return 0


SUBCOMMANDS = (_add_simulate, _add_process, _add_record_sim, _add_bench)
"""Functions that each add one subcommand to the parser."""


def build_parser() -> argparse.ArgumentParser:
    """The ``sonar-ring`` argument parser with every subcommand."""
    parser = argparse.ArgumentParser(prog="sonar-ring", description="Sonar ring perception tools.")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in SUBCOMMANDS:
        add(subparsers)
    return parser


def main(argv=None) -> int:
    """Run ``sonar-ring`` with ``argv`` (default: the process arguments); return the exit code.

    Bad input files and arguments print one line naming the problem to stderr
    and return 1; usage errors exit with status 2 (argparse).
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.handler(args)
    except (SceneError, LayoutError, ValueError, OSError) as exc:
        print(f"sonar-ring {args.command}: error: {exc}", file=sys.stderr)
        return 1


def run() -> None:
    """The ``sonar-ring`` command: :func:`main`, then exit without the interpreter's teardown.

    By then every output is written and closed; what the teardown would free is
    mostly numba's compiled code, whose freeing is a noticeable share of a short
    ``sonar-ring process`` run and buys nothing.
    """
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    run()
