"""eval/runs.py: the one completeness check, and lenient reading of result files."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dynslam_cli.errors import DynslamError
from dynslam_cli.eval import runs


def _run(root: Path, name: str, run_json) -> Path:
    d = root / name
    d.mkdir(parents=True)
    if run_json is not None:
        (d / "run.json").write_text(run_json if isinstance(run_json, str) else json.dumps(run_json))
    return d


@pytest.mark.parametrize("run_json, why", [
    ({"status": "running"}, "run.json status: running"),
    ({"status": "failed", "error": "boom"}, "run.json status: failed"),
    ({"status": "interrupted"}, "run.json status: interrupted"),
    ({"mode": "dynamic"}, "run.json status: None"),
    (None, "no run.json"),
    ("{broken", "run.json is corrupt"),
    ("[1, 2]", "run.json is corrupt"),
])
def test_incomplete_runs(tmp_path, run_json, why):
    d = _run(tmp_path, "r", run_json)
    reason = runs.incomplete_reason(d)
    assert reason == f"run {d} is not completed ({why}); pass --include-incomplete to use it anyway"
    assert runs.incomplete_reason(d, include_incomplete=True) is None
    with pytest.raises(DynslamError, match=why.replace("(", r"\(")):
        runs.require_completed(d)
    assert runs.require_completed(d, include_incomplete=True) == d
    assert not runs.is_finished(d)


def test_completed_and_missing(tmp_path):
    d = _run(tmp_path, "ok", {"status": "completed"})
    assert runs.incomplete_reason(d) is None and runs.require_completed(str(d)) == d
    assert not runs.is_finished(d)  # no ate.json yet
    (d / "ate.json").write_text("{}")
    assert runs.is_finished(d)
    missing = tmp_path / "nope"
    assert runs.incomplete_reason(missing, include_incomplete=True) == f"run folder not found: {missing}"
    with pytest.raises(DynslamError, match="run folder not found"):
        runs.require_completed(missing, include_incomplete=True)


def test_select_completed(tmp_path):
    ok = _run(tmp_path, "ok", {"status": "completed"})
    bad = _run(tmp_path, "bad", {"status": "failed"})
    keep, warnings = runs.select_completed([ok, bad])
    assert keep == [ok] and warnings == [f"skipped: {runs.incomplete_reason(bad)}"]
    assert runs.select_completed([ok, bad], include_incomplete=True) == ([ok, bad], [])
    with pytest.raises(DynslamError, match="run folder not found"):
        runs.select_completed([ok, tmp_path / "typo"])


@pytest.mark.parametrize("text, problem", [
    ('{"rmse_m": "abc"}', "'rmse_m' is not a number (\"abc\")"),
    ('{"rmse_m": true}', "'rmse_m' is not a number (true)"),
    ("[0.1, 0.2]", "expected a JSON object, got list"),
    ('"0.1"', "expected a JSON object, got str"),
    ("{broken", "not readable JSON"),
    ('{"median_ms": [1, 2]}', "'median_ms' is not an object of numbers"),
    ('{"median_ms": {"track": "x"}}', "'median_ms' is not an object of numbers"),
])
def test_read_result_json_problems(tmp_path, text, problem):
    p = tmp_path / "ate.json"
    p.write_text(text)
    data, why = runs.read_result_json(p, ("rmse_m",), ("median_ms",))
    assert data == {} and why.startswith(f"{p}: ") and problem in why and "\n" not in why


def test_read_result_json_good_and_absent(tmp_path):
    p = tmp_path / "ate.json"
    assert runs.read_result_json(p, ("rmse_m",)) == ({}, None)
    p.write_text('{"rmse_m": 0.5, "rmse_still_m": null, "median_ms": {"track": 3}, "other": "text"}')
    data, why = runs.read_result_json(p, ("rmse_m", "rmse_still_m"), ("median_ms",))
    assert why is None and data["rmse_m"] == 0.5 and data["other"] == "text"
