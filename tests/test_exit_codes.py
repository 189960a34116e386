"""Every command's exit codes as the CLI documents them: 0 ok, 1 problems found or render
failed, 2 bad option or unreadable input (130, interrupted, is in test_render_job). Each
refusal is one line on stderr, or with ``--json`` one JSON object with ``error`` and
``code`` on stdout; never a traceback."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from pxr import Usd
from scenes import cube_stage, mirror_gallery_stage

CLI = [sys.executable, "-m", "typer", "phrt_usd.cli", "run"]
RENDER = ["--frames", "1:2", "--budget-rays", "600", "--resolution", "32x24"]


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("codes")
    good = mirror_gallery_stage(root / "gallery.usda", frames=2)
    garbage = root / "garbage.usda"
    garbage.write_bytes(b"\x00\x01 not usd at all")
    problems = root / "problems.usda"  # readable, but a reflector K below 0
    stage = Usd.Stage.Open(str(good))
    reflector = next(p for p in stage.Traverse() if p.HasAPI("PhrtReflectorAPI"))
    reflector.GetAttribute("phrt:priority").Set(-1.0)
    stage.GetRootLayer().Export(str(problems))
    run = root / "run"
    done = _run("render", str(good), "--out", str(run), *RENDER)
    assert done.returncode == 0, done.stderr
    return {"good": good, "garbage": garbage, "missing": root / "missing.usda",
            "problems": problems, "run": run, "root": root}  # fmt: skip


def _check(done: subprocess.CompletedProcess, code: int, json_out: bool = False) -> None:
    assert done.returncode == code, (done.returncode, done.stdout[-500:], done.stderr[-2000:])
    assert "Traceback" not in done.stderr
    if code in (1, 2) and json_out:
        error = json.loads(done.stdout)
        assert error["code"] == code and error["error"]
    elif code == 2 or (code == 1 and "error:" in done.stderr):
        assert done.stderr.count("error:") == 1, done.stderr


@pytest.mark.parametrize("json_out", [False, True])
def test_validate(files, json_out):
    flag = ["--json"] if json_out else []
    _check(_run("validate", str(files["good"]), *flag), 0)
    done = _run("validate", str(files["problems"]), *flag)
    assert done.returncode == 1 and "Traceback" not in done.stderr
    _check(_run("validate", str(files["garbage"]), *flag), 2, json_out)
    _check(_run("validate", str(files["missing"]), *flag), 2, json_out)


@pytest.mark.parametrize("json_out", [False, True])
def test_inspect(files, json_out):
    flag = ["--json"] if json_out else []
    _check(_run("inspect", str(files["good"]), *flag), 0)
    _check(_run("inspect", str(files["garbage"]), *flag), 2, json_out)
    _check(_run("inspect", str(files["root"]), *flag), 2, json_out)  # a directory


@pytest.mark.parametrize("json_out", [False, True])
def test_render(files, tmp_path, json_out):
    flag = ["--json"] if json_out else []
    _check(_run("render", str(files["good"]), "--out", str(tmp_path / "a"), *RENDER, *flag), 0)
    # A stage without camera renders with a default one; a readable stage the render
    # refuses, with neither camera nor geometry (problems found -> 1).
    no_camera = cube_stage(tmp_path / "no_camera.usda")
    _check(_run("render", str(no_camera), "--out", str(tmp_path / "b0"), *RENDER, *flag), 0)
    empty = tmp_path / "empty.usda"
    Usd.Stage.CreateNew(str(empty)).Save()
    _check(_run("render", str(empty), "--out", str(tmp_path / "b"), *flag), 1, json_out)
    _check(_run("render", str(files["missing"]), "--out", str(tmp_path / "c"), *flag), 2,
           json_out)  # fmt: skip
    _check(_run("render", str(files["good"]), "--out", str(tmp_path / "d"), "--budget-rays",
                "-5", *flag), 2, json_out)  # fmt: skip
    # Refusing a non-empty OUT is a problem with the run, not a bad value: 1.
    _check(_run("render", str(files["good"]), "--out", str(files["run"]), *RENDER, *flag), 1,
           json_out)  # fmt: skip


@pytest.mark.parametrize("json_out", [False, True])
def test_report(files, tmp_path, json_out):
    flag = ["--json"] if json_out else []
    _check(_run("report", str(files["run"]), *flag), 0)
    _check(_run("report", str(tmp_path / "nothing"), *flag), 2, json_out)
    _check(_run("report", str(files["garbage"]), *flag), 2, json_out)


@pytest.mark.parametrize("json_out", [False, True])
def test_sweep(files, tmp_path, json_out):
    flag = ["--json"] if json_out else []
    common = ["--out", str(tmp_path / "s"), "--frames", "1:1", "--resolution", "32x24"]
    _check(_run("sweep", str(files["good"]), *common, "--budgets-rays", "x", *flag), 2,
           json_out)  # fmt: skip
    _check(_run("sweep", str(files["good"]), *common, "--heuristics", "heu9",
                "--budgets-rays", "100", *flag), 2, json_out)  # fmt: skip
    _check(_run("sweep", str(files["missing"]), *common, "--budgets-rays", "100", *flag), 2,
           json_out)  # fmt: skip
