"""What a benchmark report states about where and when it ran: machine, versions, revision, date."""

from __future__ import annotations

import datetime
import importlib.metadata
import os
import platform
import subprocess
import time
from pathlib import Path

import numpy as np

VERSIONED = ("numpy", "scipy", "matplotlib", "rclpy", "PyYAML")
"""Distributions whose versions a report lists (those installed)."""


def machine() -> str:
    """CPU model and count, OS, Python and numpy versions, and the load when the run started."""
    cpu = platform.processor() or "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    return (f"{cpu} ({os.cpu_count()} cores), {platform.system()} {platform.release()}, Python "
            f"{platform.python_version()}, numpy {np.__version__}; load average at start {load} "
            "(a shared machine: timings vary by up to 2x between runs)")


def versions() -> str:
    """``name version`` of Python and of each installed distribution of :data:`VERSIONED`, comma-separated."""
    found = [f"Python {platform.python_version()}"]
    for name in VERSIONED:
        try:
            found.append(f"{name} {importlib.metadata.version(name)}")
        except importlib.metadata.PackageNotFoundError:
            continue
    return ", ".join(found)


def revision(directory: Path) -> str:
    """Git commit of the checkout holding ``directory``, marked when the work tree differs; or "unknown"."""
    try:
        head = subprocess.run(["git", "-C", str(directory), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, timeout=10)
        if head.returncode != 0:
            return "unknown (not a git checkout)"
        changes = subprocess.run(["git", "-C", str(directory), "status", "--porcelain", "--untracked-files=no"],
                                 capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return "unknown (git not available)"
    dirty = " with uncommitted changes" if changes.stdout.strip() else ""
    return f"{head.stdout.strip()}{dirty}"


def today() -> str:
    """The current UTC date and time, ISO 8601 to the minute."""
    return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")


def write_report(path: Path, lines: list[str], started: float) -> None:
    """Write a study's Markdown ``lines`` to ``path``, ending with its run time since ``started``, and print it.

    ``started`` is a :func:`time.perf_counter` reading taken when the study began.
    """
    lines = [*lines, "", f"Run time: {time.perf_counter() - started:.0f} s."]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
