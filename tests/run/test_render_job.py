"""Render runs: interruption and resume, files always whole, CLI summary."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest
from pxr import Usd
from scenes import mirror_gallery_stage

from phrt_usd.api import run_render
from phrt_usd.engine.renderer import RenderOptions
from phrt_usd.run.frames import parse_frames
from phrt_usd.run.render_job import RenderJob
from phrt_usd.run.selection_layer import read_selection

#: Deterministic budget used by these tests: fits only some of the mirrors per frame.
BUDGET_RAYS = 600


def _phrt(*args: str, **kw) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "typer", "phrt_usd.cli", "run", *args]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, **kw)


def _selected_samples(layer: Path) -> dict[str, dict[float, bool]]:
    stage = Usd.Stage.Open(str(layer))
    out = {}
    for prim in stage.TraverseAll():
        attr = prim.GetAttribute("phrt:selected")
        if attr:
            out[str(prim.GetPath())] = {t: bool(attr.Get(t)) for t in attr.GetTimeSamples()}
    return out


def test_parse_frames():
    assert parse_frames("1:5", (0, 0)) == [1, 2, 3, 4, 5]
    assert parse_frames("1:10:4", (0, 0)) == [1, 5, 9]
    assert parse_frames(None, (3, 5)) == [3, 4, 5]
    assert parse_frames("7", (0, 0)) == [7]


@pytest.mark.slow
def test_sigint_then_resume_equals_uninterrupted(tmp_path, check_readable):
    stage = mirror_gallery_stage(tmp_path / "gallery.usda", frames=40)
    args = ["--frames", "1:40", "--budget-rays", str(BUDGET_RAYS), "--resolution", "64x48"]
    full = tmp_path / "full"
    done = subprocess.run(
        [sys.executable, "-m", "typer", "phrt_usd.cli", "run", "render", str(stage),
         "--out", str(full), *args, "--json"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr

    part = tmp_path / "part"
    proc = _phrt("render", str(stage), "--out", str(part), *args)
    checked = 0
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:
        checked += check_readable(part) if part.exists() else 0
        if len(list((part / "frames").glob("*.png"))) >= 20 if part.exists() else False:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err.decode()
    assert checked > 0
    times, _, _, _ = read_selection(part / "selection.usda")
    finished = len(list((part / "frames").glob("*.png")))
    assert 20 <= len(times) == finished < 40  # every finished frame is in the layer
    check_readable(part)

    resumed = subprocess.run(
        [sys.executable, "-m", "typer", "phrt_usd.cli", "run", "render", str(stage),
         "--out", str(part), *args, "--resume", "--json"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr
    assert _selected_samples(part / "selection.usda") == _selected_samples(full / "selection.usda")
    summary = json.loads(resumed.stdout)
    assert summary["frames"] == 40


@pytest.mark.slow
def test_render_summary_and_files(tmp_path):
    stage = mirror_gallery_stage(tmp_path / "gallery.usda", frames=6)
    job = RenderJob(
        stage_path=stage,
        out_dir=tmp_path / "run",
        options=RenderOptions(width=64, height=48, budget_ms=None, budget_rays=BUDGET_RAYS),
    )
    summary = run_render(job)
    for key in ("frames", "mean_fps", "median_frame_ms", "mean_selected", "transitions",
                "reflectors", "budget_ms", "budget_overruns"):  # fmt: skip
        assert key in summary, key
    assert summary["frames"] == 6 and summary["reflectors"] == 5
    assert "trace" in summary["passes"]
    stats = json.loads((tmp_path / "run" / "stats.json").read_text())
    assert len(stats["frames"]) == 6
    spec = oiio.ImageInput.open(str(tmp_path / "run" / "frames" / "0001.exr")).spec()
    names = list(spec.channelnames)
    assert names[:4] == ["R", "G", "B", "A"] and "Z" in names and "id" in names
    assert not list((tmp_path / "run").rglob(".*tmp*"))


@pytest.mark.slow
def test_resume_refuses_other_options(tmp_path):
    stage = mirror_gallery_stage(tmp_path / "gallery.usda", frames=3)
    opts = RenderOptions(width=32, height=24, budget_ms=None, budget_rays=BUDGET_RAYS)
    run_render(RenderJob(stage_path=stage, out_dir=tmp_path / "r", options=opts))
    other = RenderOptions(width=32, height=24, budget_ms=None, budget_rays=BUDGET_RAYS + 1)
    from phrt_usd.errors import PhrtError

    with pytest.raises(PhrtError, match="budget_rays"):
        run_render(RenderJob(stage_path=stage, out_dir=tmp_path / "r", options=other, resume=True))


@pytest.mark.slow
def test_raster_run_casts_no_rays(tmp_path):
    stage = mirror_gallery_stage(tmp_path / "gallery.usda", frames=2)
    opts = RenderOptions(mode="raster", width=32, height=24)
    summary = run_render(RenderJob(stage_path=stage, out_dir=tmp_path / "r", options=opts))
    assert "trace" not in summary["passes"]
    stats = json.loads((tmp_path / "r" / "stats.json").read_text())
    assert all(f["rays"] == 0 for f in stats["frames"])
    assert np.isfinite(summary["median_frame_ms"])


@pytest.mark.slow
def test_probe_frames_closer_than_a_thousandth(tmp_path):
    """Frames whose time codes round to the same 1/1000 (the precision of file names)
    would overwrite each other's images: refused with exit 2 before any frame renders, in
    one line naming both frames; frames 1/1000 apart each get their own files."""
    stage = mirror_gallery_stage(tmp_path / "gallery.usda", frames=2)
    out = tmp_path / "close"
    for frames, shown in (("1.0001,1.0002", ("1.0001", "1.0002")),
                          ("1,1.0000001", ("frames 1 ", "1.0000001"))):  # fmt: skip
        done = subprocess.run(
            [sys.executable, "-m", "typer", "phrt_usd.cli", "run", "render", str(stage),
             "--out", str(out), "--frames", frames, "--resolution", "32x24",
             "--budget-rays", str(BUDGET_RAYS)],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert done.returncode == 2, done.stderr
        errors = [line for line in done.stderr.splitlines() if line.startswith("error:")]
        assert len(errors) == 1 and "Traceback" not in done.stderr, done.stderr
        assert all(part in errors[0] for part in shown), errors[0]
        assert not out.exists()  # refused before the run directory was even made
    opts = RenderOptions(width=32, height=24, budget_ms=None, budget_rays=BUDGET_RAYS)
    apart = tmp_path / "apart"
    run_render(RenderJob(stage_path=stage, out_dir=apart, options=opts, frames="1:1.002x0.001"))
    assert sorted(p.name for p in (apart / "frames").glob("*.exr")) == [
        "0001.001.exr", "0001.002.exr", "0001.exr"]  # fmt: skip


def test_parse_frames_takes_usd_frame_specs():
    """USD's FrameSpec (as usdrecord takes it): strides, counting down, comma lists;
    rendered once each in increasing time order."""
    assert parse_frames("101:109x2", (0, 0)) == [101, 103, 105, 107, 109]
    assert parse_frames("10:1x-2", (0, 0)) == [2, 4, 6, 8, 10]
    assert parse_frames("1:3,10,20:30x5,2", (0, 0)) == [1, 2, 3, 10, 20, 25, 30]
    assert parse_frames("1:2x0.5", (0, 0)) == [1, 1.5, 2]
