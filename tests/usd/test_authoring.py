"""phrt_usd.usd.authoring: opinions in a new layer over the stage (the input untouched, all its
layer metadata carried over), or in place in the file's own format; never overwriting what
it should not."""

import os
import stat
from contextlib import contextmanager
from pathlib import Path

import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdUtils
from scenes import composed_stage, cube_stage
from typer.testing import CliRunner

from phrt_usd.cli import app
from phrt_usd.errors import PhrtError
from phrt_usd.usd import authoring, schema
from phrt_usd.usd.authoring import author_reflectors, default_overlay_path


@pytest.fixture()
def stage_file(tmp_path):
    path = tmp_path / "scene.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, "Z")
    UsdGeom.Xform.Define(stage, "/World")
    UsdGeom.Cube.Define(stage, "/World/Box")
    UsdGeom.Sphere.Define(stage, "/World/Ball")
    stage.GetRootLayer().Save()
    return path


def test_default_writes_overlay_and_keeps_input_bytes(stage_file):
    before = stage_file.read_bytes()
    result = author_reflectors(stage_file, ["/World/Box", "/World/Ball"], 4.0, reflectivity=0.5)
    assert stage_file.read_bytes() == before
    overlay = default_overlay_path(stage_file)
    assert result.layer == str(overlay) and overlay.name == "scene.phrt.usda"
    layer = Sdf.Layer.FindOrOpen(str(overlay))
    assert list(layer.subLayerPaths) == ["scene.usda"]  # relative to the overlay
    assert layer.GetPrimAtPath("/World/Box").specifier == Sdf.SpecifierOver
    stage = Usd.Stage.Open(str(overlay))
    for path in ("/World/Box", "/World/Ball"):
        prim = stage.GetPrimAtPath(path)
        assert schema.is_reflector(prim)
        assert schema.reflector_priority(prim) == 4.0
        assert schema.reflector_reflectivity(prim) == 0.5
    assert UsdGeom.GetStageUpAxis(stage) == "Z"
    assert not list(stage_file.parent.glob(".*"))  # no temp file left behind


def test_out_in_other_directory_uses_relative_sublayer(stage_file, tmp_path, capfd):
    out = tmp_path / "sub" / "k.usda"
    author_reflectors(stage_file, ["/World/Box"], 2.0, out=out)
    # USD warns on stderr (C++) if a stage recomposes against the not-yet-saved path.
    assert "Could not load sublayer" not in capfd.readouterr().err
    assert list(Sdf.Layer.FindOrOpen(str(out)).subLayerPaths) == ["../scene.usda"]
    assert schema.reflector_priority(Usd.Stage.Open(str(out)).GetPrimAtPath("/World/Box")) == 2.0


def test_in_place_edits_root_layer(stage_file):
    author_reflectors(stage_file, ["/World/Box"], 3.0, in_place=True)
    Sdf.Layer.FindOrOpen(str(stage_file)).Reload()
    assert "PhrtReflectorAPI" in stage_file.read_text()
    stage = Usd.Stage.Open(str(stage_file))
    prim = stage.GetPrimAtPath("/World/Box")
    assert schema.is_reflector(prim) and schema.reflector_priority(prim) == 3.0
    assert not default_overlay_path(stage_file).exists()


@pytest.mark.parametrize(
    "prims, priority, message",
    [
        (["/World/Nope"], 1.0, "/World/Nope: no such prim"),
        (["/World"], 1.0, "/World: is a Xform, not a gprim"),
        (["/World/Box", "/World"], 1.0, "/World: is a Xform"),
        (["/World/Box"], -2.0, "--priority -2.0"),
        (["/World/Box"], float("nan"), "--priority nan"),
    ],
)
def test_errors_write_nothing(stage_file, prims, priority, message):
    before = stage_file.read_bytes()
    with pytest.raises(PhrtError, match=message.replace("(", r"\(")):
        author_reflectors(stage_file, prims, priority)
    assert stage_file.read_bytes() == before
    assert sorted(p.name for p in stage_file.parent.iterdir()) == ["scene.usda"]


# --- fixtures: stages in other formats, composed stages, an animated 30 fps stage ------

runner = CliRunner()


FPS30_SAMPLES = (1.0, 7.5, 13.0, 24.0, 30.0, 48.0)


