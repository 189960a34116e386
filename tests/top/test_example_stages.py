"""The committed example stages through the CLI: clean paper stages, planted problems."""

from __future__ import annotations

import json

import pytest
from repo_paths import STAGES
from typer.testing import CliRunner

from phrt_usd.cli import app

runner = CliRunner()

#: stage → the prim.attribute every error line of `phrt validate` must name.
PLANTED = {
    "zero_area_reflector": ("/World/ZeroAreaMirror.points", "WARNING"),
    "degenerate_reflector": ("/World/BrokenMirror.faceVertex", "ERROR"),
    "nan_points": ("/World/NanMirror.points", "ERROR"),
    "negative_priority": ("/World/Mirror.phrt:priority", "ERROR"),
}


@pytest.mark.slow
@pytest.mark.parametrize("name,reflectors", [("farm", 17), ("sewer", 33)])
def test_paper_stage_validates_and_inspects(name, reflectors):
    path = str(STAGES / f"{name}.usda")
    result = runner.invoke(app, ["validate", path])
    assert result.exit_code == 0, result.output
    result = runner.invoke(app, ["inspect", "--json", path])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert len(summary["reflectors"]) == reflectors
    assert {"gbuffer", "reflections"} <= set(summary["passes"])


@pytest.mark.slow
@pytest.mark.parametrize("path", sorted((STAGES / "extreme").glob("*.usda")), ids=lambda p: p.stem)
def test_extreme_stage_reports_exactly_its_planted_problem(path):
    result = runner.invoke(app, ["validate", "--json", str(path)])
    report = json.loads(result.stdout)
    lines = [*report["errors"], *report["warnings"]]
    if path.stem not in PLANTED:
        assert result.exit_code == 0 and not lines, lines
        return
    where, severity = PLANTED[path.stem]
    assert lines and all(where in json.dumps(line) for line in lines), lines
    assert result.exit_code == (1 if severity == "ERROR" else 0)
