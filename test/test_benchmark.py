"""``sonar-ring bench --quick``: the report is produced end to end -- rows, targets, plots -- not its timings."""

import importlib.util
import re
import time

import pytest

from sonar_ring.benchmark import slam_cost, worlds
from sonar_ring.benchmark.environment import write_report
from sonar_ring.benchmark.measure import LSQ_NAME
from sonar_ring.benchmark.methods import BEARING, RING_FAMILIES
from sonar_ring.benchmark.report import LATENCY_BEGIN, LATENCY_END, PLOT_DIR, REPORT, TABLE_BEGIN, TABLE_END
from sonar_ring.cli import main

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def test_quick_report_has_every_row_the_targets_and_the_plots(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text(f"# Project\n\n{TABLE_BEGIN}\nan old table\n{TABLE_END}\n\n## Next section\n")
    kept = f"{worlds.SECTION_BEGIN}\n## Maps in a real robot's world\n\nthe map study's table\n{worlds.SECTION_END}"
    cost = f"{slam_cost.SECTION_BEGIN}\n## Cost of the mapper with SLAM\n\nthe cost table\n{slam_cost.SECTION_END}"
    history = f"{LATENCY_BEGIN}\n## Latency work, step by step\n\nwritten by hand\n{LATENCY_END}"
    (tmp_path / REPORT).write_text(f"# An old report\n\n{kept}\n\n{cost}\n\n{history}\n")
    assert main(["bench", "--quick", "--out", str(tmp_path), "--seed", "3"]) == 0

    text = (tmp_path / REPORT).read_text()
    assert "An old report" not in text and kept in text and cost in text  # the studies' sections survive a rerun
    assert history in text  # and so does the history written by hand
    tables = text[text.index(TABLE_BEGIN):text.index(TABLE_END)]
    for family in (BEARING, *RING_FAMILIES):
        for method in family.methods:
            assert f"| {family.name} | {method.name} | {method.role} |" in tables
    for family in ("plane", "corner", "edge"):
        assert f"| {family} | {LSQ_NAME} | baseline |" in tables
    for row in ("| classification | amplitude rules", "| classification | consistency test",
                "| azimuth (triad) | Kreczmer (n1, n2) search", "| azimuth (triad) | grid search over phi, 0.01 deg",
                "| azimuth (triad) | direct, R1-R2 pair", "| graph | ping → markers"):
        assert row in tables
    # the graph row holds figures where ROS 2 is there, else says what it needs
    graph_row = next(line for line in tables.splitlines() if line.startswith("| graph |"))
    if importlib.util.find_spec("rclpy") is None:
        assert "needs ROS 2" in graph_row
    else:  # make test runs in the built ROS 2 environment: the graph must have run
        assert "latency median" in graph_row, graph_row

    targets = text[text.index("## Targets"):text.index("## Main tables")]
    for target in ("≤ 100 ns per landmark", "plane: ≥ 1000× faster than per-point least squares",
                   "corner: ≥ 1000× faster", "edge: ≥ 1000× faster", "noise-free position error ≤ 1e-9 m",
                   "within 10 % of the CRLB", "in < 10 min on 2 cores", "graph: ping → markers median ≤ 2 ms",
                   "pings/s sustained"):
        line = next(line for line in targets.splitlines() if target in line)
        assert re.search(r"\*\*(met|missed)\*\*", line), line
    for stated in ("- Date: ", "- Machine: ", "- Versions: Python", "`--seed 3`", "--quick"):
        assert stated in text

    for name in ("pareto.png", "error_vs_range.png", "error_vs_bearing.png"):
        picture = tmp_path / PLOT_DIR / name
        assert picture.read_bytes()[:8] == PNG_SIGNATURE
        assert f"]({(PLOT_DIR / name).as_posix()})" in text

    updated = readme.read_text()
    assert "an old table" not in updated
    assert updated.startswith("# Project\n\n" + TABLE_BEGIN) and updated.endswith(TABLE_END + "\n\n## Next section\n")
    assert tables.strip() in updated


def test_a_report_without_the_latency_history_gets_none(tmp_path):
    from sonar_ring.benchmark.report import kept_sections

    (tmp_path / REPORT).write_text("# An old report\n")
    kept = "\n".join(kept_sections(tmp_path / REPORT))
    assert LATENCY_BEGIN not in kept and "Latency work" not in kept
    assert worlds.SECTION_BEGIN in kept and slam_cost.SECTION_BEGIN in kept  # placeholders that say how to make them


def test_quick_map_study_writes_its_section_and_readme_table(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text(f"# Project\n\n{worlds.SUMMARY_BEGIN}\nold\n{worlds.SUMMARY_END}\n")
    assert main(["bench", "--map", "--quick", "--out", str(tmp_path)]) == 0
    text = (tmp_path / REPORT).read_text()
    section = text[text.index(worlds.SECTION_BEGIN):text.index(worlds.SECTION_END)]
    for world in ("ideal", "realistic"):
        row = next(line for line in section.splitlines() if line.startswith(f"| {world} | odom-frame map"))
        assert re.search(r"\| \d+\.\d of \d+\.\d \|", row) and "ms |" in row, row
        # walls past their ends (median / worst; runs within 2 cm) and the pose's RMS / final error
        assert re.search(r"\| \d+\.\d / \d+\.\d cm, \d of 2 \|", row), row
        assert re.search(r"\| \d+\.\d / \d+\.\d cm \|", row), row
    # the similarity fit: the shape's point error, the scale and the rotation the whole map is off by
    assert re.search(r"\| \d+\.\d mm; ×\d\.\d{4}, \d+\.\d\d° \|", section), section
    assert "sonar-ring bench --map" in section and "2 seeds" in section
    summary = readme.read_text()
    assert "old" not in summary and "| realistic | odom-frame map |" in summary
    assert "| realistic | SLAM + echo tests |" in summary
    assert main(["bench", "--map", "--seed", "1", "--out", str(tmp_path)]) == 1  # the study's seeds are fixed


def test_graph_targets_are_judged_on_one_cpu_with_any_cpu_beside():
    from sonar_ring.benchmark.report import _graph_targets

    latency = {"latency_median_ms": 1.6, "latency_p99_ms": 3.9, "rate_hz": 30.0, "pings": 600, "dropped": 0}
    unpinned = {**latency, "latency_median_ms": 2.06, "latency_p99_ms": 5.1}
    graph = {**latency, "max_sustained_rate_hz": 300.0, "ladder": [], "cpu": 1, "any_cpu": unpinned}
    (_, figures, verdict), (_, rate_figures, rate_verdict) = _graph_targets(graph)
    assert figures == "on CPU 1 (`cpus:=1`): median 1.60 ms, p99 3.90 ms; on any CPU: median 2.06 ms, p99 5.10 ms"
    assert verdict == "**met** on one CPU; on any CPU **missed** (median ×1.03, p99 ×1.02 the target)"
    assert (rate_figures, rate_verdict) == ("on CPU 1 (`cpus:=1`): sustains 300 Hz", "**met**")
    # A machine that gives the benchmark one CPU: one run, on it, judged as it is.
    alone = {**graph, "cpu": 0, "any_cpu": None, "latency_median_ms": 2.5}
    (_, figures, verdict), _ = _graph_targets(alone)
    assert figures == "on CPU 0 (`cpus:=0`): median 2.50 ms, p99 3.90 ms"
    assert verdict == "**missed** (median ×1.25, p99 ×0.78 the target)"
    # A failed second run leaves the first one's figures and verdicts.
    failed = {**graph, "note": "the graph", "node_latency_ms": {},
              "any_cpu": {"error": "failed: the graph did not start: no output"}}
    (_, figures, verdict), (_, _, rate_verdict) = _graph_targets(failed)
    assert figures.endswith("; on any CPU: failed: the graph did not start: no output")
    assert verdict == "**met** on one CPU; on any CPU not measured" and rate_verdict == "**met**"
    assert "failed: the graph did not start" in "".join(_graph_section_lines(failed))


def _graph_section_lines(graph):
    from types import SimpleNamespace

    from sonar_ring.benchmark.report import _graph_section

    return _graph_section(SimpleNamespace(graph=graph, pipeline={"error": "not run"}))


def test_quick_slam_cost_writes_its_section_beside_the_others(tmp_path):
    kept = f"{worlds.SECTION_BEGIN}\n## Maps in a real robot's world\n\nthe map study's table\n{worlds.SECTION_END}"
    (tmp_path / REPORT).write_text(f"# Benchmarks\n\n{kept}\n\n{slam_cost.SECTION_BEGIN}\nold figures\n"
                                   f"{slam_cost.SECTION_END}\n")
    assert main(["bench", "--slam-cost", "--quick", "--out", str(tmp_path)]) == 0
    text = (tmp_path / REPORT).read_text()
    assert kept in text and "old figures" not in text and text.count(slam_cost.SECTION_BEGIN) == 1
    section = text[text.index(slam_cost.SECTION_BEGIN):text.index(slam_cost.SECTION_END)]
    for stated in ("Regenerate with `sonar-ring bench --slam-cost --quick`", "sonar_ring at git", "cores",
                   "load average at start", "not for reading"):
        assert stated in section, stated

    targets = {name: next(line for line in section.splitlines() if line.startswith("| " + name))
               for name in ("mapper update per ping", "memory flat over a 0.1-minute run", "`sonar-ring process`")}
    per_ping, memory, process = targets.values()
    assert re.search(r"\| median \d+\.\d\d ms, p99 \d+\.\d\d ms over 150 pings \| \*\*(met|missed)\*\*", per_ping)
    assert re.search(r"\| [+-]\d+\.\d % \(\d+\.\d MiB at 0\.\d min, \d+\.\d MiB at 0\.1 min; peak \+\d+\.\d %\) "
                     r"\| \*\*(met|missed)\*\* \|$", memory), memory
    if importlib.util.find_spec("rclpy") is None or importlib.util.find_spec("sonar_ring.msg") is None:
        assert "needs ROS 2" in process and process.endswith("| not measured |")
    else:  # make test runs in the built ROS 2 environment: the command must have run
        assert re.search(r"\| ×\d+\.\d: 2\.0 s of data in \d+\.\d\d s \(median of 1 run of the whole command\); "
                         r"120 pings: ×\d+\.\d \(4\.0 s in \d+\.\d\d s\) \| \*\*(met|missed)\*\*", process), process
        assert section.count("timed as a whole command, 1 run:") == 2  # a paragraph per recording

    lap = next(line for line in section.splitlines() if line.startswith("| lap 1 | 150 |"))
    assert lap.count(" ms") >= 12 and "not measured" not in lap, lap  # every part timed
    readings = [line for line in section.splitlines() if re.match(r"\| \d+\.\d min \| \d+ \| \d+\.\d MiB \|", line)]
    assert [int(line.split(" | ")[1]) for line in readings] == [0, 30, 60, 90, 120, 150, 180]

    assert main(["bench", "--slam-cost", "--seed", "1", "--out", str(tmp_path)]) == 1  # the simulation's seed is fixed
    with pytest.raises(SystemExit):
        main(["bench", "--slam-cost", "--map", "--out", str(tmp_path)])  # one study at a time


def test_memory_growth_is_judged_after_the_warm_up_and_says_when_the_run_stopped_early():
    def reading(minute, mib):
        return dict(minute=minute, rss=mib * 2**20)

    run = dict(samples=[reading(0.0, 80), reading(2.5, 200), reading(5.0, 300), reading(20.0, 330),
                        reading(30.0, 312)], stopped="")
    found = slam_cost.growth(run, warmup=5.0)
    assert found["base"]["minute"] == 5.0 and found["growth"] == pytest.approx(0.04)
    assert found["peak_growth"] == pytest.approx(0.10)
    target, figures, verdict = slam_cost._memory_target(run, 30.0, 5.0)
    assert "≤ 5 % after warm-up (5 min)" in target and verdict == "**met**"
    assert figures == "+4.0 % (300.0 MiB at 5.0 min, 312.0 MiB at 30.0 min; peak +10.0 %)"

    stopped = dict(run, samples=run["samples"][:4], stopped="stopped at the wall-time budget (60 min) after 20.0 of 30 "
                                                             "simulated minutes")
    _, figures, verdict = slam_cost._memory_target(stopped, 30.0, 5.0)
    assert figures.endswith("; stopped at the wall-time budget (60 min) after 20.0 of 30 simulated minutes")
    assert verdict == "**missed** up to 20.0 min; not measured to 30 min"
    early = dict(run, samples=run["samples"][:2], stopped="stopped at the wall-time budget")
    assert slam_cost._memory_target(early, 30.0, 5.0)[1:] == ("stopped at the wall-time budget", "not measured")


def test_a_study_report_ends_with_its_run_time(tmp_path):
    started = time.perf_counter() - 3.0
    report = tmp_path / "results" / "study.md"
    write_report(report, ["# A study", "", "| a |"], started)
    # 3 s, or more on a machine busy enough to stall the write: the test times nothing
    assert re.fullmatch(r"# A study\n\n\| a \|\n\nRun time: \d+ s\.\n", report.read_text())
    assert int(report.read_text().split("Run time: ")[1].split(" ")[0]) >= 3
