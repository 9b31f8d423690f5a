"""The benchmarks still run: ``python -m bench --quick`` on the cheap parts and a short soak.

No timing is asserted (the figures depend on the machine and its load): only that the runs
complete, exit 0 (no correctness check failed: nothing lost, one companion) and write their JSON.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def bench(*args: str, timeout: float) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)}
    return subprocess.run([sys.executable, "-m", "bench", *args], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=timeout)


# Two halves and the soak as three tests: each half runs a few seconds, and the suite's two
# workers share them instead of one worker running all at its end.
QUICK = ("core,actions,mindproto,eventcpu", "discovery,idle,migration,llm")


@pytest.mark.timeout(240)
@pytest.mark.parametrize("only", QUICK)
def test_quick_benchmarks(tmp_path: Path, only: str) -> None:
    out = tmp_path / "quick.json"
    result = bench("--quick", "--only", only, "--json", str(out), timeout=200)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    doc = json.loads(out.read_text())
    assert set(doc["benchmarks"]) == set(only.split(","))
    for name, run in doc["benchmarks"].items():
        assert run["rows"], name
        assert all(row["n"] > 0 and not row["failures"] for row in run["rows"]), name
    if "migration" in doc["benchmarks"]:  # the bare handshake ran beside it, in the same run
        metrics = {row["metric"] for row in doc["benchmarks"]["migration"]["rows"]}
        assert {"migration_floor_10kib", "migration_10kib_vs_floor", "migration_floor_10mib", "migration_10kib_aged"} <= metrics


@pytest.mark.timeout(240)
def test_short_soak(tmp_path: Path) -> None:
    soak = tmp_path / "soak.json"
    result = bench("soak", "--seconds", "5", "--json", str(soak), timeout=120)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    rows = json.loads(soak.read_text())["benchmarks"]["soak"]["rows"]
    assert {row["metric"] for row in rows} >= {"soak_migrations", "soak_actions", "soak_writes", "soak_events", "soak_inhabitants"}
    assert all(not row["failures"] for row in rows)
