"""The report's pictures: error against time (Pareto), error against range and against bearing.

matplotlib is imported here only, and this module only when a report is
written; figures are drawn on an off-screen Agg canvas (no display, no pyplot).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import NullFormatter

from sonar_ring import uncertainty
from sonar_ring.benchmark.measure import HEADLINE, LSQ_NAME, NOISE_LEVELS, Results
from sonar_ring.benchmark.scenes import SWEEP_SPEED

MARKERS = dict(zip(NOISE_LEVELS, ("o", "s", "^", "D"), strict=True))
"""Marker of each noise level."""
PARETO_FAMILIES = ("plane", "corner", "edge", "range-only")
"""Families whose rows are localisation methods timed as such (``vertical`` times the correction alone)."""
FAMILY_COLOURS = {"plane": "tab:blue", "corner": "tab:red", "edge": "tab:green", "range-only": "tab:grey",
                  "bearing": "tab:purple"}
ROLE_STYLES = {"production": "-", "paper": "--", "baseline": ":"}
COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:grey",
           "tab:olive", "tab:cyan", "black", "gold", "navy", "lime", "teal", "maroon")
"""One colour per method of a Pareto panel."""


def _save(figure: Figure, path: Path) -> Path:
    FigureCanvasAgg(figure)
    figure.savefig(path, dpi=100)
    return path


def _short(name: str) -> str:
    """A method's name without the code in back-quotes, for legends."""
    return name.split(" (`")[0].split(" `")[0]


def _scatter_rows(ax, entries, scale: float) -> None:
    """``entries``: (label, ns per estimate, {sigma: rms}) per method; one point per method and noise level."""
    entries = [entry for entry in entries if np.isfinite(entry[1])]
    handles = []
    for (label, ns, errors), colour in zip(entries, COLOURS, strict=False):
        for sigma, rms in errors.items():
            if np.isfinite(rms) and rms > 0:
                ax.scatter(ns, rms * scale, marker=MARKERS[sigma], color=colour, s=30, zorder=3)
        handles.append(Line2D([], [], marker="o", linestyle="", color=colour, label=label))
    handles += [Line2D([], [], marker=MARKERS[s], linestyle="", color="black", label=f"sigma_t = {s * 1e6:g} us")
                for s in NOISE_LEVELS]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.14), fontsize=7, ncol=1, frameon=False)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("time per estimate, batched [ns]")
    ax.grid(True, which="major", alpha=0.3)


def pareto(results: Results, path: Path) -> Path:
    """RMS error against batched time per estimate, one point per method and noise level, three panels."""
    figure = Figure(figsize=(17, 9))
    positions, bearings, triads = figure.subplots(1, 3)
    entries = [(f"{row.family}: {_short(row.name)}", row.ns_per_landmark,
                {s: a.rms for s, a in row.levels.items()})
               for row in results.rows if row.family in PARETO_FAMILIES]
    _scatter_rows(positions, entries, 1.0)
    positions.set_ylabel("RMS position error [m]")
    positions.set_title("ring echoes in the standard scenes")
    entries = [(_short(row.name), row.ns_per_landmark, {s: a.rms for s, a in row.levels.items()})
               for row in results.family("bearing")]
    _scatter_rows(bearings, entries, np.degrees(1.0))
    bearings.set_ylabel("RMS bearing error [deg]")
    bearings.set_title("bearing sweep, +-80 deg, 0.5-5 m")
    names = [run.name for run in results.triads["runs"][HEADLINE]]
    entries = []
    for index, name in enumerate(names):
        errors = {}
        for sigma, runs in results.triads["runs"].items():
            run = runs[index]
            errors[sigma] = float(np.sqrt(np.mean(np.square(run.error[run.valid])))) if run.valid.any() else np.nan
        entries.append((name, results.triads["runs"][HEADLINE][index].batched * 1e9, errors))
    _scatter_rows(triads, entries, np.degrees(1.0))
    triads.set_ylabel("RMS azimuth error, wrong lobes included [deg]")
    triads.set_title("Kreczmer triad, sigma_t = zero-crossing jitter")
    figure.suptitle("Speed against error (lower left is better)")
    figure.tight_layout()
    return _save(figure, path)


