"""phrt validate / inspect / author through the CLI: exit codes, one-line errors, JSON."""

import json
import subprocess

import pytest
from pxr import Sdf, Usd, UsdGeom, UsdLux, UsdShade
from repo_paths import REPO
from scenes import clean_stage, cube_stage
from typer.testing import CliRunner

from phrt_usd.cli import app

runner = CliRunner()


@pytest.fixture()
def good(tmp_path):
    stage = clean_stage(tmp_path / "good.usda")
    stage.GetRootLayer().Save()
    return tmp_path / "good.usda"


def run(*args):
    result = runner.invoke(app, [str(a) for a in args])
    assert "Traceback" not in result.output + (result.stderr or "")
    assert result.exception is None or isinstance(result.exception, SystemExit)
    return result


def test_validate_clean_and_json(good):
    assert run("validate", good).exit_code == 0
    result = run("validate", good, "--json")
    data = json.loads(result.stdout)
    assert data == {
        "stage": str(good),
        "ok": True,
        "errors": [],
        "warnings": [],
        "reflectors": ["/World/Mirror"],
        "instanced_reflectors": [],
    }


def test_validate_bad_stage_exit_1_one_line_per_problem(tmp_path, good):
    stage = Usd.Stage.Open(str(good))
    stage.GetPrimAtPath("/World/Mirror").GetAttribute("phrt:priority").Set(-3.0)
    stage.GetPrimAtPath("/World/Render").GetAttribute("phrt:bounceLimit").Set(40)
    stage.GetRootLayer().Save()
    result = run("validate", good)
    assert result.exit_code == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 2
    assert lines[0].startswith("ERROR /World/Mirror.phrt:priority:")
    assert lines[1].startswith("ERROR /World/Render.phrt:bounceLimit:")
    data = json.loads(run("validate", good, "--json").stdout)
    assert data["ok"] is False and len(data["errors"]) == 2


@pytest.mark.parametrize("name", ["missing.usda", ".", "junk.usda"])
def test_unreadable_input_exit_2(tmp_path, name):
    (tmp_path / "junk.usda").write_text("not usd at all")
    for command in ("validate", "inspect"):
        result = run(command, tmp_path / name)
        assert result.exit_code == 2
        assert result.stderr.startswith("error: ") and len(result.stderr.splitlines()) == 1


@pytest.mark.slow
def test_real_subprocess_nonexistent():
    proc = subprocess.run(
        ["uv", "run", "phrt", "validate", "/nonexistent"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == "error: /nonexistent: no such file"


def test_inspect_json_and_passes(good):
    stage = Usd.Stage.Open(str(good))
    UsdLux.DistantLight.Define(stage, "/World/Sun")
    UsdLux.DomeLight.Define(stage, "/World/Sky")
    shader = UsdShade.Shader.Define(stage, "/World/Looks/Glass/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(0.3)
    stage.GetRootLayer().Save()
    data = json.loads(run("inspect", good, "--json").stdout)
    (refl,) = data["reflectors"]
    assert refl["path"] == "/World/Mirror" and refl["priority"] == 2.0
    assert refl["reflectivity"] == 0.5 and refl["triangles"] == 2
    assert refl["bounds"]["min"] == [0, 0, 0] and refl["bounds"]["max"] == [1, 1, 0]
    (path,) = data["camera_paths"]
    assert (path["camera"], path["start"], path["end"], path["control_points"]) == (
        "/World/Cam",
        1,
        24,
        2,
    )
    assert data["render_settings"]["settings_path"] == "/World/Render"
    assert data["passes"] == ["gbuffer", "shadows", "reflections", "refraction", "environment"]
    assert {(li["type"], li["path"]) for li in data["lights"]} == {
        ("DistantLight", "/World/Sun"),
        ("DomeLight", "/World/Sky"),
    }
    assert data["metadata"]["upAxis"] == "Y"


def test_inspect_table_and_minimal_passes(tmp_path):
    path = cube_stage(tmp_path / "plain.usda")
    result = run("inspect", path)
    assert result.exit_code == 0
    assert "Passes: gbuffer" in result.stdout
    assert json.loads(run("inspect", path, "--json").stdout)["passes"] == ["gbuffer"]


def test_author_cli(good, tmp_path):
    before = good.read_bytes()
    stage = Usd.Stage.Open(str(good))
    UsdGeom.Sphere.Define(stage, "/World/Ball")
    stage.GetRootLayer().Save()
    before = good.read_bytes()
    result = run("author", good, "/World/Ball", "--priority", "8")
    assert result.exit_code == 0, result.output
    assert good.read_bytes() == before
    overlay = tmp_path / "good.phrt.usda"
    data = json.loads(run("inspect", overlay, "--json").stdout)
    assert {r["path"]: r["priority"] for r in data["reflectors"]} == {
        "/World/Mirror": 2.0,
        "/World/Ball": 8.0,
    }
    bad = run("author", good, "/World/Cam", "--priority", "1", "--out", tmp_path / "x.usda")
    assert bad.exit_code == 1 and bad.stderr.startswith("error: /World/Cam: is a Camera")
    assert not (tmp_path / "x.usda").exists()
    assert good.read_bytes() == before


def _gl_out_of_memory() -> Exception:
    from OpenGL.error import GLError

    return GLError(err=0x0505, description=b"out of memory")  # GL_OUT_OF_MEMORY


@pytest.mark.parametrize("json_out", [False, True])
@pytest.mark.parametrize("error", [MemoryError, _gl_out_of_memory])
def test_probe_memory_error(good, tmp_path, monkeypatch, json_out, error):
    """Memory running out in a render (a large frame under a memory limit: numpy's
    MemoryError, or OpenGL's GL_OUT_OF_MEMORY from llvmpipe) is one line, or the one
    JSON object, saying so and where: the frame being rendered and the resolution;
    exit 1 as a failed render, no traceback."""
    from phrt_usd import api

    def out_of_memory(job, on_frame=None, stage_scene=None):
        on_frame(1, 2, None)  # the first frame finished, the second runs out
        raise error()

    monkeypatch.setattr(api, "run_render", out_of_memory)
    args = ["render", good, "--out", tmp_path / "run", "--frames", "1:2", "--resolution",
            "32x24", *(["--json"] if json_out else [])]  # fmt: skip
    result = run(*args)
    assert result.exit_code == 1, result.output
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    said = json.loads(result.stdout)["error"] if json_out else errors[0]
    assert len(errors) == (0 if json_out else 1), result.stderr  # warnings aside
    assert "memory ran out rendering frame 2 at 32x24 (1 of 2 frames finished" in said, said
