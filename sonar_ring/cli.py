"""The ``sonar-ring`` command line.

Each subcommand is a pair of functions: ``_add_<name>(subparsers)`` declares
its arguments and sets ``handler`` to ``_run_<name>(args) -> int``.  Add a
subcommand by writing such a pair and listing the ``_add_`` function in
:data:`SUBCOMMANDS`.

``sonar-ring simulate SCENE`` runs the scene simulator (:mod:`sonar_ring.simulate`)
and writes the pings as ``.npz`` or ``.json`` (format in :func:`write_pings`)
and, on request, a PNG picture.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from sonar_ring.geometry import LayoutError, load_layout
from sonar_ring.simulate import (
    CLASS_NAMES,
    DEFAULT_THRESHOLD,
    PING_ROW_FIELDS,
    Noise,
    SceneError,
    Simulator,
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
                   help="write the pings to FILE.npz or FILE.json (format: see README)")
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
    p.set_defaults(handler=_run_simulate)


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
    simulator = Simulator(scene, layout, threshold=args.threshold)
    pings = simulator.run(poses, times, noise=noise, rng=np.random.default_rng(args.seed))

    _print_summary(scene, layout, pings)
    if args.out is not None:
        write_pings(args.out, pings, scene=scene.name, layout=layout.name)
        print(f"wrote {args.out}")
    if args.png is not None:
        from sonar_ring import plot  # matplotlib only when a picture is asked for

        plot.save_png(args.png, scene, layout, pings)
        print(f"wrote {args.png}")
    return 0


def _print_summary(scene, layout, pings) -> None:
    classes = np.concatenate([p.truth_class for p in pings])
    counts = ", ".join(f"{CLASS_NAMES[c]} {np.count_nonzero(classes == c)}" for c in np.unique(classes))
    print(f"{scene.name} / {layout.name}: {len(pings)} ping(s), {classes.size} echoes ({counts or 'none'}), "
          f"c = {pings[0].speed_of_sound:.2f} m/s")
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
        print(f"{ping.group[n]:5d} {ping.transmitter[n]:3d} {scene.reflector_names[ping.truth_reflector[n]]:<14} "
              f"{CLASS_NAMES[ping.truth_class[n]]:<7} {tofs} {amplitudes}")


def write_pings(path, pings, *, scene: str, layout: str) -> Path:
    """Write simulated pings as ``.npz`` or ``.json``.

    Both hold ``format`` (:data:`OUTPUT_FORMAT`), ``scene``, ``layout``,
    ``receivers_per_group`` (K) and ``class_names`` (index = class code).

    * ``.npz``: the rows of all pings stacked (:func:`sonar_ring.simulate.stack_pings`):
      ``ping`` (N,), ``group`` (N,), ``transmitter`` (N,), ``tof`` (N, K) s,
      ``amplitude`` (N, K), ``phase_delay`` (N, K-1 or 0) s, ``truth_reflector``
      (N,), ``truth_class`` (N,), ``truth_position`` (N, 2) m, ``truth_normal``
      (N, 2), ``truth_reflection_point`` (N, K, 2) m, and per ping ``time`` (P,) s,
      ``pose`` (P, 3) world x, y (m), yaw (rad), ``speed_of_sound`` (P,) m/s.
      NaN marks a receiver that did not hear an echo.
    * ``.json``: ``pings``, a list with, per ping, ``time``, ``pose``,
      ``speed_of_sound`` and the same row fields as nested lists; NaN is ``null``.

    Returns
    -------
    Path
        The file written.
    """
    path = Path(path)
    header = dict(format=OUTPUT_FORMAT, scene=scene, layout=layout,
                  receivers_per_group=int(pings[0].tof.shape[1]), class_names=list(CLASS_NAMES))
    if path.suffix == ".npz":
        np.savez_compressed(path, **header, **stack_pings(pings))
    elif path.suffix == ".json":
        def plain(array):
            array = np.asarray(array)
            return np.where(np.isnan(array), None, array).tolist() if array.dtype.kind == "f" else array.tolist()

        records = [dict(time=p.time, pose=plain(p.pose), speed_of_sound=p.speed_of_sound,
                        **{name: plain(getattr(p, name)) for name in PING_ROW_FIELDS}) for p in pings]
        path.write_text(json.dumps(dict(header, pings=records)))
    else:
        raise ValueError(f"write_pings: {str(path)!r} must end in .npz or .json")
    return path


SUBCOMMANDS = (_add_simulate,)
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


if __name__ == "__main__":
    sys.exit(main())