def _binned(along, error, edges, statistic, minimum=5):
    centres, values = [], []
    for low, high in zip(edges[:-1], edges[1:], strict=True):
        inside = (along >= low) & (along < high) & np.isfinite(error)
        if inside.sum() >= minimum:
            centres.append(0.5 * (low + high))
            values.append(statistic(np.abs(error[inside])))
    return np.array(centres), np.array(values)


def _rms(values):
    return np.sqrt(np.mean(values**2))


def _noisy_and_exact(noisy, exact, bin_name: str, x_label: str, y_label: str) -> None:
    """Titles, log scale, labels and grid of the two panels: RMS at the headline noise, largest error without."""
    noisy.set_title(f"sigma_t = {HEADLINE * 1e6:g} us: RMS per {bin_name}")
    exact.set_title(f"noise-free: largest error per {bin_name}")
    for ax in (noisy, exact):
        ax.set_yscale("log")
        ax.set_xlabel(x_label)
        ax.set_ylabel(y_label)
        ax.grid(True, which="major", alpha=0.3)


def error_vs_range(results: Results, path: Path) -> Path:
    """Position error against the true range from the ring centre: RMS at the headline noise, max noise-free."""
    figure = Figure(figsize=(12, 5))
    noisy, exact = figure.subplots(1, 2)
    edges = np.arange(0.25, 6.51, 0.25)
    for row in results.rows:
        # least squares ran on a subsample; the ideal classifier repeats the families' production rows
        if row.family not in PARETO_FAMILIES or row.name == LSQ_NAME or not np.isfinite(row.ns_per_landmark):
            continue
        style = dict(color=FAMILY_COLOURS[row.family], linestyle=ROLE_STYLES[row.role], marker=".",
                     label=f"{row.family}: {_short(row.name)}")
        noisy.plot(*_binned(row.along, row.errors[HEADLINE], edges, _rms), **style)
        exact.plot(*_binned(row.along, row.errors[0.0], edges, np.max), **style)
    _noisy_and_exact(noisy, exact, "0.25 m of range", "true range from the ring centre [m]", "position error [m]")
    exact.legend(fontsize=6.5, loc="center right")
    figure.tight_layout()
    return _save(figure, path)


def error_vs_bearing(results: Results, path: Path) -> Path:
    """Bearing error against the true bearing: RMS at the headline noise with the CRLB, max noise-free."""
    figure = Figure(figsize=(12, 5))
    noisy, exact = figure.subplots(1, 2)
    edges = np.radians(np.arange(-80, 80.1, 5))
    rows = results.family("bearing")
    for index, row in enumerate(rows):
        style = dict(color=f"C{index}", marker=".", linestyle=ROLE_STYLES[row.role], label=_short(row.name))
        for ax, sigma, statistic in ((noisy, HEADLINE, _rms), (exact, 0.0, np.max)):
            centres, values = _binned(row.along, row.errors[sigma], edges, statistic)
            ax.plot(np.degrees(centres), np.degrees(values), **style)
    centres = 0.5 * (edges[:-1] + edges[1:])
    separation = results.sweep_separation
    bound = uncertainty.cramer_rao_bound(separation, HEADLINE, SWEEP_SPEED, centres)[0]
    noisy.plot(np.degrees(centres), np.degrees(bound), color="black", linewidth=1, label="Cramer-Rao bound")
    _noisy_and_exact(noisy, exact, "5 deg (0.5-5 m)", "true bearing at R1 [deg]", "bearing error [deg]")
    noisy.legend(fontsize=7)
    figure.tight_layout()
    return _save(figure, path)


def save_all(results: Results, directory: Path) -> list[Path]:
    """Write every picture into ``directory`` (created); return their paths."""
    directory.mkdir(parents=True, exist_ok=True)
    return [pareto(results, directory / "pareto.png"),
            error_vs_range(results, directory / "error_vs_range.png"),
            error_vs_bearing(results, directory / "error_vs_bearing.png")]