def _fps30_stage(path: Path) -> Path:
    """A 30 fps stage (time codes 1..48, a render settings path, custom layer data) with
    an xform animated by time samples and a cube under it."""
    stage = Usd.Stage.CreateNew(str(path))
    stage.SetTimeCodesPerSecond(30)
    stage.SetFramesPerSecond(30)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(48)
    UsdGeom.SetStageUpAxis(stage, "Z")
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    root = stage.GetRootLayer()
    root.pseudoRoot.SetInfo("renderSettingsPrimPath", "/Render/Settings")
    root.customLayerData = {"studio": "phrt", "shot": 7}
    root.documentation = "thirty frames a second"
    stage.DefinePrim("/Render/Settings", "RenderSettings")
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    mover = UsdGeom.Xform.Define(stage, "/World/Mover")
    translate = mover.AddTranslateOp()
    rotate = mover.AddRotateZOp()
    for t in FPS30_SAMPLES:
        translate.Set(Gf.Vec3d(t, 2 * t, -t), t)
        rotate.Set(3.0 * t, t)
    UsdGeom.Cube.Define(stage, "/World/Mover/Box")
    root.Save()
    return path


def _stage_metadata(stage: Usd.Stage) -> dict:
    return {
        "start": stage.GetStartTimeCode(),
        "end": stage.GetEndTimeCode(),
        "tcps": stage.GetTimeCodesPerSecond(),
        "fps": stage.GetFramesPerSecond(),
        "render_settings": stage.GetMetadata("renderSettingsPrimPath"),
        "up": UsdGeom.GetStageUpAxis(stage),
        "mpu": UsdGeom.GetStageMetersPerUnit(stage),
        "default_prim": str(stage.GetDefaultPrim().GetPath()),
    }


def _assert_reflector(path: Path, prim: str, priority: float) -> None:
    layer = Sdf.Layer.FindOrOpen(str(path))
    layer.Reload(force=True)
    stage = Usd.Stage.Open(layer)
    p = stage.GetPrimAtPath(prim)
    assert schema.is_reflector(p) and schema.reflector_priority(p) == priority


@contextmanager
def _umask(mask: int):
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


# --- in place: the file keeps its format ----------------------------------------------


def test_in_place_usdc_stays_crate(tmp_path):
    path = cube_stage(tmp_path / "scene.usdc")
    assert path.read_bytes().startswith(b"PXR-USDC")
    result = author_reflectors(path, ["/World/Box"], 3.0, in_place=True)
    assert result.layer == str(path)
    assert path.read_bytes().startswith(b"PXR-USDC")
    _assert_reflector(path, "/World/Box", 3.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.usdc"]


@pytest.mark.parametrize("fmt, magic", [("usda", b"#usda"), ("usdc", b"PXR-USDC")])
def test_in_place_usd_keeps_its_flavour(tmp_path, fmt, magic):
    path = cube_stage(tmp_path / "scene.usd", fmt)
    assert path.read_bytes().startswith(magic)
    author_reflectors(path, ["/World/Box"], 5.0, in_place=True)
    assert path.read_bytes().startswith(magic)
    _assert_reflector(path, "/World/Box", 5.0)


def test_in_place_usdz_refused_file_byte_identical(tmp_path):
    inner = cube_stage(tmp_path / "inner.usdc")
    package = tmp_path / "scene.usdz"
    assert UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(inner)), str(package))
    before = package.read_bytes()
    listing = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(PhrtError) as info:
        author_reflectors(package, ["/World/Box"], 2.0, in_place=True)
    message = str(info.value)
    assert "\n" not in message and str(package) in message
    assert "cannot be edited in place" in message and "overlay" in message
    assert package.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == listing
    # The suggested way works: an overlay next to the package.
    overlay = Path(author_reflectors(package, ["/World/Box"], 2.0).layer)
    assert package.read_bytes() == before
    _assert_reflector(overlay, "/World/Box", 2.0)


def test_in_place_symlinked_stage_edits_target_keeps_link(tmp_path):
    real = cube_stage(tmp_path / "real.usdc")
    link = tmp_path / "link.usdc"
    link.symlink_to(real.name)
    author_reflectors(link, ["/World/Box"], 6.0, in_place=True)
    assert link.is_symlink() and real.read_bytes().startswith(b"PXR-USDC")
    _assert_reflector(real, "/World/Box", 6.0)


@pytest.mark.parametrize("mode, mask", [(0o644, 0o002), (0o664, 0o022), (0o600, 0o022)])
def test_in_place_keeps_file_mode(tmp_path, mode, mask):
    path = cube_stage(tmp_path / "scene.usdc")
    path.chmod(mode)
    with _umask(mask):
        author_reflectors(path, ["/World/Box"], 1.5, in_place=True)
    assert stat.S_IMODE(path.stat().st_mode) == mode
    _assert_reflector(path, "/World/Box", 1.5)


