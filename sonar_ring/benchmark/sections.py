"""Marked sections of ``BENCHMARKS.md`` and the README: one study's text between its two markers.

A study that is run apart from ``sonar-ring bench`` (``--map``, ``--slam-cost``)
writes its section between its own markers; ``sonar-ring bench`` keeps those
sections when it rewrites the rest of the report (:func:`kept`), and each study
replaces only its own (:func:`write`).  A section written by hand between its
own markers is kept as it stands (:func:`existing`).
"""

from __future__ import annotations

from pathlib import Path


def replace(path: Path, begin: str, end: str, lines: list[str]) -> bool:
    """Put ``lines`` (markers included) where ``begin`` ... ``end`` stand in ``path``; False without file or markers."""
    if not path.is_file():
        return False
    text = path.read_text()
    start, stop = text.find(begin), text.find(end)
    if start < 0 or stop < start:
        return False
    path.write_text(text[:start] + "\n".join(lines) + text[stop + len(end):])
    return True


def write(report: Path, begin: str, end: str, lines: list[str]) -> None:
    """Replace the section in ``report``, or append it when the report has none (or create the report)."""
    if not replace(report, begin, end, lines):
        existing = report.read_text() if report.is_file() else "# Benchmarks\n"
        report.write_text(existing.rstrip("\n") + "\n\n" + "\n".join(lines) + "\n")


def existing(report: Path, begin: str, end: str) -> list[str]:
    """The section of an existing ``report`` (markers included); empty without file or markers."""
    if report.is_file():
        text = report.read_text()
        start, stop = text.find(begin), text.find(end)
        if 0 <= start < stop:
            return text[start:stop + len(end)].splitlines()
    return []


def kept(report: Path, begin: str, end: str, title: str, command: str) -> list[str]:
    """The section of an existing ``report`` (markers included), or one that says ``command`` makes it."""
    return existing(report, begin, end) or [begin, title, "", f"Not measured yet: run `{command}`.", end]
