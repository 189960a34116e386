"""Corrupted run files: ``--resume`` and ``report`` either work or refuse with one line.

A good run directory is rendered once; hypothesis then corrupts one of its files (bytes
flipped, cut short, or a JSON value replaced by any other JSON) and the readers must
either accept it or raise ``PhrtError`` — never another exception (which the CLI would
show as a traceback). The CLI checks at the end confirm the one-line, exit-code side.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scenes import mirror_gallery_stage

from phrt_usd.api import run_render
from phrt_usd.engine.renderer import RenderOptions
from phrt_usd.errors import PhrtError
from phrt_usd.evaluate.report import build_report
from phrt_usd.run.frames import parse_frames
from phrt_usd.run.render_job import RenderJob, _load_checkpoint, job_run_info
from phrt_usd.run.run_files import CHECKPOINT_FILE
from phrt_usd.select.policies import make_policy
from phrt_usd.usd.stage import open_stage

OPTIONS = RenderOptions(width=32, height=24, budget_ms=None, budget_rays=600)
#: Examples per file kind: each is a parse of a small file, so a few hundred stay quick.
EXAMPLES = 150

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner,
                                                                 max_size=4),  # fmt: skip
    max_leaves=12,
)


@pytest.fixture(scope="module")
def good_run(tmp_path_factory):
    """(run directory, run_info) of a finished 3-frame render."""
    root = tmp_path_factory.mktemp("fuzz")
    stage = mirror_gallery_stage(root / "gallery.usda", frames=3)
    job = RenderJob(stage_path=stage, out_dir=root / "run", options=OPTIONS, frames="1:3")
    run_render(job)
    scene = open_stage(stage)
    return job.out_dir, job_run_info(job, scene, parse_frames("1:3", scene.frame_range))


def _corrupt_bytes(data: bytes, draw) -> bytes:
    kind = draw(st.sampled_from(["flip", "cut", "insert"]))
    at = draw(st.integers(0, max(len(data) - 1, 0)))
    if kind == "cut":
        return data[:at]
    junk = draw(st.binary(min_size=1, max_size=16))
    if kind == "insert":
        return data[:at] + junk + data[at:]
    return data[:at] + junk + data[at + len(junk) :]


def _replace_json_value(document, draw):
    """``document`` with one value somewhere inside replaced by any JSON value."""
    if not isinstance(document, dict | list) or not document or draw(st.booleans()):
        return draw(json_values)
    if isinstance(document, dict):
        key = draw(st.sampled_from(sorted(document)))
        return {**document, key: _replace_json_value(document[key], draw)}
    i = draw(st.integers(0, len(document) - 1))
    return [*document[:i], _replace_json_value(document[i], draw), *document[i + 1 :]]


def _corrupted(path: Path, draw) -> bytes:
    data = path.read_bytes()
    if path.suffix == ".json" and draw(st.booleans()):
        return json.dumps(_replace_json_value(json.loads(data), draw)).encode()
    return _corrupt_bytes(data, draw)


def _readers_refuse_or_accept(call) -> None:
    try:
        call()
    except PhrtError as error:
        assert "\n" not in str(error).strip(), str(error)


@pytest.mark.slow
@settings(max_examples=EXAMPLES, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
@given(data=st.data())
def test_corrupted_checkpoint_resumes_or_is_refused(good_run, tmp_path, data):
    out, run_info = good_run
    (tmp_path / CHECKPOINT_FILE).write_bytes(_corrupted(out / CHECKPOINT_FILE, data.draw))
    renderer = SimpleNamespace(policy=make_policy("heu1", selection_weight=1.0, bounce_limit=5))
    _readers_refuse_or_accept(lambda: _load_checkpoint(tmp_path, run_info, renderer))


@pytest.mark.slow
@settings(max_examples=EXAMPLES, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
@given(data=st.data(), name=st.sampled_from(["stats.json", "selection.usda"]))
def test_corrupted_stats_or_selection_layer_report_or_refuse(good_run, tmp_path, data, name):
    out, _ = good_run
    run = tmp_path / "run"
    shutil.rmtree(run, ignore_errors=True)
    run.mkdir()
    for file in ("stats.json", "selection.usda"):
        shutil.copy(out / file, run / file)
    (run / name).write_bytes(_corrupted(out / name, data.draw))
    _readers_refuse_or_accept(lambda: build_report(run))


@pytest.mark.slow
@pytest.mark.parametrize("name", [CHECKPOINT_FILE, "stats.json", "selection.usda"])
def test_cli_on_a_corrupted_run_is_one_line(good_run, tmp_path, name):
    out, run_info = good_run
    run = tmp_path / "run"
    shutil.copytree(out, run)
    (run / name).write_bytes((run / name).read_bytes()[:40] + b"\x00garbage")
    cli = [sys.executable, "-m", "typer", "phrt_usd.cli", "run"]
    for args in (["report", str(run)], ["report", str(run), "--json"]):
        done = subprocess.run([*cli, *args], capture_output=True, text=True, timeout=120)
        assert done.returncode in (0, 2), done.stderr
        assert "Traceback" not in done.stderr
    stage = run_info["stage"]
    done = subprocess.run([*cli, "render", stage, "--out", str(run), "--frames", "1:3",
                           "--budget-rays", "600", "--resolution", "32x24", "--resume"],
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert "Traceback" not in done.stderr
    if name == CHECKPOINT_FILE:
        assert done.returncode == 1 and done.stderr.count("error:") == 1, done.stderr
