"""Benchmark of the localisation core on Browne's full 1 mm test grid.

Regenerate ``bench/results/localise.md`` (about a minute on one core)::

    source tools/env.sh && python bench/bench_localise.py   # from the repository root

For one receiver pair of the shipped ``browne_ring`` layout (D = 40 mm, ring
radius 0.31 m) and every point of Browne's grid (section 5: 1 mm steps, 0.01 to
5.7 m in front of the pair, +-1 m to its sides, 11.4 million points) it forms
the noise-free path lengths of a plane (foot point on the grid), a corner and
an edge (in extended precision, rounded to float64), localises them with the
production path (:mod:`sonar_ring.localise`) and with Browne's formulas
(:mod:`sonar_ring.reference.browne`), and reports the maximum position errors
and the wall-clock time of each model over the whole grid.  A Monte-Carlo run
compares the bearing and range spread with the Cramer-Rao bound of one pair
(``uncertainty.cramer_rao_bound``).  Results go to ``bench/results/localise.md``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from sonar_ring import localise as loc
from sonar_ring import uncertainty
from sonar_ring.benchmark.environment import machine
from sonar_ring.benchmark.timing import interleaved_best
from sonar_ring.geometry import load_layout
from sonar_ring.reference import browne

ROOT = Path(__file__).resolve().parents[1]

LD = np.longdouble
AHEAD_MM = np.arange(10, 5701)  # 0.010 .. 5.700 m in front of the pair
SIDE_MM = np.arange(-1000, 1001)  # -1.000 .. 1.000 m
CHUNK_ROWS = 150  # rows of AHEAD per chunk: 300 k points
BANDS = ((0.01, 1.0), (1.0, 3.0), (3.0, 5.7))
REPEATS = 5
C = 343.2
SIGMA_TOF = 1e-6


def norm(v):
    return np.sqrt(np.sum(np.square(v), axis=-1))


def chunks(radius):
    """Yield (ahead in m, grid points (n, 2)) for consecutive blocks of rows of the grid."""
    side = SIDE_MM / 1000.0
    for start in range(0, AHEAD_MM.size, CHUNK_ROWS):
        ahead = AHEAD_MM[start:start + CHUNK_ROWS] / 1000.0
        x, y = np.meshgrid(radius + ahead, side, indexing="ij")
        yield np.repeat(ahead, side.size), np.stack([x.ravel(), y.ravel()], axis=-1)


def truth(tx, rx1, rx2, points):
    """Float64 path lengths (from extended precision) and the true reflection point of receiver 1."""
    p, t, r1, r2 = points.astype(LD), tx.astype(LD), rx1.astype(LD), rx2.astype(LD)
    image = 2 * p - t
    corner = (norm(image - r1).astype(float), norm(image - r2).astype(float))
    k = norm(p - t)
    edge = ((k + norm(p - r1)).astype(float), (k + norm(p - r2)).astype(float))
    normal = (p - t) / k[:, None]
    reflection = []
    for r in (r1, r2):
        depth = np.sum((p - r) * normal, axis=-1)
        reflection.append((r + (depth / np.sum((image - r) * normal, axis=-1))[:, None] * (image - r)).astype(float))
    return corner, edge, reflection


class Tally:
    """Maximum error per range band and overall, and the count of invalid (non-finite) results."""

    def __init__(self):
        self.worst = np.zeros(len(BANDS))
        self.invalid = 0

    def add(self, ahead, error):
        """Fold in the errors of one chunk (``ahead``: each point's distance in front of the pair)."""
        self.invalid += int(np.count_nonzero(~np.isfinite(error)))
        for i, (low, high) in enumerate(BANDS):
            band = error[(ahead >= low) & (ahead <= high)]
            if band.size:
                self.worst[i] = max(self.worst[i], np.nanmax(band))

    @property
    def overall(self):
        """Maximum over the whole grid."""
        return self.worst.max()


def run_grid(tx, rx1, rx2, radius, separation):
    names = ["plane", "corner", "edge", "bearing"]
    production = {name: Tally() for name in names}
    paper = {name: Tally() for name in names}
    agreement = {name: 0.0 for name in names}
    for ahead, points in chunks(radius):
        (c1, c2), (e1, e2), reflection = truth(tx, rx1, rx2, points)
        true_bearing = np.arctan2(*(2 * points - tx - rx1).T[::-1])

        plane = loc.plane(tx, rx1, rx2, c1, c2)
        corner = loc.corner(tx, rx1, rx2, c1, c2)
        edge = loc.edge(tx, rx1, rx2, e1, e2)
        bearing = loc.bearing(c1, c2, separation)
        plane_error = np.maximum.reduce([norm(plane.position - points),
                                         norm(plane.reflection_points[:, 0] - reflection[0]),
                                         norm(plane.reflection_points[:, 1] - reflection[1])])
        production["plane"].add(ahead, np.where(plane.valid, plane_error, np.inf))
        production["corner"].add(ahead, np.where(corner.valid, norm(corner.position - points), np.inf))
        production["edge"].add(ahead, np.where(edge.valid, norm(edge.position - points), np.inf))
        production["bearing"].add(ahead, np.where(bearing.valid, np.abs(bearing.value - true_bearing), np.inf))

        paper_plane = browne.plane_point(c1, c2, separation, radius)
        paper_corner = browne.corner_point(c1, c2, separation, radius)
        paper_edge = browne.edge_point(e1, e2, separation, radius)
        paper_bearing = browne.bearing_eq4(c1, c2, separation)
        paper["plane"].add(ahead, norm(paper_plane - reflection[0]))
        paper["corner"].add(ahead, norm(paper_corner - points))
        paper["edge"].add(ahead, norm(paper_edge - points))
        paper["bearing"].add(ahead, np.abs(paper_bearing - true_bearing))

        agreement["plane"] = max(agreement["plane"], np.max(norm(paper_plane - plane.reflection_points[:, 0])))
        agreement["corner"] = max(agreement["corner"], np.max(norm(paper_corner - corner.position)))
        agreement["edge"] = max(agreement["edge"], np.max(norm(paper_edge - edge.position)))
        agreement["bearing"] = max(agreement["bearing"], np.max(np.abs(paper_bearing - bearing.value)))
    return production, paper, agreement


def time_full_grid(tx, rx1, rx2, radius, separation):
    """Best-of-REPEATS wall-clock seconds (production, reference) over the whole grid, paths prepared beforehand."""
    prepared = []
    for _, points in chunks(radius):
        (c1, c2), (e1, e2), _ = truth(tx, rx1, rx2, points)
        prepared.append((c1, c2, e1, e2))
    calls = {
        "plane": (lambda c1, c2, e1, e2: loc.plane(tx, rx1, rx2, c1, c2),
                  lambda c1, c2, e1, e2: browne.plane_point(c1, c2, separation, radius)),
        "corner": (lambda c1, c2, e1, e2: loc.corner(tx, rx1, rx2, c1, c2),
                   lambda c1, c2, e1, e2: browne.corner_point(c1, c2, separation, radius)),
        "edge": (lambda c1, c2, e1, e2: loc.edge(tx, rx1, rx2, e1, e2),
                 lambda c1, c2, e1, e2: browne.edge_point(e1, e2, separation, radius)),
        "bearing": (lambda c1, c2, e1, e2: loc.bearing(c1, c2, separation),
                    lambda c1, c2, e1, e2: browne.bearing_eq4(c1, c2, separation)),
    }
    # production and reference alternate, so that load from other processes hits both alike
    runs = {(name, which): (lambda function=function: [function(*arrays) for arrays in prepared])
            for name, pair in calls.items() for which, function in enumerate(pair)}
    best = interleaved_best(runs, REPEATS)
    return {name: [best[name, 0], best[name, 1]] for name in calls}


def monte_carlo(samples=100_000):
    """Bearing (eq 4) and corner range spread vs the CRLB: D = 40 mm, transmitter at the pair's mid-point."""
    tx, rx1, rx2 = np.zeros(2), np.array([0.0, 0.02]), np.array([0.0, -0.02])
    rng = np.random.default_rng(2011)
    rows = []
    for degrees in (-45, -30, -15, 0, 15, 30, 45):
        phi = np.radians(degrees)
        apex = 2.0 * np.array([np.cos(phi), np.sin(phi)])
        image = 2 * apex - tx
        d1, d2 = norm(image - rx1), norm(image - rx2)
        true_bearing = np.arctan2(*(image - rx1)[::-1])
        noisy1 = d1 + C * SIGMA_TOF * rng.normal(size=samples)
        noisy2 = d2 + C * SIGMA_TOF * rng.normal(size=samples)
        sigma_bearing, sigma_range = uncertainty.cramer_rao_bound(0.04, SIGMA_TOF, C, true_bearing)
        bearings = loc.bearing(noisy1, noisy2, 0.04).value
        ranges = norm(loc.corner(tx, rx1, rx2, noisy1, noisy2).position - tx)
        rows.append((degrees, np.std(bearings) / sigma_bearing, (np.mean(bearings) - true_bearing) / sigma_bearing,
                     np.std(ranges) / sigma_range, (np.mean(ranges) - 2.0) / sigma_range,
                     np.degrees(sigma_bearing), sigma_range * 1e3))
    return rows


def main():
    ring = load_layout("browne_ring")
    rx1, rx2 = ring.group_receivers()[0, :, :2]
    tx = ring.transmitters[0, :2]
    radius = float(np.mean([rx1[0], rx2[0]]))
    separation = float(ring.group_separation()[0])
    points = AHEAD_MM.size * SIDE_MM.size

    start = time.perf_counter()
    production, paper, agreement = run_grid(tx, rx1, rx2, radius, separation)
    seconds = time_full_grid(tx, rx1, rx2, radius, separation)
    crlb = monte_carlo()
    total = time.perf_counter() - start

    units = {"plane": "m", "corner": "m", "edge": "m", "bearing": "rad"}
    lines = [
        "# Localisation benchmark: Browne's 1 mm grid",
        "",
        "Regenerate: `python bench/bench_localise.py` (from the repository root, after `source tools/env.sh`; "
        f"took {total:.0f} s here).",
        "",
        f"Machine: {machine()}.",
        "",
        f"Grid: pair 0 of `browne_ring` (D = {separation * 1e3:.0f} mm, emitter at the ring centre "
        f"{radius:.2f} m behind the pair), every 1 mm from 0.010 to 5.700 m in front of the pair and "
        f"-1.000 to 1.000 m to its sides: {AHEAD_MM.size} x {SIDE_MM.size} = {points:,} points per model. "
        "Noise-free paths are formed in extended precision (80-bit) and rounded to float64; "
        "a plane's foot point, a corner and an edge sit on each grid point.",
        "",
        "## Maximum position error over the grid (noise-free round trip)",
        "",
        "| model | production | Browne's formulas | production vs Browne | invalid: production, Browne |",
        "|---|---|---|---|---|",
    ]
    references = {"plane": "eqs 9-18 (X of R1)", "corner": "eq 19", "edge": "Appendix A", "bearing": "eq 4"}
    for name in ("plane", "corner", "edge", "bearing"):
        lines.append(f"| {name} | {production[name].overall:.2e} {units[name]} | {paper[name].overall:.2e} "
                     f"{units[name]} ({references[name]}) | {agreement[name]:.2e} {units[name]} | "
                     f"{production[name].invalid}, {paper[name].invalid} |")
    lines += [
        "",
        "The production plane error is the worst of its foot point and both reflection points; "
        "Browne's plane formulas give the reflection point X of receiver R1 only.",
        "",
        "By range band (maximum error):",
        "",
        "| model | " + " | ".join(f"{lo:g}-{hi:g} m prod." for lo, hi in BANDS) + " | "
        + " | ".join(f"{lo:g}-{hi:g} m Browne" for lo, hi in BANDS) + " |",
        "|---|" + "---|" * (2 * len(BANDS)),
    ]
    for name in ("plane", "corner", "edge", "bearing"):
        lines.append(f"| {name} | " + " | ".join(f"{v:.1e}" for v in production[name].worst) + " | "
                     + " | ".join(f"{v:.1e}" for v in paper[name].worst) + " |")
    lines += [
        "",
        f"## Time for the whole grid ({points:,} points, best of {REPEATS}, chunks of "
        f"{CHUNK_ROWS * SIDE_MM.size:,} points)",
        "",
        "| model | production | Browne's formulas | production / Browne | production per point |",
        "|---|---|---|---|---|",
    ]
    for name, (ours, theirs) in seconds.items():
        lines.append(f"| {name} | {ours:.2f} s | {theirs:.2f} s | {ours / theirs:.2f} | "
                     f"{ours / points * 1e9:.0f} ns |")
    lines += [
        "",
        "Production calls include the input checks and reason codes; the plane also returns its normal and "
        "both reflection points.",
        "",
        "## Monte Carlo vs the Cramer-Rao bound (uncertainty.cramer_rao_bound)",
        "",
        f"sigma_t = {SIGMA_TOF * 1e6:.0f} us, c = {C} m/s, D = 40 mm, transmitter at the pair's mid-point, "
        "corner at 2 m; 100,000 draws per bearing. Bearing = eq 4 (`localise.bearing`), range = distance of "
        "the `localise.corner` estimate from the transmitter.",
        "",
        "| phi | std(bearing) / CRLB | bias(bearing) / CRLB | std(range) / CRLB | bias(range) / CRLB | "
        "CRLB bearing | CRLB range |",
        "|---|---|---|---|---|---|---|",
    ]
    for degrees, b_ratio, b_bias, r_ratio, r_bias, sb, sr in crlb:
        lines.append(f"| {degrees:+d} deg | {b_ratio:.3f} | {b_bias:+.3f} | {r_ratio:.3f} | {r_bias:+.3f} | "
                     f"{sb:.3f} deg | {sr:.4f} mm |")
    out = ROOT / "bench" / "results" / "localise.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
