"""An echo heard by several pairs, fitted over all their receivers: error against the joint Cramer-Rao bound.

Regenerate ``bench/results/joint.md`` (a few seconds):

    source tools/env.sh && python bench/bench_joint.py   # from the repository root

Browne's ring in the benchmark's standard scenes (:mod:`sonar_ring.benchmark.scenes`: one wall, one corner, one
pole from random poses 0.5-5 m away, and a lap of the room), noise-free echoes with Gaussian TOF noise added per
level.  :func:`sonar_ring.ring_consistency.ring_consistency` joins each echo row with the overlapping groups' rows
of the same echo and fits both models over every receiver that heard it.  For the echoes heard by two or more
pairs (three or more receivers), with the fit of the true model usable (it fits: chi-square within the test's
limit): the error of the fitted point -- a plane's foot point and a corner's vertex ``(T + T') / 2``, an edge's
point -- against the joint CRLB, the same receivers' ``(J^T W J)^-1`` at the true point (computed here in numpy,
apart from the kernel), the share of normalised errors within the 3-sigma ellipse of the fit's own covariance
(the 2-D chi-square's 99.73 % point), and the pair's closed form of the same model
(:func:`sonar_ring.pipeline.localise_ping`) on the same echoes.  Then what a ping's landmarks are: the pairs'
labelled ones against those :func:`sonar_ring.pipeline.joint_landmarks` publishes, one per echo.  Seeded: a rerun
on the same versions gives the same file but for the date and the revision.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from sonar_ring import pipeline, ring_consistency
from sonar_ring.benchmark.environment import machine, revision, today
from sonar_ring.benchmark.scenes import standard_scenes
from sonar_ring.echoes import EchoArrays
from sonar_ring.landmarks import CORNER, EDGE, PLANE

ROOT = Path(__file__).resolve().parents[1]
RESULT = ROOT / "bench" / "results" / "joint.md"
SEED = 23
SIGMAS_US = (0.3, 1.0, 2.0)
CLASSES = {"plane": PLANE, "corner": CORNER, "edge": EDGE}


def joint_crlb(layout, table, result, horizontal, sigma, truth, edge):
    """Each row's joint CRLB (N, 2, 2) of its fitted point at the true one, over the receivers its fit used, m^2.

    ``horizontal`` and ``sigma`` (N, K): every row's horizontal paths (NaN: not heard) and their standard
    deviations; ``truth`` (N, 2) the true point (a plane's foot point, a corner's or an edge's vertex);
    ``edge`` (N,) which rows take the edge model.  NaN where the row's fit joined nothing.
    """
    plan = layout.plan
    bound = np.full((len(truth), 2, 2), np.nan)
    transmitter = plan.transmitters[table["group"], 0]
    for n in np.flatnonzero(result.dof >= 1):
        rows = result.joined[n][result.joined[n] >= 0]
        receivers = plan.receivers[table["group"][rows]].reshape(-1, 2)
        heard = np.isfinite(horizontal[rows]).reshape(-1)
        receivers, weight = receivers[heard], 1.0 / sigma[rows].reshape(-1)[heard] ** 2
        if edge[n]:
            to = truth[n] - receivers
            jacobian = to / np.linalg.norm(to, axis=1)[:, None]
            away = truth[n] - transmitter[n]
            jacobian = jacobian + away / np.linalg.norm(away)
            scale = 1.0
        else:
            image = 2.0 * truth[n] - transmitter[n]  # T' = 2G - T
            to = image - receivers
            jacobian = to / np.linalg.norm(to, axis=1)[:, None]
            scale = 0.25  # G = (T + T') / 2
        bound[n] = scale * np.linalg.inv(jacobian.T @ (weight[:, None] * jacobian))
    return bound


def ping_echoes(layout, table, tof):
    """Each ping of the table as the localiser takes it: its rows (indices into the table) and its echoes."""
    for ping in np.unique(table["ping"]):
        rows = np.flatnonzero(table["ping"] == ping)
        yield rows, EchoArrays(layout, float(table["speed_of_sound"][ping]), table["group"][rows],
                               table["transmitter"][rows], tof[rows], np.zeros((rows.size, 1)),
                               np.zeros((rows.size, 0)))


def pair_errors(layout, table, tof, truth, edge):
    """Each row's error (N,) of its pair's closed form of the true model (corner for a plane too: the same G), m."""
    error = np.full(len(truth), np.nan)
    for rows, echoes in ping_echoes(layout, table, tof):
        hypotheses = pipeline.localise_ping(layout, echoes)
        hypotheses = hypotheses.select(hypotheses.valid)
        for wanted in (CORNER, EDGE):
            of_model = hypotheses.select(hypotheses.landmark_class == wanted)
            row = rows[of_model.echo]
            take = edge[row] == (wanted == EDGE)
            error[row[take]] = np.hypot(*(of_model.position[take] - truth[row[take]]).T)
    return error


def published(layout, table, tof, sigma_tof):
    """A ping's landmarks: the pairs' (labelled) and those :func:`~sonar_ring.pipeline.joint_landmarks` publishes.

    Per true class: the landmarks of each kind, how many of the published are joint fits, their median errors and
    the published ones' share within their own 3-sigma ellipse.
    """
    settings = pipeline.Settings(sigma_tof=sigma_tof)
    found = {name: dict(pairs=[], published=[], joint=0, within=0) for name in CLASSES}
    for rows, echoes in ping_echoes(layout, table, tof):
        labelled = pipeline.classify_ping(layout, echoes, pipeline.localise_ping(layout, echoes, settings), settings)
        joint = pipeline.joint_landmarks(layout, echoes, labelled, settings)
        moved = np.any(joint.position != labelled.position[np.searchsorted(labelled.echo, joint.echo)], axis=1)
        for name, code in CLASSES.items():
            for landmarks, key in ((labelled, "pairs"), (joint, "published")):
                of_class = table["truth_class"][rows[landmarks.echo]] == code
                error = landmarks.position[of_class] - table["truth_position"][rows[landmarks.echo[of_class]]]
                found[name][key].append(np.hypot(*error.T))
                if key == "published":
                    normalised = np.einsum("ni,nij,nj->n", error, np.linalg.inv(landmarks.covariance[of_class]), error)
                    found[name]["within"] += int(np.count_nonzero(normalised <= ring_consistency.CHI2_3_SIGMA))
                    found[name]["joint"] += int(np.count_nonzero(moved[of_class]))
    lines = []
    for name, f in found.items():
        pairs, joint = np.concatenate(f["pairs"]), np.concatenate(f["published"])
        lines.append(dict(sigma=sigma_tof, name=name, pairs=pairs.size, published=joint.size, joint=f["joint"],
                          pair_median=float(np.median(pairs)), median=float(np.median(joint)),
                          within=f["within"] / joint.size))
    return lines


def level(scenes, sigma_tof, rng):
    """One noise level's rows: per class, the table line's figures."""
    layout, table = scenes.layout, scenes.table
    tof = scenes.noisy_tof(sigma_tof, rng)
    speed = table["speed_of_sound"][table["ping"]][:, None]
    paths = speed * tof
    sigma_path = float(np.mean(table["speed_of_sound"])) * sigma_tof
    result = ring_consistency.ring_consistency(layout, table["group"], paths, sigma_path, ping=table["ping"],
                                               covariances=True)
    truth, truth_class = table["truth_position"], table["truth_class"]
    edge = truth_class == EDGE
    transmitter = layout.plan.transmitters[table["group"], 0]
    fitted = np.where(edge[:, None], result.edge_position, 0.5 * (transmitter + result.virtual_image))
    covariance = np.where(edge[:, None, None], result.edge_covariance, 0.25 * result.image_covariance)
    dz = layout.plan.height_offset[table["group"], 0]
    horizontal = np.sqrt(paths ** 2 - dz ** 2)
    sigma = sigma_path * paths / horizontal
    bound = joint_crlb(layout, table, result, horizontal, sigma, truth, edge)
    pair = pair_errors(layout, table, tof, truth, edge)
    pairs_joined = (result.joined >= 0).sum(axis=1)
    joint = (result.dof >= 1) & (pairs_joined >= 2) & np.isfinite(covariance[:, 0, 0]) & np.isfinite(pair)
    error = fitted - truth
    distance = np.hypot(*error.T)
    lines = []
    for name, code in CLASSES.items():
        of_class = (truth_class == code) & np.isfinite(pair)
        chosen = joint & of_class
        e, c = error[chosen], covariance[chosen]
        normalised = np.einsum("ni,nij,nj->n", e, np.linalg.inv(c), e)
        rms = np.sqrt(np.mean(distance[chosen] ** 2))
        crlb = np.sqrt(np.mean(np.trace(bound[chosen], axis1=1, axis2=2)))
        pair_rms = np.sqrt(np.mean(pair[chosen] ** 2))
        everything = np.where(chosen, distance, pair)[of_class]
        lines.append(dict(
            sigma=sigma_tof, name=name, echoes=int(of_class.sum()), joint=int(chosen.sum()), rms=rms, crlb=crlb,
            within=float(np.mean(normalised <= ring_consistency.CHI2_3_SIGMA)), nees=float(np.mean(normalised)),
            pair_rms=pair_rms, median=float(np.median(distance[chosen])), pair_median=float(np.median(pair[chosen])),
            all_median=float(np.median(everything)), all_pair_median=float(np.median(pair[of_class]))))
    return lines, published(layout, table, tof, sigma_tof)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--poses", type=int, default=400, help="poses per single-reflector scene (default 400)")
    parser.add_argument("--room-stride", type=int, default=4, help="every n-th pose of the room's lap (default 4)")
    parser.add_argument("--output", type=Path, default=RESULT, help="Markdown file to write")
    args = parser.parse_args()
    host = machine()
    rng = np.random.default_rng(SEED)
    scenes = standard_scenes(args.poses, args.room_stride, rng)
    rows, per_ping = [], []
    for sigma_us in SIGMAS_US:
        fits, landmarks = level(scenes, sigma_us * 1e-6, rng)
        rows += fits
        per_ping += landmarks
        print(f"sigma_t {sigma_us} us done", flush=True)
    lines = [
        "# An echo heard by several pairs: the joint fit against its Cramer-Rao bound",
        "",
        "Regenerate: `python bench/bench_joint.py` (from the repository root, after `source tools/env.sh`)",
        "",
        f"Machine: {host}.  Revision {revision(ROOT)}, {today()}.",
        "",
        f"Browne's ring in the standard scenes ({', '.join(scenes.names)}: {args.poses} random poses per "
        f"single-reflector scene, every {args.room_stride}th pose of the room's lap), "
        f"{len(scenes.table['group'])} echo rows, Gaussian TOF noise.  *Joint*: the echoes heard by two or more "
        "pairs whose fit of the true model fits (chi-square within the consistency test's limit), of the echoes "
        "the pair localises.  Errors of a plane's foot point, a corner's vertex, an edge's point; *CRLB*: the "
        "joint bound at the true point, RMS of its trace's root; *3 sigma*: normalised errors within the fit's "
        "own 3-sigma ellipse (99.73 % for a Gaussian), and their mean (2 for a Gaussian); *pair*: the pair's "
        "closed form of the same model on the same echoes.  *All echoes*: every echo the pair localises, by the "
        "joint fit where it has one, else by its pair.",
        "",
        "| σ_t | reflector | joint, of echoes | RMS joint | joint CRLB | RMS / CRLB | 3 sigma | mean normalised "
        "| RMS pair | median joint / pair | all echoes: median, joint where it can / pair |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| {1e6 * row['sigma']:.1f} µs | {row['name']} | {row['joint']} of {row['echoes']} "
            f"({100 * row['joint'] / row['echoes']:.0f} %) | {1e3 * row['rms']:.1f} mm | {1e3 * row['crlb']:.1f} mm "
            f"| {row['rms'] / row['crlb']:.2f} | {100 * row['within']:.2f} % | {row['nees']:.2f} "
            f"| {1e3 * row['pair_rms']:.1f} mm | {1e3 * row['median']:.1f} / {1e3 * row['pair_median']:.1f} mm "
            f"| {1e3 * row['all_median']:.1f} / {1e3 * row['all_pair_median']:.1f} mm |")
    lines += [
        "",
        "## What a ping's landmarks are",
        "",
        "The same echoes through the pipeline: *pairs*, one labelled landmark per echo row, each its pair's "
        "closed form by the class the ping's evidence decides (an undecided echo placed at the virtual image, "
        "`pipeline.classify_ping`); *published*, one per echo (`pipeline.joint_landmarks`): the joint fit by that "
        "class's model where two or more pairs heard it and the fit fits, else the pairs' landmarks.  Errors "
        "against the true point by the reflector's true class; *3 sigma*: the published landmarks' normalised "
        "errors within their own 3-sigma ellipse.",
        "",
        "| σ_t | reflector | landmarks: pairs / published | joint fits | median error: published / pairs "
        "| 3 sigma |",
        "|---|---|---|---|---|---|",
    ]
    for row in per_ping:
        lines.append(
            f"| {1e6 * row['sigma']:.1f} µs | {row['name']} | {row['pairs']} / {row['published']} "
            f"| {row['joint']} ({100 * row['joint'] / row['published']:.0f} %) "
            f"| {1e3 * row['median']:.1f} / {1e3 * row['pair_median']:.1f} mm | {100 * row['within']:.2f} % |")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
