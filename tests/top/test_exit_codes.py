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


@pytest.mark.slow
@pytest.mark.parametrize("json_out", [False, True])
def test_validate(files, json_out):
    flag = ["--json"] if json_out else []
    _check(_run("validate", str(files["good"]), *flag), 0)
    done = _run("validate", str(files["problems"]), *flag)
    assert done.returncode == 1 and "Traceback" not in done.stderr
    _check(_run("validate", str(files["garbage"]), *flag), 2, json_out)
    _check(_run("validate", str(files["missing"]), *flag), 2, json_out)


@pytest.mark.slow
@pytest.mark.parametrize("json_out", [False, True])
def test_inspect(files, json_out):
    flag = ["--json"] if json_out else []
    _check(_run("inspect", str(files["good"]), *flag), 0)
    _check(_run("inspect", str(files["garbage"]), *flag), 2, json_out)
    _check(_run("inspect", str(files["root"]), *flag), 2, json_out)  # a directory


@pytest.mark.slow
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


@pytest.mark.slow
@pytest.mark.parametrize("json_out", [False, True])
def test_report(files, tmp_path, json_out):
    flag = ["--json"] if json_out else []
    _check(_run("report", str(files["run"]), *flag), 0)
    _check(_run("report", str(tmp_path / "nothing"), *flag), 2, json_out)
    _check(_run("report", str(files["garbage"]), *flag), 2, json_out)


@pytest.mark.slow
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


#: The ``phrt`` entry point itself (the console script's ``app()``): ``python -m typer``
#: builds its own command group, without phrt's handling of usage errors.
PHRT = [sys.executable, "-c",
        "import sys; from phrt_usd.cli import app; sys.argv[0] = 'phrt'; app()"]  # fmt: skip

#: A text layer that does not parse: line 5, column 21 holds the second number of a
#: scalar value, where the parser expects the end of the prim.
UNPARSABLE = '#usda 1.0\n\ndef Xform "World"\n{\n    double radius = 1 2\n}\n'


def _phrt(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*PHRT, *args], capture_output=True, text=True, timeout=300)


@pytest.mark.slow
@pytest.mark.parametrize("json_out", [False, True])
def test_probe_usd_parse_error_reaches_the_user(tmp_path, json_out):
    """validate, inspect, author and render of a stage that does not parse: exit 2 and
    one line (or the one JSON object) holding USD's ``file:line:column: what``."""
    bad = tmp_path / "bad.usda"
    bad.write_text(UNPARSABLE)
    flag = ["--json"] if json_out else []
    located = f"{bad}:5:"
    for args in (["validate", str(bad), *flag], ["inspect", str(bad), *flag],
                 ["render", str(bad), "--out", str(tmp_path / "run"), *flag]):  # fmt: skip
        done = _run(*args)
        _check(done, 2, json_out)
        said = json.loads(done.stdout)["error"] if json_out else done.stderr
        assert located in said and "Expected" in said, (args, said)
    done = _run("author", str(bad), "/World", "--priority", "1")
    _check(done, 2)
    assert located in done.stderr, done.stderr


@pytest.mark.slow
def test_probe_validate_of_a_layer_that_does_not_parse(tmp_path):
    """validate of a stage whose referenced layer, sublayer, usdz member, or a layer of
    an unselected variant does not parse: a finding (exit 1) located at the parser's
    ``file:line:column``, never a traceback (USD's own validators stop at such a layer;
    the others' findings are kept)."""
    from pxr import Sdf, UsdGeom

    bad = tmp_path / "bad.usda"
    bad.write_text(UNPARSABLE)
    referencing = tmp_path / "ref.usda"
    stage = Usd.Stage.CreateNew(str(referencing))
    UsdGeom.Camera.Define(stage, "/World/Cam")
    UsdGeom.Cube.Define(stage, "/World/Box")
    stage.DefinePrim("/World/Prop").GetReferences().AddReference("./bad.usda")
    stage.GetRootLayer().subLayerPaths.append("./bad.usda")
    stage.GetRootLayer().Save()
    unselected = tmp_path / "variant.usda"
    stage = Usd.Stage.CreateNew(str(unselected))
    UsdGeom.Camera.Define(stage, "/World/Cam")
    holder = stage.DefinePrim("/World/Var")
    look = holder.GetVariantSets().AddVariantSet("look")
    look.AddVariant("plain")
    look.AddVariant("fancy")
    look.SetVariantSelection("fancy")
    with look.GetVariantEditContext():
        holder.GetReferences().AddReference("./bad.usda")
    look.SetVariantSelection("plain")
    stage.GetRootLayer().Save()
    package = tmp_path / "pkg.usdz"
    member = tmp_path / "member"
    member.mkdir()
    stage = Usd.Stage.CreateNew(str(member / "root.usda"))
    UsdGeom.Camera.Define(stage, "/World/Cam")
    stage.DefinePrim("/World/Prop").GetReferences().AddReference("./bad.usda")
    stage.GetRootLayer().Save()
    writer = Sdf.ZipFileWriter.CreateNew(str(package))
    writer.AddFile(str(member / "root.usda"), "root.usda")
    writer.AddFile(str(bad), "bad.usda")
    writer.Save()
    for path, located in ((referencing, f"{bad}:5:"), (unselected, f"{bad}:5:"),
                          (package, f"{package}[bad.usda]:5:")):  # fmt: skip
        for flag in ([], ["--json"]):
            done = _run("validate", str(path), *flag)
            assert done.returncode == 1, (path, done.stdout[-800:], done.stderr[-2000:])
            assert "Traceback" not in done.stderr
            said = done.stdout if flag else done.stderr
            assert located in said, (path, said[-2000:])
            if flag:
                assert json.loads(done.stdout)["ok"] is False


