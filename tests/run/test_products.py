"""UsdRender outputs: --settings, RenderProducts and RenderVars as EXR files and channels,
camera matrices and the id manifest in the header, --image, --aovs, byte-identical runs,
and the run directory's rules for product files.

The stage: ``mirror_floor_stage`` (its own /Render/Settings, the stage's, has no products)
plus a second RenderSettings /Render/Second with another camera and one product
``beauty.$F4.exr`` (color, depth, normal, primId), over two still frames.
"""

from __future__ import annotations

import json
import subprocess
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdRender
from scenes import SPHERE_CENTER, SPHERE_RADIUS, _look_at_matrix, mirror_floor_stage, render_var

from phrt_usd.engine.renderer import RenderOptions
from phrt_usd.errors import BadOption, PhrtError
from phrt_usd.run.images import ID_BACKGROUND, element_ids, read_exr, read_manifest
from phrt_usd.run.products import (
    expand,
    plan_images,
    relative_template,
    template_pattern,
    var_channels,
)
from phrt_usd.run.render_job import RenderJob, render_to_directory
from phrt_usd.usd.render_settings import (
    MULTIPART_ATTR,
    RenderProductSpec,
    RenderSettingsSpec,
    read_render_settings,
)

CLI = [sys.executable, "-m", "typer", "phrt_usd.cli", "run", "render"]
#: A deterministic budget: the run's pixels do not depend on the machine's speed.
RAYS = ["--budget-rays", "4000"]
#: The second camera (world metres; the stage is 1 m per unit).
EYE2 = np.array([1.0, 1.6, 4.0])
TARGET2 = np.array([0.0, 0.8, 0.0])
#: /Render/Second's resolution, and its product's own, which wins.
SETTINGS_RES, PRODUCT_RES = (80, 60), (96, 72)


def _settings(stage: Usd.Stage, path: str, products: list[UsdRender.Product], camera=None):
    settings = UsdRender.Settings.Define(stage, path)
    settings.CreateResolutionAttr(Gf.Vec2i(*SETTINGS_RES))
    settings.CreateProductsRel().SetTargets([p.GetPath() for p in products])
    if camera is not None:
        settings.CreateCameraRel().SetTargets([camera])
    return settings


def _product(stage: Usd.Stage, path: str, name: str, variables, resolution=None):
    product = UsdRender.Product.Define(stage, path)
    product.CreateProductNameAttr(name)
    product.CreateOrderedVarsRel().SetTargets(list(variables))
    if resolution is not None:
        product.CreateResolutionAttr(Gf.Vec2i(*resolution))
    return product


def products_stage(path: Path) -> Path:
    mirror_floor_stage(path)
    stage = Usd.Stage.Open(str(path))
    stage.SetEndTimeCode(2)
    camera = UsdGeom.Camera.Define(stage, "/World/Camera2")
    camera.CreateFocalLengthAttr(30.0)
    camera.CreateHorizontalApertureAttr(36.0)
    camera.CreateClippingRangeAttr(Gf.Vec2f(0.05, 50.0))
    UsdGeom.Xformable(camera).AddTransformOp().Set(_look_at_matrix(EYE2, TARGET2))
    variables = [
        render_var(stage, "color", "color", "color3h"),
        render_var(stage, "depth", "depth", "float"),
        render_var(stage, "N", "normal", "normal3f"),
        render_var(stage, "id", "primId", "int"),
    ]
    beauty = _product(stage, "/Render/Products/Beauty", "beauty.$F4.exr", variables, PRODUCT_RES)
    _settings(stage, "/Render/Second", [beauty], camera.GetPath())
    # Settings whose products phrt must refuse (tests pick them with --settings).
    outside = _product(stage, "/Render/Products/Outside", "/tmp/phrt-outside.$F4.exr", [])
    _settings(stage, "/Render/Escape", [outside])
    parts = _product(stage, "/Render/Products/Parts", "parts.$F4.exr", variables[:2])
    parts.GetPrim().CreateAttribute(MULTIPART_ATTR, Sdf.ValueTypeNames.Bool).Set(True)
    _settings(stage, "/Render/Parts", [parts])
    stage.GetRootLayer().Save()
    return path


@pytest.fixture(scope="module")
def stage(tmp_path_factory) -> Path:
    return products_stage(tmp_path_factory.mktemp("stage") / "products.usda")


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=300)


