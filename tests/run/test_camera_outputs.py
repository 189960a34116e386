"""What the camera's UsdRender settings do to a run's outputs: ``dataWindowNDC`` crops every
written file (EXR display/data windows, PNG pixels), the EXR camera matrices follow the
aperture offsets, the selection metrics project through the same window; and the
validation/camera-resolution rules that read the same settings.

The stage: a unit square (z = 0, facing +Z, element "Square") and a small marker square
(side 0.1, at ``MARKER``, 0.1 in front of it) seen by a camera at z = 1.25 looking down -Z:
focal 20 over a square 20 x 20 aperture with offsets (2.5, 1.25), rendered at 64 x 48
(4:3, expandAperture). The window is then x in 0.125 +- 2/3, y in 0.0625 +- 0.5
(``CameraFrame.image_window``): the image moves 6 px left and 3 px down against a centred
camera, so a centred matrix misses the marker by ~6.7 px.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender
from scenes import render_var

from phrt_usd.engine.renderer import RenderOptions
from phrt_usd.errors import PhrtError
from phrt_usd.model.scene import CameraFrame
from phrt_usd.run import render_job
from phrt_usd.run.images import element_ids, read_exr, read_manifest, read_preview_png
from phrt_usd.run.render_job import RenderJob, prepare_job, render_to_directory
from phrt_usd.select.metrics import box_screen_area, centrality
from phrt_usd.usd import rules, schema
from phrt_usd.usd.stage import open_stage

W, H = 64, 48
OFFSETS = (2.5, 1.25)
MARKER = np.array([0.2, -0.1, 0.1])  # world metres (1 m per unit)
OPTIONS = RenderOptions(width=W, height=H, mode="raster", budget_ms=None)
#: dataWindowNDC of the crop: columns whose centres are in [0.25, 0.75] * 64 (16..47),
#: rows (down) whose centres are in [1 - 0.875, 1 - 0.25] * 48 = [6, 36] (6..35).
CROP_NDC = (0.25, 0.25, 0.75, 0.875)
CROP = (16, 6, 48, 36)  # col0, row0, col1, row1 (half-open)


def _quad(stage: Usd.Stage, path: str, centre, half: float) -> UsdGeom.Mesh:
    x, y, z = centre
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(
        [(x - half, y - half, z), (x + half, y - half, z), (x + half, y + half, z),
         (x - half, y + half, z)]
    )  # fmt: skip
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    return mesh


def _stage(path: Path, data_window=None) -> Path:
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(1)
    _quad(stage, "/World/Square", (0.0, 0.0, 0.0), 0.5)
    _quad(stage, "/World/Marker", MARKER, 0.05)
    light = UsdLux.DistantLight.Define(stage, "/World/Sun")
    light.CreateIntensityAttr(1.0)
    cam = UsdGeom.Camera.Define(stage, "/World/Cam")
    cam.CreateFocalLengthAttr(20.0)
    cam.CreateHorizontalApertureAttr(20.0)
    cam.CreateVerticalApertureAttr(20.0)
    cam.CreateHorizontalApertureOffsetAttr(OFFSETS[0])
    cam.CreateVerticalApertureOffsetAttr(OFFSETS[1])
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 10.0))
    cam.AddTranslateOp().Set(Gf.Vec3d(0, 0, 1.25))
    variables = []
    for name, source, data_type in (
        ("color", "color", "color3h"),
        ("depth", "depth", "float"),
        ("id", "primId", "int"),
        ("N", "normal", "normal3f"),
    ):
        variables.append(render_var(stage, name, source, data_type))
    multi = UsdRender.Product.Define(stage, "/Render/Products/Multi")
    multi.CreateProductNameAttr("multi.$F4.exr")
    multi.CreateOrderedVarsRel().SetTargets(variables)
    multi.GetPrim().CreateAttribute(
        "driver:parameters:OpenEXR:multipart", Sdf.ValueTypeNames.Bool
    ).Set(True)
    png = UsdRender.Product.Define(stage, "/Render/Products/Preview")
    png.CreateProductNameAttr("preview.$F4.png")
    png.CreateOrderedVarsRel().SetTargets(variables[:1])
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateResolutionAttr(Gf.Vec2i(W, H))
    settings.CreateCameraRel().SetTargets([cam.GetPath()])
    settings.CreateProductsRel().SetTargets([multi.GetPath(), png.GetPath()])
    if data_window is not None:
        settings.CreateDataWindowNDCAttr(Gf.Vec4f(*data_window))
    stage.GetRootLayer().Save()
    return path


def _render(stage: Path, out: Path) -> Path:
    render_to_directory(
        RenderJob(stage, out, OPTIONS, frames="1", aovs=("P",), checkpoint_every=100)
    )
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> tuple[Path, Path]:
    """(full run, cropped run) of the same stage, but for dataWindowNDC."""
    root = tmp_path_factory.mktemp("camera_outputs")
    full = _render(_stage(root / "full.usda"), root / "full")
    crop = _render(_stage(root / "crop.usda", CROP_NDC), root / "crop")
    return full, crop


def _window(header, name: str) -> tuple:
    low, high = header[name]
    return (int(low[0]), int(low[1])), (int(high[0]), int(high[1]))


def _project(point: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """A world point through a header matrix (row vectors, as Imath multiplies them)."""
    row = np.append(point, 1.0) @ np.asarray(matrix, dtype=np.float64)
    return row[:3] / row[3]


@pytest.mark.slow
def test_data_window_crops_every_channel_and_sets_the_exr_windows(runs):
    full, crop = runs
    header, whole = read_exr(full / "multi.0001.exr")
    cropped_header, part = read_exr(crop / "multi.0001.exr")
    col0, row0, col1, row1 = CROP
    # The full render: both windows the whole image (OpenEXR inclusive corners).
    assert _window(header, "displayWindow") == _window(header, "dataWindow") == ((0, 0), (63, 47))
    # The crop: displayWindow the whole image, dataWindow the pixels held.
    assert _window(cropped_header, "displayWindow") == ((0, 0), (W - 1, H - 1))
    assert _window(cropped_header, "dataWindow") == ((col0, row0), (col1 - 1, row1 - 1))
    assert set(part) == set(whole)  # every var and the --aovs P, in every part
    for name, values in part.items():
        assert values.shape == (row1 - row0, col1 - col0), name
        # Same stage, same raster render: the crop is the full image's pixels exactly.
        np.testing.assert_array_equal(values, whole[name][row0:row1, col0:col1], err_msg=name)
        for r, c in ((0, 0), (0, -1), (-1, 0), (-1, -1)):  # the data window's corners
            assert values[r, c] == whole[name][(row0, row1 - 1)[r], (col0, col1 - 1)[c]]
    # The crop covers the square and the background both (not a trivial region).
    ids = element_ids(part["id"])
    assert (ids >= 0).any() and (ids < 0).any()
    # The manifest names the ids in the file only.
    assert set(read_manifest(cropped_header)) == {int(i) for i in np.unique(ids) if i >= 0}


@pytest.mark.slow
def test_data_window_crops_the_png_products(runs):
    full, crop = runs
    whole = read_preview_png(full / "preview.0001.png")
    part = read_preview_png(crop / "preview.0001.png")
    col0, row0, col1, row1 = CROP
    assert whole.shape == (H, W, 3)
    np.testing.assert_array_equal(part, whole[row0:row1, col0:col1])


@pytest.mark.slow
def test_header_world_to_ndc_follows_the_aperture_offsets(runs):
    full, crop = runs
    header, channels = read_exr(full / "multi.0001.exr")
    ids = element_ids(channels["id"])
    marker = next(i for i, p in read_manifest(header).items() if p == "/World/Marker")
    rows, cols = np.nonzero(ids == marker)
    # The marker's pixel centres (+0.5) average to its projected centre: its edges cover
    # ~4.8 px each way, so the covered centres are within half a pixel of symmetric.
    seen = np.array([cols.mean() + 0.5, rows.mean() + 0.5])
    ndc = _project(MARKER, header["worldToNDC"])
    np.testing.assert_allclose(ndc[:2] * [W, H], seen, atol=0.5)
    # The one rule: the header matrix is CameraFrame.project (float32 matrix: 1e-4 px).
    camera = open_stage(full.parent / "full.usda").camera(1.0)
    np.testing.assert_allclose(ndc[:2] * [W, H], camera.project(MARKER[None], W, H)[0, :2],
                               atol=1e-3)  # fmt: skip
    # The cropped file's matrix is the same (NDC of the display window): the marker's
    # pixel there is its full-image pixel less the data window's origin.
    cropped_header, part = read_exr(crop / "multi.0001.exr")
    np.testing.assert_allclose(cropped_header["worldToNDC"], header["worldToNDC"])
    col, row = (ndc[:2] * [W, H]).astype(int)
    assert element_ids(part["id"])[row - CROP[1], col - CROP[0]] == marker


def _offset_camera(offset_x: float) -> CameraFrame:
    world_from_camera = np.eye(4)
    world_from_camera[2, 3] = 1.25
    return CameraFrame(world_from_camera, 20.0, 20.0, 0.1, 10.0, 20.0, offset_x, 0.0)


def test_screen_area_and_centrality_use_the_offset_window():
    lo, hi = np.array([[-0.4, -0.4, 0.0]]), np.array([[0.4, 0.4, 0.0]])
    centred, shifted = _offset_camera(0.0), _offset_camera(10.0)
    # Centred: x in +-2/3, y in +-0.5; the box's edges at tan +-0.4 / 1.25 = +-0.32:
    # columns (+-0.32 / (2/3) + 1) * 32 = 16.64..47.36, rows (1 -+ 0.32 / 0.5) * 24 =
    # 8.64..39.36: 30.72 x 30.72 px.
    area = box_screen_area(lo, hi, [centred, shifted], W, H)
    assert area[0, 0] == pytest.approx(30.72 * 30.72, rel=1e-9)
    # Offset 10 / 20 = 0.5: x in 0.5 +- 2/3; columns ((+-0.32 - 0.5) / (2/3) + 1) * 32 =
    # -7.36 (clipped to 0) .. 23.36: 23.36 x 30.72 px.
    assert area[1, 0] == pytest.approx(23.36 * 30.72, rel=1e-9)
    # P of the box centre: ndc_x = -0.5 / (2/3) = -0.75 → 1 - 0.75.
    p = centrality(np.zeros((1, 3)), shifted, W, H)
    assert p[0] == pytest.approx(0.25, rel=1e-9)
    assert centrality(np.zeros((1, 3)), centred, W, H)[0] == pytest.approx(1.0)


def test_an_empty_data_window_is_refused_before_rendering(tmp_path):
    # Columns whose centres are in [0, 0.005 * 64 = 0.32]: none.
    stage = _stage(tmp_path / "empty.usda", (0.0, 0.0, 0.005, 1.0))
    with pytest.raises(PhrtError, match=r"^/Render/Settings\.dataWindowNDC: .* holds no pixel"):
        render_to_directory(RenderJob(stage, tmp_path / "out", OPTIONS, frames="1"))
    assert not (tmp_path / "out" / "multi.0001.exr").exists()


def _purpose_stage(included) -> Usd.Stage:
    """A floor, and a render-purpose reflector with K = -1 (an error wherever it is read)."""
    stage = Usd.Stage.CreateInMemory()
    cam = UsdGeom.Camera.Define(stage, "/World/Cam")
    cam.AddTranslateOp().Set(Gf.Vec3d(0, 0, 5))
    _quad(stage, "/World/Floor", (0.0, 0.0, 0.0), 1.0)
    bad = _quad(stage, "/World/RenderOnly", (0.0, 0.0, 0.5), 0.2)
    UsdGeom.Imageable(bad).CreatePurposeAttr(UsdGeom.Tokens.render)
    schema.apply_reflector(bad.GetPrim(), priority=-1.0)
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    if included is not None:
        settings.CreateIncludedPurposesAttr(included)
    return stage


def _geometry_errors(stage: Usd.Stage) -> list[str]:
    return [
        i.line() for i in rules.render_issues(stage) if i.rule == rules.GEOMETRY
        and i.severity == rules.ERROR
    ]  # fmt: skip


def test_validation_reads_the_settings_included_purposes():
    # Fallback purposes (default, render): the render-purpose prim is read, its K refused.
    assert any("/World/RenderOnly" in line for line in _geometry_errors(_purpose_stage(None)))
    # includedPurposes = [default]: the render draws no render-purpose prim, nor does
    # validation check it (nor does read_stage refuse it).
    issues = rules.render_issues(_purpose_stage(["default"]))
    assert not any("/World/RenderOnly" in i.line() for i in issues)


def _holed_reflector(holes) -> Usd.Stage:
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.Camera.Define(stage, "/World/Cam").AddTranslateOp().Set(Gf.Vec3d(0, 0, 5))
    mesh = UsdGeom.Mesh.Define(stage, "/World/Mirror")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0), (2, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4, 4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 1, 4, 5, 2])
    if holes is not None:
        mesh.CreateHoleIndicesAttr(holes)
    schema.apply_reflector(mesh.GetPrim())
    return stage


def _zero_area(stage: Usd.Stage) -> bool:
    return any("zero area" in i.message for i in rules.render_issues(stage))


def test_zero_area_rule_does_not_count_hole_faces():
    assert not _zero_area(_holed_reflector(None))
    assert not _zero_area(_holed_reflector([1]))  # face 0 (1 x 1) is still drawn
    assert _zero_area(_holed_reflector([0, 1]))  # every face a hole: nothing is drawn


def test_camera_name_is_resolved_once(tmp_path, monkeypatch):
    stage = _stage(tmp_path / "named.usda")
    scene = open_stage(stage, camera="Cam")
    assert scene.camera_path == "/World/Cam"

    def second_read(*args, **kwargs):
        raise AssertionError("prepare_job read the stage again for the same camera")

    monkeypatch.setattr(render_job, "read_stage", second_read)
    job, same, _ = prepare_job(RenderJob(stage, tmp_path / "out", OPTIONS, camera="Cam"), scene)
    assert same is scene
    assert job.camera == "/World/Cam"  # workers of a cluster read the path
