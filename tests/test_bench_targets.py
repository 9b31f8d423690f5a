"""The benchmark targets and their check: which rows meet or miss what, and what ``--check`` says.

Pure logic on made-up rows and run files: no benchmark runs, nothing is timed.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from bench import tables, targets
from bench.registry import Row
from bench.stats import summarize
from bench.targets import TARGETS, Target

ROOT = Path(__file__).resolve().parents[1]


def row(metric: str, median: float, *, unit: str = "ms", baseline: str | None = None, ratio: float | None = None) -> Row:
    scale = 1.0 if unit != "ms" else 1000.0
    return Row(metric, metric, summarize([median / scale] * 3, scale), baseline=baseline, ratio=ratio, unit=unit)


def test_every_row_of_issue_15s_table_has_a_target() -> None:
    metrics = {t.metric for t in TARGETS if t.source == "issue 15"}
    assert metrics >= {"mesh_event", "mesh_set_property", "fanout_mesh_1", "fanout_mesh_8", "wildcard_mesh_100000",
                       "migration_1mib", "migration_10mib", "act_one_client", "mesh_token_seen",
                       "migration_return_10mib_delta", "migration_return_10mib_delta_sent"}
    assert len({t.metric for t in TARGETS}) == len(TARGETS)


def test_a_ratio_ceiling_is_met_at_the_bound_and_missed_above_it() -> None:
    at, above = row("mesh_event", 0.13, ratio=1.3), row("mesh_event", 0.14, ratio=1.31)
    targets.apply([at, above])
    assert (at.target, at.at_least) == (1.3, False)
    assert at.meets is True and above.meets is False
    assert "MISSED" in above.verdict() and "<= 1.3x" in above.verdict()


def test_a_rate_is_higher_is_better() -> None:
    fast, slow = row("fanout_mesh_8", 50_000, unit="events/s", ratio=0.5), row("fanout_mesh_8", 20_000, unit="events/s", ratio=0.2)
    targets.apply([fast, slow])
    assert fast.at_least and fast.meets is True
    assert slow.meets is False
    assert ">= 0.5x MISSED" in slow.verdict()


def test_a_strict_limit_is_missed_at_the_bound() -> None:
    under, at = row("migration_return_10mib_delta", 19.9), row("migration_return_10mib_delta", 20.0)
    sent = row("migration_return_10mib_delta_sent", 0.5, unit="%")
    targets.apply([under, at, sent])
    assert under.strict and under.meets is True
    assert at.meets is False
    assert sent.meets is True and sent.bounds() == "< 1 %"


def test_an_inclusive_limit_is_met_at_the_bound() -> None:
    act = row("act_one_client", 0.6)
    targets.apply([act])
    assert act.limit == 0.6 and not act.strict and act.meets is True


def test_a_target_the_run_did_not_measure_is_not_measured_not_missed() -> None:
    rows = [row("mesh_event", 0.1, ratio=1.1)]
    verdicts = {v.target.metric: v.state for v in targets.verdicts(rows)}
    assert verdicts["mesh_event"] == "met"
    assert verdicts["migration_return_10mib_delta"] == "not measured"
    assert targets.missed(rows) == []


def test_a_ratio_target_without_a_ratio_is_missed_not_met() -> None:
    # the baseline failed, so the ratio could not be computed: the target is not shown to be met
    missed = targets.missed([row("mesh_set_property", 0.3)])
    assert [v.target.metric for v in missed] == ["mesh_set_property"]
    assert missed[0].state == "no ratio"


def test_a_row_in_another_unit_than_its_target_is_missed_not_compared() -> None:
    sent = row("migration_return_10mib_delta_sent", 0.5, unit="bytes")
    targets.apply([sent])
    assert sent.limit is None
    assert [v.state for v in targets.missed([sent])] == ["wrong unit"]


def test_rows_come_back_from_json_as_they_were() -> None:
    original = row("fanout_mesh_1", 123_456, unit="events/s", baseline="fanout_raw_1", ratio=0.45)
    original.extra["lost"] = 0
    targets.apply([original])
    back = Row.from_json(json.loads(json.dumps(original.to_json())))
    assert back == original
    latency = row("migration_return_10mib_delta", 12.5)
    targets.apply([latency])
    assert Row.from_json(latency.to_json()) == latency


def run_file(path: Path, rows: list[Row]) -> Path:
    doc = {"command": "python -m bench --only x", "created": "2025-01-01T00:00:00+00:00",
           "machine": {"cpus": 2, "python": "3.11", "zenoh": "1.10.2"},
           "benchmarks": {"x": {"rows": [r.to_json() for r in rows]}}}
    path.write_text(json.dumps(doc))
    return path


def report(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)}
    return subprocess.run([sys.executable, "-m", "bench", "report", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=60)


def test_report_check_exits_1_naming_the_missed_target(tmp_path: Path) -> None:
    rows = [row("raw_pubsub", 0.1), row("mesh_event", 0.2, baseline="raw_pubsub", ratio=2.0), row("act_one_client", 0.5)]
    done = report(str(run_file(tmp_path / "run.json", rows)), "--check")
    assert done.returncode == 1, done.stdout + done.stderr
    assert "MISSED mesh_event (event one-way): <= 1.3x: ratio 2.00x, missed" in done.stdout
    assert "met    act_one_client" in done.stdout
    assert "| event one-way (`mesh_event`) | 0.1 ms (p99 0.1) | 0.2 ms (p99 0.2) | 2.00x | <= 1.3x (issue 15) | **missed** |" \
        in done.stdout
    assert "| set request round trip (`mesh_set_property`) | - | - | - | <= 1.3x (issue 15) | not measured |" in done.stdout


def test_report_check_exits_0_when_every_measured_target_is_met(tmp_path: Path) -> None:
    done = report(str(run_file(tmp_path / "run.json", [row("act_one_client", 0.5)])), "--check")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "1 met, 0 missed" in done.stdout


def test_a_rows_baseline_is_the_one_of_its_own_benchmark(tmp_path: Path) -> None:
    core = [row("raw_get", 0.2), row("mesh_set_property", 0.26, baseline="raw_get", ratio=1.3)]
    doc = {"command": "c", "created": "d", "machine": {},
           "benchmarks": {"core": {"rows": [r.to_json() for r in core]}, "actions": {"rows": [row("raw_get", 0.9).to_json()]}}}
    path = tmp_path / "run.json"
    path.write_text(json.dumps(doc))
    rows, _ = tables.load([path])
    assert "| set request round trip (`mesh_set_property`) | 0.2 ms (p99 0.2) | 0.26 ms (p99 0.26) | 1.30x |" in tables.markdown(rows)


def test_a_later_run_replaces_an_earlier_ones_row(tmp_path: Path) -> None:
    first = run_file(tmp_path / "a.json", [row("act_one_client", 0.9)])
    second = run_file(tmp_path / "b.json", [row("act_one_client", 0.5)])
    assert report(str(first), str(second), "--check").returncode == 0
    assert report(str(second), str(first), "--check").returncode == 1


def test_report_refuses_a_file_that_is_not_a_run(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2]")
    done = report(str(bad))
    assert done.returncode == 2
    assert f"{bad}: not a benchmark run's JSON" in done.stderr


def test_the_readme_table_is_replaced_between_its_markers(tmp_path: Path) -> None:
    readme = tmp_path / "README.md"
    readme.write_text(f"# title\n\nbefore\n{tables.BEGIN}\nold table\n{tables.END}\nafter\n")
    tables.write_readme("| new |\n", readme)
    assert readme.read_text() == f"# title\n\nbefore\n{tables.BEGIN}\n| new |\n{tables.END}\nafter\n"
    readme.write_text("no markers\n")
    with pytest.raises(ValueError, match="markers"):
        tables.write_readme("| new |", readme)


def test_the_markdown_table_has_a_line_per_target() -> None:
    text = tables.markdown([], [Target("m", "a metric", "median <", 1.0, "issue 0", "ms")])
    assert text.splitlines()[2] == "| a metric (`m`) | - | - | - | < 1 ms (issue 0) | not measured |"