@pytest.mark.parametrize("mask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_new_overlay_follows_umask(stage_file, mask, mode):
    with _umask(mask):
        overlay = Path(author_reflectors(stage_file, ["/World/Box"], 1.0).layer)
    assert stat.S_IMODE(overlay.stat().st_mode) == mode


def test_failed_check_leaves_file_and_stage_layer_untouched(tmp_path, monkeypatch):
    path = cube_stage(tmp_path / "scene.usdc")
    before = path.read_bytes()
    held = Sdf.Layer.FindOrOpen(str(path))  # the layer the stage will be opened on
    monkeypatch.setattr(authoring, "_MAGIC", {**authoring._MAGIC, "usdc": b"NOT-CRATE"})
    with pytest.raises(PhrtError, match="is not a usdc layer"):
        author_reflectors(path, ["/World/Box"], 1.0, in_place=True)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.usdc"]
    # The opinions that never reached the file are not left in the open layer either.
    assert not held.dirty and not held.GetPrimAtPath("/World/Box").HasInfo("apiSchemas")
    assert not schema.is_reflector(Usd.Stage.Open(str(path)).GetPrimAtPath("/World/Box"))


# --- overlays never overwrite what they should not --------------------------------------


def test_out_existing_file_needs_force(stage_file, tmp_path):
    out = tmp_path / "other.usda"
    out.write_text("#usda 1.0\n")
    with pytest.raises(PhrtError) as info:
        author_reflectors(stage_file, ["/World/Box"], 2.0, out=out)
    assert str(info.value) == f"{out}: already exists; pass --force to overwrite it"
    assert out.read_text() == "#usda 1.0\n"
    author_reflectors(stage_file, ["/World/Box"], 2.0, out=out, force=True)
    _assert_reflector(out, "/World/Box", 2.0)


def test_default_overlay_existing_needs_force(stage_file):
    author_reflectors(stage_file, ["/World/Box"], 2.0)
    overlay = default_overlay_path(stage_file)
    before = overlay.read_bytes()
    with pytest.raises(PhrtError, match="already exists; pass --force"):
        author_reflectors(stage_file, ["/World/Ball"], 3.0)
    assert overlay.read_bytes() == before
    author_reflectors(stage_file, ["/World/Ball"], 3.0, force=True)
    _assert_reflector(overlay, "/World/Ball", 3.0)


@pytest.mark.parametrize(
    "name", ["sub.usda", "deep.usda", "ref.usda", "pay.usda", "var.usda", "vardeep.usda"]
)
def test_out_onto_a_layer_the_stage_uses_refused_even_with_force(tmp_path, name):
    stage_file = composed_stage(tmp_path)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    for target in (tmp_path / name, tmp_path / "elsewhere" / ".." / name):
        with pytest.raises(PhrtError) as info:
            author_reflectors(stage_file, ["/World/Box"], 2.0, out=target, force=True)
        message = str(info.value)
        assert message.startswith(f"{target}: is a layer the stage uses") and "\n" not in message
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_out_symlink_to_used_layer_refused_even_with_force(tmp_path):
    stage_file = composed_stage(tmp_path)
    (tmp_path / "links").mkdir()
    link = tmp_path / "links" / "alias.usda"
    link.symlink_to(tmp_path / "ref.usda")
    before = (tmp_path / "ref.usda").read_bytes()
    with pytest.raises(PhrtError, match="is a layer the stage uses"):
        author_reflectors(stage_file, ["/World/Box"], 2.0, out=link, force=True)
    assert link.is_symlink() and (tmp_path / "ref.usda").read_bytes() == before


def test_out_is_the_input_stage_refused(tmp_path):
    stage_file = composed_stage(tmp_path)
    link = tmp_path / "same.usda"
    link.symlink_to(stage_file.name)
    before = stage_file.read_bytes()
    for out in (stage_file, link):
        with pytest.raises(PhrtError, match="is the input stage; use --in-place"):
            author_reflectors(stage_file, ["/World/Box"], 2.0, out=out, force=True)
    assert stage_file.read_bytes() == before


def test_overlay_of_composed_stage_written_next_to_layers(tmp_path):
    stage_file = composed_stage(tmp_path)
    overlay = Path(author_reflectors(stage_file, ["/World/Box", "/World/Ref"], 4.0).layer)
    stage = Usd.Stage.Open(str(overlay))
    assert schema.reflector_priority(stage.GetPrimAtPath("/World/Ref")) == 4.0
    assert stage.GetPrimAtPath("/Deep") and stage.GetPrimAtPath("/World/Pay")


# --- an overlay composes exactly like the stage alone ---------------------------------


@pytest.mark.parametrize("out_name", [None, "sub/shot.usda", "shot.usdc"])
def test_overlay_of_30fps_stage_keeps_timing_and_metadata(tmp_path, out_name):
    stage_file = _fps30_stage(tmp_path / "anim.usda")
    out = tmp_path / out_name if out_name else None
    overlay = Path(author_reflectors(stage_file, ["/World/Mover/Box"], 2.0, out=out).layer)
    alone = Usd.Stage.Open(str(stage_file))
    over = Usd.Stage.Open(str(overlay))
    assert schema.reflector_priority(over.GetPrimAtPath("/World/Mover/Box")) == 2.0
    assert _stage_metadata(over) == _stage_metadata(alone)
    assert _stage_metadata(alone)["tcps"] == 30.0 and _stage_metadata(alone)["start"] == 1.0
    src, dst = Sdf.Layer.FindOrOpen(str(stage_file)), Sdf.Layer.FindOrOpen(str(overlay))
    assert dst.customLayerData == src.customLayerData == {"studio": "phrt", "shot": 7}
    assert dst.documentation == src.documentation
    samples = alone.GetAttributeAtPath("/World/Mover.xformOp:translate").GetTimeSamples()
    assert samples == list(FPS30_SAMPLES)
    box_alone = UsdGeom.Xformable(alone.GetPrimAtPath("/World/Mover/Box"))
    box_over = UsdGeom.Xformable(over.GetPrimAtPath("/World/Mover/Box"))
    for t in [*samples, 4.0, 40.0]:
        assert box_over.ComputeLocalToWorldTransform(t) == box_alone.ComputeLocalToWorldTransform(
            t
        ), t
    translate = over.GetAttributeAtPath("/World/Mover.xformOp:translate")
    assert translate.GetTimeSamples() == samples
    assert translate.Get(13.0) == Gf.Vec3d(13, 26, -13)


# --- the CLI -------------------------------------------------------------------------------


def _cli(*args):
    result = runner.invoke(app, ["author", *(str(a) for a in args)])
    assert "Traceback" not in result.output + (result.stderr or "")
    assert result.exception is None or isinstance(result.exception, SystemExit)
    return result


def test_cli_author_exit_codes(stage_file, tmp_path):
    before = stage_file.read_bytes()
    ok = _cli(stage_file, "/World/Box", "--priority", "2")
    assert ok.exit_code == 0 and ok.stdout.startswith(f"wrote {default_overlay_path(stage_file)}")

    existing = tmp_path / "taken.usda"
    existing.write_text("#usda 1.0\n")
    refused = _cli(stage_file, "/World/Box", "--priority", "2", "--out", existing)
    assert refused.exit_code == 1
    assert refused.stderr == f"error: {existing}: already exists; pass --force to overwrite it\n"
    assert existing.read_text() == "#usda 1.0\n"
    forced = _cli(stage_file, "/World/Box", "--priority", "2", "--out", existing, "--force")
    assert forced.exit_code == 0
    _assert_reflector(existing, "/World/Box", 2.0)

    bad_prim = _cli(stage_file, "/World/Nope", "--priority", "2", "--out", tmp_path / "n.usda")
    assert bad_prim.exit_code == 1 and bad_prim.stderr.startswith("error: /World/Nope: no such")
    assert not (tmp_path / "n.usda").exists()

    both = _cli(
        stage_file, "/World/Box", "--priority", "2", "--in-place", "--out", tmp_path / "b.usda"
    )
    assert both.exit_code == 2 and "--out and --in-place exclude each other" in both.stderr

    assert stage_file.read_bytes() == before


def test_cli_author_refusals_exit_1(tmp_path):
    stage_file = composed_stage(tmp_path)
    result = _cli(
        stage_file, "/World/Box", "--priority", "1", "--out", tmp_path / "ref.usda", "--force"
    )
    assert result.exit_code == 1 and result.stderr.count("\n") == 1
    assert "is a layer the stage uses" in result.stderr

    inner = cube_stage(tmp_path / "inner.usdc")
    package = tmp_path / "p.usdz"
    assert UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(inner)), str(package))
    before = package.read_bytes()
    result = _cli(package, "/World/Box", "--priority", "1", "--in-place")
    assert result.exit_code == 1 and result.stderr.count("\n") == 1
    assert result.stderr.startswith(f"error: {package}: a .usdz package cannot be edited in place")
    assert package.read_bytes() == before


def test_cli_author_in_place_usdc(tmp_path):
    path = cube_stage(tmp_path / "scene.usdc")
    result = _cli(path, "/World/Box", "--priority", "7", "--in-place")
    assert result.exit_code == 0, result.output
    assert path.read_bytes().startswith(b"PXR-USDC")
    _assert_reflector(path, "/World/Box", 7.0)


@pytest.mark.parametrize("kind", ["missing", "garbage", "directory"])
def test_cli_author_unreadable_stage_exit_2(tmp_path, kind):
    path = tmp_path / "broken.usda"
    if kind == "garbage":
        path.write_text("this is not usd {{{\n")
    elif kind == "directory":
        path.mkdir()
    result = _cli(path, "/World/Box", "--priority", "1")
    assert result.exit_code == 2 and result.stderr.startswith(f"error: {path}")
    assert not default_overlay_path(path).exists()
