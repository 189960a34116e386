"""provenance: what a sweep or benchmark records never fails it, and says "unknown" for
what it cannot find (an installed copy has no commit; a machine without git)."""

from __future__ import annotations

import json

import pytest
from repo_paths import REPO

import phrt_usd
from phrt_usd import base
from phrt_usd.evaluate import provenance


def test_commit_is_unknown_for_an_installed_copy(monkeypatch, tmp_path):
    """A package under site-packages (no checkout around it) has no commit to give, and a
    repository of another project that holds the package at its top (no phrt-usd
    pyproject.toml there) does not give its commit as phrt's."""
    installed = tmp_path / "venv" / "lib" / "site-packages" / "phrt_usd"
    installed.mkdir(parents=True)
    monkeypatch.setattr(base, "__file__", str(installed / "base.py"))
    assert provenance.source_commit() == ("unknown", None)
    (installed.parent / ".git").mkdir()  # a pipeline's repository, not phrt's
    assert provenance.source_commit() == ("unknown", None)


def test_commit_is_unknown_without_git(monkeypatch):
    """No git on PATH: "unknown", no exception."""
    monkeypatch.setenv("PATH", "")
    assert provenance.source_commit() == ("unknown", None)


def test_commit_of_the_checkout(monkeypatch):
    """Run from this checkout: the 40-hex-digit commit of HEAD."""
    if not (REPO / ".git").exists():
        return  # a copy without git metadata: the test above covers it
    commit, dirty = provenance.source_commit()
    assert len(commit) == 40 and set(commit) <= set("0123456789abcdef")
    assert dirty in (True, False)


def test_record_is_json_and_its_line_is_one_line():
    record = provenance.collect(threads=2, gl="osmesa", argv=["/usr/bin/phrt", "sweep", "a b"])
    assert json.loads(json.dumps(record, allow_nan=False)) == record
    assert record["command"] == "phrt sweep 'a b'"  # shell-quoted, the program by name
    assert record["threads"]["setting"] == 2 and record["gl"]["requested"] == "osmesa"
    line = provenance.provenance_line(record)
    assert "\n" not in line and line.startswith(f"provenance: phrt {phrt_usd.__version__}")
    assert "px per degree" in line and "cores" in line


@pytest.mark.slow
def test_benchmark_tool_prints_its_provenance_first(tmp_path, capsys):
    """tools/bench.py on a tiny stage: its output starts with the provenance line (the
    command as run, the machine) before its table."""
    import sys

    from scenes import mirror_gallery_stage

    sys.path.insert(0, str(REPO / "tools"))
    try:
        import bench
    finally:
        sys.path.remove(str(REPO / "tools"))
    stage = mirror_gallery_stage(tmp_path / "tiny.usda", frames=2)
    args = [str(stage), "--resolutions", "32x24", "--frames", "1:2"]
    assert bench.main(args) == 0
    first, _blank, table = capsys.readouterr().out.partition("\n\n")
    assert first.startswith("provenance: phrt ") and "\n" not in first
    assert f"command python tools/bench.py {' '.join(args)};" in first
    assert table.startswith("| stage |")
