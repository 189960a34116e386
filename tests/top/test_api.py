"""The Python API: phrt_usd.render / phrt_usd.open, the options the CLI shares with it,
and a cheap `import phrt_usd`."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from pxr import Sdf, Usd
from scenes import mirror_gallery_stage
from typer.testing import CliRunner

import phrt_usd
from phrt_usd.api import render_options
from phrt_usd.cli import app
from phrt_usd.errors import BadOption, PhrtError

#: The render --json fields docs/design.md §2 promises (and RenderResult.summary holds).
SUMMARY_KEYS = (
    "frames",
    "mean_fps",
    "median_frame_ms",
    "mean_selected",
    "transitions",
    "reflectors",
    "budget_ms",
    "budget_overruns",
)
#: A rays budget: the same selections on every machine (the gallery's mirrors need
#: ~300-900 rays each at 64x48).
RAYS = 2000


@pytest.fixture(scope="module")
def gallery(tmp_path_factory):
    """Five mirrors on a 6-frame camera path, 64x48, render settings budget 1000 ms."""
    return mirror_gallery_stage(tmp_path_factory.mktemp("gallery") / "gallery.usda", frames=6)


@pytest.mark.slow
def test_render_returns_summary_frames_and_images(gallery, tmp_path):
    out = tmp_path / "out"
    result = phrt_usd.render(gallery, out, frames="1:4", budget_rays=RAYS)
    assert set(SUMMARY_KEYS) <= set(result.summary)
    assert result.summary["frames"] == 4 and result.summary["reflectors"] == 5
    assert result.summary["out"] == str(out) and result.out == out
    assert result.summary["mean_selected"] > 0  # the budget traces some mirrors
    assert result.summary["kernels"] in ("cached", "compiled")  # how the kernels ran
    assert [f.time for f in result.frames] == [1.0, 2.0, 3.0, 4.0]
    assert all(f.rays <= RAYS for f in result.frames)
    assert result.selection_layer == out / "selection.usda" and result.selection_layer.is_file()
    assert [i.time for i in result.images] == [1.0, 2.0, 3.0, 4.0]
    assert all(path.is_file() for i in result.images for path in i.files)
    assert result.image(3).exr.is_file() and result.image(3).png.is_file()
    frame = result.read_frame(3)
    assert frame["beauty"].shape == (48, 64, 3) and np.isfinite(frame["beauty"]).all()
    assert frame["traced_mask"].any() == bool(result.frames[2].selected)
    assert not result.temporary
    with pytest.raises(PhrtError, match="no frame at time code 7"):
        result.image(7)


@pytest.mark.slow
def test_cli_render_is_the_api_render(gallery, tmp_path):
    """The same options through `phrt render --json` and phrt_usd.render give the same
    run (a rays budget makes the selections deterministic)."""
    api = phrt_usd.render(gallery, tmp_path / "api", frames="2:5", budget_rays=RAYS).summary
    cli = CliRunner().invoke(
        app,
        ["render", str(gallery), "-o", str(tmp_path / "cli"), "--frames", "2:5"]
        + ["--budget-rays", str(RAYS), "--json"],
    )
    assert cli.exit_code == 0, cli.output
    summary = json.loads(cli.stdout)
    for key in ("frames", "mean_selected", "transitions", "reflectors", "budget_ms", "passes"):
        assert summary[key] == api[key], key
    assert set(api) <= set(summary)


@pytest.mark.slow
def test_probe_summary_finished_twice(gallery, tmp_path):
    """The API finishes a render's summary once: run_render (what `phrt render` calls)
    gives the fields RenderResult.summary has, the stage's warnings, default light rig and
    support report included."""
    from phrt_usd.api import render_job, run_render

    job, _ = render_job(gallery, tmp_path / "job", "1:2", budget_rays=RAYS)
    summary = run_render(job)  # no stage read given: run_render reads it
    result = phrt_usd.render(gallery, tmp_path / "api", frames="1:2", budget_rays=RAYS)
    assert set(summary) == set(result.summary)
    for key in ("warnings", "default_light_rig", "support"):
        assert summary[key] == result.summary[key], key


def test_probe_cli_render_only_prints_the_api_summary(gallery, tmp_path, monkeypatch):
    """`phrt render --json` prints the summary run_render returns, as it is: the command
    parses, calls and prints, and adds nothing of its own."""
    from phrt_usd import api

    finished = {"frames": 0, "out": str(tmp_path / "cli"), "selection_layer": "s.usda",
                "warnings": [], "only_the_api_knows": 1}  # fmt: skip
    monkeypatch.setattr(api, "run_render", lambda job, **_: dict(finished))
    cli = CliRunner().invoke(app, ["render", str(gallery), "-o", finished["out"], "--json"])
    assert cli.exit_code == 0, cli.output
    assert json.loads(cli.stdout) == finished


@pytest.mark.slow
def test_cli_render_hands_the_cluster_options_to_run_render(gallery, tmp_path, monkeypatch):
    """`phrt render --workers N` passes the cluster options to run_render as they were
    given (the API runs the cluster and finishes the summary); none without them."""
    from phrt_usd import api

    calls = []

    def fake(job, on_frame=None, stage_scene=None, **cluster):
        calls.append(cluster)
        return {"warnings": [], "out": str(job.out_dir), "selection_layer": "s.usda"}

    monkeypatch.setattr(api, "run_render", fake)
    base = ["render", str(gallery), "--json", "-o"]
    plain = CliRunner().invoke(app, [*base, str(tmp_path / "a")])
    chunked = CliRunner().invoke(app, [*base, str(tmp_path / "b"), "--workers", "1",
                                       "--chunk-frames", "2"])  # fmt: skip
    assert plain.exit_code == 0 and chunked.exit_code == 0, (plain.output, chunked.output)
    assert calls == [{}, {"workers": 1, "chunk_frames": 2}]


@pytest.mark.slow
def test_run_render_on_a_cluster_gives_the_same_finished_summary(gallery, tmp_path):
    """run_render on a one-worker local cluster (chunks of 2 frames, no warm-up) finishes
    its summary as a one-process run does: the same fields (the cluster adds its chunks'
    worker processes), the same frames, selections, stage facts and warnings."""
    from phrt_usd.api import render_job, run_render

    job, scene = render_job(gallery, tmp_path / "one", "1:4", budget_rays=RAYS)
    single = run_render(job, stage_scene=scene)
    job, scene = render_job(gallery, tmp_path / "many", "1:4", budget_rays=RAYS)
    chunked = run_render(job, stage_scene=scene, workers=1, chunk_frames=2, warmup=0)
    assert set(chunked) == set(single) | {"chunk_pids"}
    for key in ("frames", "mean_selected", "reflectors", "support", "default_light_rig"):
        assert chunked[key] == single[key], key
    # Every warning of the one-process run, and those the workers found while rendering
    # (each chunk warns of its own first clipped frame).
    assert set(single["warnings"]) <= set(chunked["warnings"])


@pytest.mark.slow
def test_out_none_renders_into_a_temporary_directory_the_result_owns(gallery):
    with phrt_usd.render(gallery, frames=2, budget_rays=RAYS, write_images=False) as result:
        assert result.temporary and result.out.is_dir()
        assert result.summary["frames"] == 1 and result.images == ()
        with pytest.raises(PhrtError, match="no images"):
            result.read_frame()
    assert not result.out.exists()


@pytest.mark.slow
def test_an_open_stage_renders_as_it_is_in_memory(gallery):
    stage = Usd.Stage.Open(str(gallery))
    for i in range(5):  # unsaved edits: no mirrors left
        stage.GetPrimAtPath(f"/World/Mirror{i}").SetActive(False)
    with phrt_usd.render(stage, frames=[1, 3], budget_rays=RAYS) as result:
        assert result.summary["reflectors"] == 0 and result.summary["frames"] == 2
        assert result.frames[0].selected == []
    assert stage.GetRootLayer().dirty  # the API never saved the caller's stage


@pytest.mark.slow
def test_session_layers_apply_to_a_stage_file(gallery, tmp_path):
    layer = Sdf.Layer.CreateNew(str(tmp_path / "no_mirrors.usda"))
    for i in range(5):
        Sdf.CreatePrimInLayer(layer, f"/World/Mirror{i}").active = False
    layer.Save()
    with phrt_usd.render(gallery, frames=1, session_layers=layer.realPath) as result:
        assert result.summary["reflectors"] == 0
    with pytest.raises(BadOption, match="already composed"):
        phrt_usd.render(Usd.Stage.Open(str(gallery)), session_layers=[layer.realPath])


def test_open_renders_frames_and_closes(gallery):
    with phrt_usd.open(gallery, budget_rays=RAYS, resolution=(32, 24)) as renderer:
        assert renderer.frames == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]  # planned: the stage's path
        first = renderer.render(1)
        third = renderer.render(3)
        assert third.beauty.shape == (24, 32, 3) and third.gbuffer.element_id.shape == (24, 32)
        assert np.isfinite(first.beauty).all() and third.stats.time == 3.0
        assert third.stats.rays <= RAYS
    assert renderer.closed
    with pytest.raises(PhrtError, match="closed"):
        renderer.render(1)
    renderer.close()  # closing twice is harmless


def test_render_options_read_the_stage_and_apply_overrides(gallery):
    stage = Usd.Stage.Open(str(gallery))
    options = render_options(stage)
    assert (options.width, options.height, options.budget_ms) == (64, 48, 1000.0)
    assert options.budget_rays is None
    rays = render_options(stage, budget_rays=500)
    assert (rays.budget_rays, rays.budget_ms) == (500, None)  # rays alone: deterministic
    assert render_options(stage, budget_ms=math.inf).budget_ms is None  # inf: unbounded
    both = render_options(stage, budget_ms=5, budget_rays=500)
    assert (both.budget_ms, both.budget_rays) == (5.0, 500)
    small = render_options(stage, resolution="32x24", mode="raster", heuristic=None)
    assert (small.width, small.height, small.mode, small.heuristic) == (32, 24, "raster", "heu1")


BAD_OPTIONS = [
    ({"mode": "fast"}, "unknown mode"),
    ({"heuristic": "best"}, "unknown heuristic"),
    ({"budget_rays": -1}, "budget-rays"),
    ({"budget_ms": "10"}, "budget_ms must be a number"),
    ({"budget_ms": -1.0}, "budget-ms"),
    ({"bounce_limit": 2.5}, "bounce_limit must be an integer"),
    ({"selection_weight": math.nan}, "selection_weight"),
    ({"resolution": "big"}, "expected WxH"),
    ({"resolution": (64, 48), "width": 64}, "not both"),
    ({"threads": 0}, r"threads must be in 1\.\.1024, got 0"),
    ({"bogus": 1}, "unknown option 'bogus'"),
]


@pytest.mark.parametrize("options,message", BAD_OPTIONS, ids=lambda v: str(v)[:30])
def test_bad_options_raise_bad_option_before_anything_is_written(
    gallery, tmp_path, options, message
):
    out = tmp_path / "out"
    with pytest.raises(BadOption, match=message) as error:
        phrt_usd.render(gallery, out, **options)
    assert "\n" not in str(error.value) and not out.exists()
    with pytest.raises(BadOption, match=message):
        phrt_usd.open(gallery, **options).close()


@pytest.mark.parametrize(
    "options,message",
    [
        ({"resume": "yes"}, "resume must be True or False"),
        ({"frames": "x:y"}, "--frames"),
        ({"frames": [1.0, math.inf]}, "finite"),
        ({"frames": {}}, "frames must be"),
        ({"selection_layer": 3}, "selection_layer must be a path"),
    ],
    ids=lambda v: str(v)[:30],
)
def test_bad_job_options_raise_bad_option(gallery, tmp_path, options, message):
    with pytest.raises(BadOption, match=message):
        phrt_usd.render(gallery, tmp_path / "out", **options)
    assert not (tmp_path / "out").exists()


def test_bad_input_is_one_line_phrt_error(tmp_path):
    with pytest.raises(PhrtError, match="no such file") as error:
        phrt_usd.render(tmp_path / "missing.usda")
    assert "\n" not in str(error.value)
    with pytest.raises(BadOption, match="Usd.Stage"):
        phrt_usd.open(42)


@pytest.mark.slow
def test_import_phrt_usd_loads_neither_the_api_nor_opengl():
    """The CLI imports phrt_usd first: the API (and GL, Embree) load on first use only.
    ``phrt_usd.render`` is plainly the API function (the renderer is ``phrt_usd.engine``)."""
    code = (
        "import sys, phrt_usd\n"
        "heavy = ('phrt_usd.api', 'OpenGL', 'pyrender', 'embreex')\n"
        "print([m for m in heavy if m in sys.modules])\n"
        "assert 'render' in dir(phrt_usd) and 'phrt_usd.api' not in sys.modules\n"
        "print(phrt_usd.render.__module__, 'phrt_usd.api' in sys.modules)\n"
    )
    lines = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.split("\n")
    assert lines[0] == "[]"
    assert lines[1] == "phrt_usd.api True"
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        phrt_usd.nope  # noqa: B018