@pytest.mark.slow
@pytest.mark.parametrize("value", ["inf", "-inf", "nan", "-1", "0"])
def test_probe_float_meters_per_unit(tmp_path, value):
    """A metersPerUnit that is no finite number > 0: inspect and render refuse the
    stage as unusable input, exit 2, one line (or JSON object) naming the layer
    metadata; no traceback (inspect --json used to fail writing inf as JSON)."""
    stage = tmp_path / "units.usda"
    stage.write_text(f'#usda 1.0\n(\n    metersPerUnit = {value}\n)\n\ndef Cube "Box"\n{{\n}}\n')
    for args in (["inspect", str(stage)], ["render", str(stage), "--out", str(tmp_path / "r")]):
        for flag in ([], ["--json"]):
            done = _run(*args, *flag)
            _check(done, 2, bool(flag))
            said = json.loads(done.stdout)["error"] if flag else done.stderr
            assert f"{stage}: layer metadata metersPerUnit must be a finite number > 0" in said


@pytest.mark.slow
def test_probe_bad_camera_settings_and_author_output_exit_2(files, tmp_path):
    """--camera or --settings naming nothing, and author's output that cannot be
    written, are bad options: exit 2 (they were 1), one line."""
    good = str(files["good"])
    for option in (["--camera", "/Nope"], ["--camera", "Nope"], ["--settings", "/Nope"]):
        done = _run("render", good, "--out", str(tmp_path / "r"), *RENDER, *option)
        _check(done, 2)
        assert f"{option[0]} {option[1]}:" in done.stderr, done.stderr
    prim = "/World/Mirror0"  # the gallery's first mirror
    a_file = tmp_path / "file.txt"
    a_file.write_text("not a directory")
    for out in (a_file / "x.usda", Path("/proc/phrt-no-such-dir/x.usda")):
        done = _run("author", good, prim, "--priority", "1", "--out", str(out))
        _check(done, 2)
        assert not out.exists()


@pytest.mark.slow
@pytest.mark.parametrize("json_out", [False, True])
def test_probe_json_usage_error(files, json_out):
    """A usage error (unknown option or command, malformed value, missing argument)
    with --json among the arguments is the one JSON error object on stdout, exit 2;
    without --json click's usage text stays on stderr."""
    flag = ["--json"] if json_out else []
    for args in (["validate", str(files["good"]), "--bogus"], ["render", "--budget-rays",
                 "abc", str(files["good"])], ["inspect"], ["bogus"]):  # fmt: skip
        done = _phrt(*args, *flag)
        assert done.returncode == 2 and "Traceback" not in done.stderr, done
        if json_out:
            error = json.loads(done.stdout)
            assert error["code"] == 2 and error["error"].startswith("phrt"), error
            assert "\n" not in error["error"]
        else:
            assert done.stdout == "" and "Usage:" in done.stderr


@pytest.mark.slow
def test_probe_unknown_variant_and_session_layer_directory(files, tmp_path):
    """--variant with a name USD cannot hold says which prim, set and variants there
    are (not "cannot open as USD"); a directory as --session-layer is said to be one."""
    good = str(files["good"])
    done = _run("render", good, "--out", str(tmp_path / "r"), "--variant", "/World:look=a.b")
    _check(done, 2)
    assert "cannot open as USD" not in done.stderr and "/World has no variant set" in done.stderr
    done = _run("render", good, "--out", str(tmp_path / "r"), "--session-layer", str(tmp_path))
    _check(done, 2)
    assert f"--session-layer {tmp_path}: is a directory" in done.stderr, done.stderr
