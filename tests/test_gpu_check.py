"""`tools/gpu_check.sh all`: the control flow of the one GPU command, with a stand-in for PYTHON that
records what it is asked (a lent GPU gets one try at it, so the time sharing and the exit codes are
tested here): the ablation gets what LIMIT_S leaves after the tests, a failed test cancels neither the
bench nor the ablation, and too little time left starts no ablation."""

import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# the stand-in: `-c` prints the versions line; `-m` calls are recorded by their first three words; pytest
# exits with TESTS_RC; the ablation writes a row in its --out folder and records the `timeout` that runs it
# (its parent's command line)
PYTHON = """#!/usr/bin/env bash
[ "$1" = -c ] && echo "3.12 torch stand-in" && exit
echo "$1 $2 $3" >> "$CALLS"
case "$1 $2 $3" in
"-m pytest "*) exit "${TESTS_RC:-0}" ;;
*"cli.main ablation")
    tr '\\0' ' ' < /proc/$PPID/cmdline >> "$CALLS" && echo >> "$CALLS"
    while [ "$1" != --out ]; do shift; done
    mkdir -p "$2/row" && echo '{}' > "$2/row/row.json" ;;
esac
"""


def gpu_check(tmp_path, stage, **env):
    py = tmp_path / "python"
    py.write_text(PYTHON)
    py.chmod(0o755)
    calls = tmp_path / "calls"
    run = subprocess.run(
        ["bash", str(ROOT / "tools/gpu_check.sh"), stage, str(tmp_path / "out"), str(tmp_path / "data")],
        env={**os.environ, "PYTHON": str(py), "CALLS": str(calls), **env}, capture_output=True, text=True,
        check=False)
    return run, calls.read_text().splitlines() if calls.exists() else []


@pytest.mark.parametrize("tests_rc", [0, 1])
def test_all_runs_both_stages_and_exits_with_the_first_failure(tmp_path, tests_rc):
    run, calls = gpu_check(tmp_path, "all", LIMIT_S="300", TESTS_RC=str(tests_rc))
    assert run.returncode == tests_rc, run.stderr
    assert "-m pytest -q" in calls and "-m ragsplat.cli.main bench" in calls
    # the ablation ran under what was left of the 300 s (the stand-in's tests take about no time)
    limit = next(int(c.split()[1]) for c in calls if c.startswith("timeout"))
    assert 290 <= limit <= 300
    assert "--no-geotiffs" in next(c for c in calls if c.startswith("timeout"))  # no rasterio there
    out = tmp_path / "out"
    assert {"tests.log", "ablation.log", "rows.tar.gz"} <= {p.name for p in out.iterdir()}
    assert "ablation: " in (out / "ablation.log").read_text()


def test_all_starts_no_ablation_without_a_minute_left(tmp_path):
    run, calls = gpu_check(tmp_path, "all", LIMIT_S="59")
    assert run.returncode == 124
    assert "the ablation is not started" in run.stderr
    assert "-m ragsplat.cli.main ablation" not in calls
    # a failed test's exit code wins over the lack of time
    run, _ = gpu_check(tmp_path, "all", LIMIT_S="59", TESTS_RC="1")
    assert run.returncode == 1