def _ok(*args: str) -> dict:
    done = _cli(*args, "--json")
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def _one_line_error(done: subprocess.CompletedProcess, code: int) -> str:
    assert done.returncode == code, (done.returncode, done.stderr, done.stdout)
    assert "Traceback" not in done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, done.stderr
    return errors[0]


def _files(out: Path) -> list[str]:
    return sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())


def _storage(channels: dict[str, np.ndarray]) -> dict[str, str]:
    """Channel name → half / float / uint, from the arrays ``read_exr`` gives."""
    names = {np.float16: "half", np.float32: "float", np.uint32: "uint"}
    return {name: names[a.dtype.type] for name, a in channels.items()}


@pytest.fixture(scope="module")
def second(stage, tmp_path_factory) -> Path:
    """A CLI render of frames 1 and 2 with --settings /Render/Second."""
    out = tmp_path_factory.mktemp("second") / "out"
    _ok(str(stage), "--out", str(out), "--settings", "/Render/Second", "--frames", "1:2", *RAYS)
    return out


def _project(point: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """A world point through a header matrix (row vectors, as Imath multiplies them)."""
    row = np.append(point, 1.0) @ matrix.astype(np.float64)
    return row[:3] / row[3]


# --- --settings and the product ----------------------------------------------------------


@pytest.mark.slow
def test_settings_picks_the_second_settings_products_names_and_resolution(stage, second):
    # The stage's own settings (/Render/Settings) have no products: the second's are used.
    run = json.loads((second / "stats.json").read_text())["run"]
    assert run["settings"] == "/Render/Second"
    assert _files(second) == [
        "beauty.0001.exr", "beauty.0002.exr", "checkpoint.json", "selection.usda", "stats.json"
    ]  # fmt: skip
    header, channels = read_exr(second / "beauty.0001.exr")
    # The product's own resolution wins over its settings' (80x60).
    assert channels["R"].shape == (PRODUCT_RES[1], PRODUCT_RES[0])
    assert run["resolution"] == list(PRODUCT_RES)
    assert _storage(channels) == {
        "R": "half", "G": "half", "B": "half", "A": "half",  # color3h
        "Z": "float",  # depth: float
        "N.x": "float", "N.y": "float", "N.z": "float",  # normal3f
        "id": "uint",  # primId: an exact uint
    }  # fmt: skip
    assert header["phrt/renderSettings"] == "/Render/Second"
    assert header["phrt/renderProduct"] == "/Render/Products/Beauty"
    assert header["phrt/camera"] == "/World/Camera2"  # the settings' camera
    assert header["framesPerSecond"] == Fraction(24, 1)
    assert header["software"].startswith("phrt-usd ")
    assert float(header["phrt/timeCode"][0]) == 1.0
    assert float(read_exr(second / "beauty.0002.exr")[0]["phrt/timeCode"][0]) == 2.0
    assert "capDate" not in header


@pytest.mark.slow
def test_camera_matrices_in_the_header_agree_with_the_camera_and_the_pixels(second):
    header, channels = read_exr(second / "beauty.0001.exr")
    height, width = channels["Z"].shape
    to_camera, to_ndc = header["worldToCamera"], header["worldToNDC"]
    # worldToCamera puts the eye at the origin and the target straight ahead (+z).
    np.testing.assert_allclose(_project(EYE2, to_camera), 0.0, atol=1e-5)
    ahead = _project(TARGET2, to_camera)
    np.testing.assert_allclose(ahead[:2], 0.0, atol=1e-5)
    assert ahead[2] == pytest.approx(np.linalg.norm(TARGET2 - EYE2), rel=1e-6)
    # worldToNDC puts the target at the image centre ((0, 0) top-left, (1, 1) bottom-right).
    np.testing.assert_allclose(_project(TARGET2, to_ndc)[:2], 0.5, atol=1e-6)
    # The ball's centre projects to a pixel that shows the ball at the depth its front has.
    ndc = _project(SPHERE_CENTER, to_ndc)
    col, row = int(ndc[0] * width), int(ndc[1] * height)
    ids = element_ids(channels["id"])
    assert read_manifest(header)[int(ids[row, col])] == "/World/Ball"
    z_centre = _project(SPHERE_CENTER, to_camera)[2]
    distance = np.linalg.norm(SPHERE_CENTER - EYE2)
    front = (distance - SPHERE_RADIUS) * z_centre / distance
    assert channels["Z"][row, col] == pytest.approx(front, abs=0.02)
    # A point above the ball projects higher in the image (NDC y grows downwards).
    assert _project(SPHERE_CENTER + [0.0, 0.3, 0.0], to_ndc)[1] < ndc[1]
    # The normal there faces the eye.
    normal = np.array([channels[f"N.{a}"][row, col] for a in "xyz"])
    facing = (EYE2 - SPHERE_CENTER) / distance
    assert np.dot(normal, facing) > 0.97


@pytest.mark.slow
def test_manifest_resolves_the_id_at_a_known_pixel_to_its_prim(second):
    header, channels = read_exr(second / "beauty.0001.exr")
    ids = channels["id"]
    assert ids.dtype == np.uint32
    manifest = read_manifest(header)
    ndc = _project(SPHERE_CENTER, header["worldToNDC"])
    row, col = int(ndc[1] * ids.shape[0]), int(ndc[0] * ids.shape[1])
    assert manifest[int(ids[row, col])] == "/World/Ball"
    # Every id in the frame is named, and only those; the sky (top row) is background.
    covered = ids[ids != ID_BACKGROUND]
    assert set(manifest) == {int(i) for i in np.unique(covered)}
    assert set(manifest.values()) == {"/World/Ball", "/World/Floor"}
    assert (ids[0] == ID_BACKGROUND).all() and ID_BACKGROUND not in manifest
    # OpenEXR's own manifest is there too, for the id channel.
    assert isinstance(header["idManifest"], OpenEXR.IDManifest)
    assert header["idManifest"].find("id") >= 0


@pytest.mark.slow
def test_identical_budget_rays_runs_write_identical_bytes(stage, second, tmp_path):
    again = tmp_path / "again"
    _ok(str(stage), "--out", str(again), "--settings", "/Render/Second", "--frames", "1:2", *RAYS)
    for name in ("beauty.0001.exr", "beauty.0002.exr"):
        assert (again / name).read_bytes() == (second / name).read_bytes(), name


@pytest.mark.slow
def test_no_products_keeps_the_default_layout_byte_for_byte(stage, tmp_path):
    out = tmp_path / "out"
    _ok(str(stage), "--out", str(out), "--frames", "1", *RAYS)  # the stage's own settings
    assert _files(out) == [
        "checkpoint.json", "frames/0001.exr", "frames/0001.png", "selection.usda", "stats.json"
    ]  # fmt: skip
    header, channels = read_exr(out / "frames" / "0001.exr")
    assert _storage(channels) == {
        "R": "half", "G": "half", "B": "half", "A": "half", "Z": "float", "id": "uint",
        "traced": "half",
    }  # fmt: skip
    assert channels["R"].shape == (120, 160)
    assert header["phrt/camera"] == "/World/Camera"
    manifest = read_manifest(header)
    assert set(manifest.values()) == {"/World/Ball", "/World/Floor"}
    again = tmp_path / "again"
    _ok(str(stage), "--out", str(again), "--frames", "1", *RAYS)
    for name in ("frames/0001.exr", "frames/0001.png"):
        assert (again / name).read_bytes() == (out / name).read_bytes(), name


# --- --image, --aovs, --timestamp --------------------------------------------------------


@pytest.mark.slow
def test_image_template_replaces_the_products_and_aovs_add_passes(stage, tmp_path):
    out = tmp_path / "out"
    _ok(str(stage), "--out", str(out), "--settings", "/Render/Second", "--frames", "1:2",
        "--image", "quick/q.####.exr", "--aovs", "P,albedo,reflectivity", "--timestamp",
        *RAYS)  # fmt: skip
    assert [f for f in _files(out) if f.endswith(".exr")] == [
        "quick/q.0001.exr",
        "quick/q.0002.exr",
    ]
    header, channels = read_exr(out / "quick" / "q.0001.exr")
    assert {"R", "Z", "N.x", "id", "P.x", "P.y", "P.z", "albedo.R", "reflectivity"} <= set(channels)
    assert "capDate" in header  # --timestamp
    # P at a pixel of the ball is on its surface and projects back onto that pixel.
    height, width = channels["Z"].shape
    ndc = _project(SPHERE_CENTER, header["worldToNDC"])
    row, col = int(ndc[1] * height), int(ndc[0] * width)
    position = np.array([channels[f"P.{a}"][row, col] for a in "xyz"], dtype=np.float64)
    # (the sphere is drawn as triangles: its facets lie up to ~1 % inside the radius)
    assert np.linalg.norm(position - SPHERE_CENTER) == pytest.approx(SPHERE_RADIUS, rel=0.01)
    back = _project(position, header["worldToNDC"])
    assert abs(back[0] * width - (col + 0.5)) < 0.51 and abs(back[1] * height - (row + 0.5)) < 0.51
    # The floor is the mirror (F = 1), the ball is not.
    ids = element_ids(channels["id"])
    floor = ids == [k for k, v in read_manifest(header).items() if v == "/World/Floor"][0]
    assert (channels["reflectivity"][floor] == 1).all()
    assert channels["reflectivity"][row, col] == 0


@pytest.mark.slow
def test_image_and_aovs_errors_are_one_line(stage, tmp_path):
    outside = tmp_path / "elsewhere" / "x.####.exr"
    line = _one_line_error(
        _cli(str(stage), "--out", str(tmp_path / "a"), "--image", str(outside)), 2
    )
    assert "outside the output directory" in line
    line = _one_line_error(_cli(str(stage), "--out", str(tmp_path / "b"), "--aovs", "P,bogus"), 2)
    assert "bogus" in line
    done = _cli(str(stage), "--out", str(tmp_path / "c"), "--frames", "1:2", "--image", "one.exr")
    assert "no frame token" in _one_line_error(done, 2)
    assert not outside.parent.exists()


@pytest.mark.slow
def test_product_outside_out_and_bad_settings_are_refused(stage, tmp_path):
    done = _cli(str(stage), "--out", str(tmp_path / "a"), "--settings", "/Render/Escape")
    line = _one_line_error(done, 1)
    assert "/Render/Products/Outside" in line and "outside the output directory" in line
    assert not list(Path("/tmp").glob("phrt-outside.*.exr"))
    # --settings naming no prim is a bad option (exit 2), listing the settings there are
    line = _one_line_error(_cli(str(stage), "--out", str(tmp_path / "b"), "--settings", "/Nope"), 2)
    assert "/Nope" in line and "/Render/Second" in line


# --- in-process: multi-part, --overwrite, --resume ---------------------------------------

OPTIONS = RenderOptions(width=64, height=48, budget_ms=None, budget_rays=4000)


def _job(stage: Path, out: Path, frames: str = "1", **kw) -> RenderJob:
    return RenderJob(stage_path=stage, out_dir=out, options=OPTIONS, frames=frames, **kw)


@pytest.mark.slow
def test_multipart_only_when_the_product_asks(stage, tmp_path):
    render_to_directory(_job(stage, tmp_path / "parts", settings="/Render/Parts"))
    image = OpenEXR.File(str(tmp_path / "parts" / "parts.0001.exr"), header_only=True)
    assert [p.name() for p in image.parts] == ["rgba", "depth"]
    render_to_directory(_job(stage, tmp_path / "one", settings="/Render/Second"))
    single = OpenEXR.File(str(tmp_path / "one" / "beauty.0001.exr"), header_only=True)
    assert len(single.parts) == 1


@pytest.mark.slow
def test_overwrite_removes_this_runs_product_files_only(stage, tmp_path):
    """--overwrite deletes the files this run's names give at any frame number, never
    another run's names (which only a file in OUT could tell) nor other files."""
    out = tmp_path / "out"
    render_to_directory(_job(stage, out, "1:2", settings="/Render/Second"))
    (out / "notes.txt").write_text("mine")
    (out / "beauty.final.exr").write_text("not a frame of phrt's")
    with pytest.raises(PhrtError, match="not empty"):
        render_to_directory(_job(stage, out, image="other/o.$F4.exr"))
    render_to_directory(_job(stage, out, settings="/Render/Second", overwrite=True))
    assert "beauty.0002.exr" not in _files(out)  # this run's name at another frame
    assert {"notes.txt", "beauty.final.exr", "beauty.0001.exr"} <= set(_files(out))
    render_to_directory(_job(stage, out, image="other/o.$F4.exr", overwrite=True))
    assert {"beauty.0001.exr", "other/o.0001.exr", "notes.txt"} <= set(_files(out))
    render_to_directory(_job(stage, out, overwrite=True))  # back to the default layout
    assert (out / "other").is_dir()  # --overwrite never deletes a folder
    assert {"frames/0001.exr", "frames/0001.png", "notes.txt"} <= set(_files(out))


def _clashing_settings(stage: Path, path: Path) -> Path:
    """A copy of ``stage`` with /Render/Clash (products ``img.$F4.exr`` and
    ``img.####.exr``: one file at every frame) and /Render/Thousand (``t.$F.exr`` and
    ``t.$F4.exr``: one file from frame 1000 on)."""
    usd = Usd.Stage.Open(str(stage))
    usd.GetRootLayer().Export(str(path))
    usd = Usd.Stage.Open(str(path))
    color = [render_var(usd, "clash_color", "color", "color3h")]
    for settings, names in (("Clash", ("img.$F4.exr", "img.####.exr")),
                            ("Thousand", ("t.$F.exr", "t.$F4.exr"))):  # fmt: skip
        products = [
            _product(usd, f"/Render/Products/{settings}{i}", name, color)
            for i, name in enumerate(names)
        ]
        _settings(usd, f"/Render/{settings}", products)
    usd.GetRootLayer().Save()
    return path


@pytest.mark.slow
def test_probe_products_expanding_to_one_file(stage, tmp_path):
    """Products are compared by the names they expand to at every frame rendered: two
    that meet are refused with exit 2 before any frame renders (OUT is not even made),
    in one line naming both products' prim paths and the frame."""
    clash = _clashing_settings(stage, tmp_path / "clash.usda")
    out = tmp_path / "out"
    line = _one_line_error(
        _cli(str(clash), "--out", str(out), "--settings", "/Render/Clash", "--frames", "1:2"), 2
    )
    assert "/Render/Products/Clash0" in line and "/Render/Products/Clash1" in line
    assert "img.0001.exr" in line and "frame 1" in line
    assert not out.exists()
    line = _one_line_error(_cli(str(clash), "--out", str(out), "--settings", "/Render/Thousand",
                                "--frames", "999:1000"), 2)  # fmt: skip
    assert "/Render/Products/Thousand0" in line and "/Render/Products/Thousand1" in line
    assert "t.1000.exr" in line and "frame 1000" in line
    assert not out.exists()
    # Below 1000 $F and $F4 differ: the same products render.
    render_to_directory(_job(clash, out, "998:999", settings="/Render/Thousand"))
    assert {"t.998.exr", "t.0998.exr", "t.999.exr", "t.0999.exr"} <= set(_files(out))
    # Names may meet at different frames too: a.1$F3.exr at 1 is a.$F4.exr at 1001.
    spec = RenderSettingsSpec(
        "/R", (8, 8), None, tuple(RenderProductSpec(f"/R/P{i}", name, "raster", None, None, ())
                                  for i, name in enumerate(("a.1$F3.exr", "a.$F4.exr")))
    )  # fmt: skip
    plan = plan_images(spec, tmp_path)
    plan.check_files([1.0, 2.0])
    with pytest.raises(BadOption, match=r"/R/P0.* and /R/P1.*a\.1001\.exr at frames 1 and 1001"):
        plan.check_files([1.0, 1001.0])


@pytest.mark.slow
def test_resume_refuses_other_products(stage, tmp_path):
    out = tmp_path / "out"
    render_to_directory(_job(stage, out, settings="/Render/Second"))
    with pytest.raises(PhrtError, match="products"):
        render_to_directory(_job(stage, out, settings="/Render/Second", aovs=("P",), resume=True))
    with pytest.raises(PhrtError, match="differs from the interrupted run"):
        render_to_directory(_job(stage, out, resume=True))  # the stage's own settings


@pytest.mark.slow
def test_cluster_chunks_write_the_same_product_files(stage, tmp_path):
    from phrt_usd.cluster import plan_chunks, render_chunk
    from phrt_usd.run.render_job import prepare_job
    from phrt_usd.usd.stage import open_stage

    render_to_directory(_job(stage, tmp_path / "whole", "1:2", settings="/Render/Second"))
    job = _job(stage, tmp_path / "chunks", "1:2", settings="/Render/Second")
    job, _, _ = prepare_job(job, open_stage(stage))  # as run_render_on_cluster sends it
    assert job.camera == "/World/Camera2" and job.options.width == PRODUCT_RES[0]
    for chunk in plan_chunks(str(stage), 2, 2, 0):
        render_chunk(chunk, job)
    for name in ("beauty.0001.exr", "beauty.0002.exr"):
        whole = (tmp_path / "whole" / name).read_bytes()
        assert (tmp_path / "chunks" / name).read_bytes() == whole, name


# --- reading settings and planning files -------------------------------------------------


def test_read_render_settings_choice_and_bad_prims(stage):
    usd = Usd.Stage.Open(str(stage))
    assert read_render_settings(usd).path == "/Render/Settings"  # renderSettingsPrimPath
    second = read_render_settings(usd, "/Render/Second")
    assert [p.product_name for p in second.products] == ["beauty.$F4.exr"]
    assert second.products[0].resolution == PRODUCT_RES and second.resolution == SETTINGS_RES
    assert [v.source_name for v in second.products[0].vars] == [
        "color", "depth", "normal", "primId"
    ]  # fmt: skip
    with pytest.raises(BadOption, match="not an absolute prim path"):
        read_render_settings(usd, "Render/Second")
    with pytest.raises(PhrtError, match="/World/Ball"):
        read_render_settings(usd, "/World/Ball")
    bad = Usd.Stage.CreateInMemory()
    settings = UsdRender.Settings.Define(bad, "/R")
    settings.CreateProductsRel().SetTargets(["/World"])
    UsdGeom.Xform.Define(bad, "/World")
    with pytest.raises(PhrtError, match=r"/R\.products: target /World is not a RenderProduct"):
        read_render_settings(bad)


def test_frame_tokens_expand_and_match():
    assert expand("beauty.$F4.exr", 12) == "beauty.0012.exr"
    assert expand("b.${F3}.exr", 7) == "b.007.exr"
    assert expand("b.$F.exr", 7) == "b.7.exr"
    assert expand("b.####.exr", -3) == "b.-003.exr"
    assert expand("b.%04d.exr", 12.5) == "b.0012.500.exr"
    assert expand("b.%d.exr", 101) == "b.101.exr"
    pattern = template_pattern("shot/b.$F4.exr")
    assert pattern.match("shot/b.0012.exr") and pattern.match("shot/b.0012.500.exr")
    assert not pattern.match("shot/b.final.exr") and not pattern.match("shot/bx0012.exr")


def test_names_must_stay_in_out_and_be_images(tmp_path):
    out = tmp_path / "out"
    assert relative_template(out, "a/b.$F4.exr", "p") == "a/b.$F4.exr"
    assert relative_template(out, str(out / "x.####.exr"), "p") == "x.####.exr"
    for bad, why in (
        ("/abs/x.exr", "outside the output directory"),
        ("../x.exr", "no '..'"),
        ("a/../../x.exr", "no '..'"),
        ("x.tif", ".exr or .png"),
        ("", "empty"),
    ):
        with pytest.raises(PhrtError, match=why):
            relative_template(out, bad, "/Render/P.productName")


def test_vars_phrt_cannot_write_are_named():
    from phrt_usd.usd.render_settings import RenderVarSpec

    def plan(*variables, name="x.$F4.exr"):
        product = RenderProductSpec("/R/P", name, "raster", None, None, tuple(variables))
        return plan_images(RenderSettingsSpec("/R", (8, 8), None, (product,)), Path("/o"))

    with pytest.raises(PhrtError, match=r"/R/V: sourceName 'st' \(raw\) is not a pass"):
        plan(RenderVarSpec("/R/V", "st", "raw", "float2"))
    with pytest.raises(PhrtError, match="dataType int cannot hold normal"):
        plan(RenderVarSpec("/R/V", "N", "raw", "int"))
    with pytest.raises(PhrtError, match="channel N.x is also written by /R/A"):
        plan(
            RenderVarSpec("/R/A", "N", "raw", "normal3f"),
            RenderVarSpec("/R/B", "normal", "raw", "normal3h"),
        )
    with pytest.raises(PhrtError, match="a .png holds the color var only"):
        plan(RenderVarSpec("/R/D", "depth", "raw", "float"), name="x.$F4.png")
    renamed = var_channels(RenderVarSpec("/R/V", "N", "raw", "normal3h", aov_name="Nworld"))
    assert [(c.name, c.storage) for c in renamed] == [
        ("Nworld.x", "half"), ("Nworld.y", "half"), ("Nworld.z", "half")
    ]  # fmt: skip
    beauty = var_channels(RenderVarSpec("/R/C", "C.*", "lpe", "color3f"))
    assert [c.name for c in beauty] == ["R", "G", "B", "A"]
    # With no vars a product gets the default layout's channels.
    assert [c.name for c in plan().products[0].channels] == [
        "R",
        "G",
        "B",
        "A",
        "Z",
        "id",
        "traced",
    ]
