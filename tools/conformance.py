"""Conformance run: render third-party USD assets and put each beside its own screenshot.

    uv run python tools/conformance.py ASSETS_DIR OUT_DIR [--list FILE | --glob PATTERN]
        [--resolution 256x192] [--mode raster,rt] [--view AZ,EL] [--timeout S]
        [--no-isolate]

For each asset stage (the lines of ``--list``, else the files ``--glob`` matches under
ASSETS_DIR, by default ``**/*.usd*``):

1. the stage is opened read-only; if it has no ``UsdGeomCamera``, a wrapper layer
   ``OUT/wrappers/NAME.usda`` sublayers it (copying its ``upAxis``, ``metersPerUnit`` and
   time range, which a sublayer does not carry) and adds ``/ConformanceCamera`` framing the
   bounds of its default and render purpose geometry (``UsdGeom.BBoxCache``): it looks at
   the bounds' centre from azimuth/elevation ``--view`` about the up axis, at the distance
   where the bounding sphere fits the smaller field of view. The asset itself is never
   written to;
2. one frame (the stage's start time code, else 0) is rendered in each ``--mode`` through
   ``phrt_usd.open`` (arrays only), recording the stage's warnings, the wall time and the
   covered fraction of the image; a failure is recorded as its one-line error and the run
   goes on with the next asset (each asset renders in a child process by default, so a
   crash or a hang past ``--timeout`` is recorded too);
3. ``OUT/NAME.png``: a contact sheet of the renders and the asset's reference picture
   (the list's third column, else the first ``screenshots/``, ``screenshot/`` or
   ``thumbnails/`` image beside the stage, fitted into a panel), each 256 px wide and
   labelled;
4. ``OUT/index.md`` (a markdown table: asset, status, camera, warnings, time, coverage)
   and ``OUT/results.json`` (the same, every warning in full).

List file lines: ``NAME | STAGE | REFERENCE`` (paths relative to ASSETS_DIR; REFERENCE may
be empty; ``#`` starts a comment).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

#: Width of each contact-sheet panel in pixels (the sheet is len(modes) + 1 panels).
PANEL_WIDTH = 256
#: Height of the label strip under each panel, and the gap between panels, in pixels.
LABEL_HEIGHT, GAP = 18, 4
#: Focal length and horizontal aperture of the wrapper camera (mm): a 36 mm-wide film back
#: at 50 mm, about 40 degrees horizontally. Only their ratio matters.
FOCAL_MM, HAPERTURE_MM = 50.0, 36.0
#: The bounding sphere fills this fraction of the smaller half field of view, so the
#: asset does not touch the frame's edges.
FILL = 0.9
#: Image suffixes accepted as reference pictures, in order of preference.
PICTURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".gif")
#: Folders beside a stage where assets keep their own pictures, in order of preference.
PICTURE_FOLDERS = ("screenshots", "screenshot", "thumbnails")
#: The wrapper camera's clipping range: near at this fraction of its distance to the
#: bounds' centre, far this many bounds diagonals beyond the bounds (depth precision of a
#: 1:1000 range is ample for the raster's depth buffer).
CLIP_NEAR, CLIP_FAR = 1e-2, 10.0
#: Camera prim the wrapper layer adds.
WRAPPER_CAMERA = "/ConformanceCamera"


@dataclass
class Asset:
    name: str
    stage: Path
    reference: Path | None
    variants: tuple[str, ...] = ()  # "PRIM:SET=NAME" selections the wrapper authors
    view: tuple[float, float] | None = None  # the wrapper camera's (azimuth, elevation)
    exposure: float = 0.0  # EV, ``--exposure`` of the render (the render's warning's advice)


@dataclass
class ModeResult:
    mode: str
    seconds: float | None = None
    covered: float | None = None  # fraction of pixels with alpha > 0
    error: str | None = None
    traceback: str | None = None  # for errors that are not the renderer's one-line refusals


@dataclass
class AssetResult:
    name: str
    stage: str
    reference: str | None
    camera: str = ""  # "own", "wrapper" or "" (not reached)
    variants: list[str] = field(default_factory=list)
    exposure: float = 0.0
    time_code: float | None = None
    warnings: list[str] = field(default_factory=list)
    modes: list[ModeResult] = field(default_factory=list)
    error: str | None = None  # the asset could not be prepared (or its child failed)
    sheet: str | None = None
    # fraction of pixels covered in both or neither of the first two modes that rendered
    agreement: float | None = None

    @property
    def status(self) -> str:
        if self.error or not self.modes:
            return "failed"
        if any(m.error for m in self.modes):
            return "partly failed"
        return "warnings" if self.warnings else "ok"


# --- finding assets ----------------------------------------------------------------------


def read_list(assets_dir: Path, list_file: Path) -> list[Asset]:
    """The assets of a list file: ``NAME | STAGE | REFERENCE | VARIANTS | VIEW | EV``
    lines (VARIANTS: ``PRIM:SET=NAME`` selections separated by spaces; VIEW: ``AZ,EL``
    degrees of the wrapper camera, else ``--view``; EV: the render's ``--exposure``, 0
    when empty)."""
    assets = []
    for number, line in enumerate(list_file.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        cells = [c.strip() for c in line.split("|")]
        if len(cells) < 2 or not cells[0] or not cells[1]:
            sys.exit(
                f"{list_file}:{number}: expected NAME | STAGE [| REF [| VARIANTS [| VIEW [| EV]]]]"
            )
        stage = assets_dir / cells[1]
        reference = assets_dir / cells[2] if len(cells) > 2 and cells[2] else None
        variants = tuple(cells[3].split()) if len(cells) > 3 else ()
        for variant in variants:
            if not parse_variant(variant):
                sys.exit(f"{list_file}:{number}: variant {variant!r} is not PRIM:SET=NAME")
        view = parse_view(cells[4]) if len(cells) > 4 and cells[4] else None
        if len(cells) > 4 and cells[4] and view is None:
            sys.exit(f"{list_file}:{number}: view {cells[4]!r} is not AZ,EL (|EL| < 89)")
        try:
            exposure = float(cells[5]) if len(cells) > 5 and cells[5] else 0.0
        except ValueError:
            exposure = math.nan
        if not math.isfinite(exposure):
            sys.exit(f"{list_file}:{number}: EV {cells[5]!r} is not a finite number")
        assets.append(
            Asset(cells[0], stage, reference or find_reference(stage), variants, view, exposure)
        )
    return assets


def glob_assets(assets_dir: Path, pattern: str) -> list[Asset]:
    """Every stage file ``pattern`` matches under ``assets_dir``, named by its stem (the
    relative path, with / as _, where two stems collide)."""
    stages = sorted(p for p in assets_dir.glob(pattern) if p.is_file())
    stems = [p.stem for p in stages]
    assets = []
    for path, stem in zip(stages, stems, strict=True):
        name = stem
        if stems.count(stem) > 1:
            name = "_".join(path.relative_to(assets_dir).with_suffix("").parts)
        assets.append(Asset(name, path, find_reference(path)))
    return assets


def find_reference(stage: Path) -> Path | None:
    """The asset's own picture: ``screenshots/`` (or ``screenshot/``) beside the stage,
    the ones naming the stage first, else ``thumbnails/STEM.png``; None when there is none."""
    folder = stage.parent
    for sub in PICTURE_FOLDERS:
        pictures = sorted(
            p for p in (folder / sub).glob("*") if p.suffix.lower() in PICTURE_SUFFIXES
        )
        if sub == "thumbnails":
            pictures = [p for p in pictures if p.stem == stage.stem]
        named = [p for p in pictures if stage.stem.lower() in p.stem.lower()]
        if named or pictures:
            return (named or pictures)[0]
    return None


# --- the wrapper camera ------------------------------------------------------------------


def parse_view(text: str) -> tuple[float, float] | None:
    """(azimuth, elevation) degrees of ``AZ,EL``; None if malformed. The elevation stays
    off the poles, where the up axis gives no image right direction."""
    try:
        view = tuple(float(v) for v in text.split(","))
    except ValueError:
        return None
    ok = len(view) == 2 and math.isfinite(view[0]) and abs(view[1]) < 89.0
    return view if ok else None


def parse_variant(text: str) -> tuple[str, str, str] | None:
    """(prim path, variant set, selection) of ``PRIM:SET=NAME``; None if malformed."""
    prim, _, rest = text.partition(":")
    variant_set, _, name = rest.partition("=")
    return (prim, variant_set, name) if prim.startswith("/") and variant_set and name else None


def has_camera(stage) -> bool:
    from pxr import Usd, UsdGeom

    predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
    return any(p.IsA(UsdGeom.Camera) for p in Usd.PrimRange(stage.GetPseudoRoot(), predicate))


def frame_time(stage) -> float:
    """The time code rendered: the stage's start time code if it authors a range, else 0."""
    return float(stage.GetStartTimeCode()) if stage.HasAuthoredTimeCodeRange() else 0.0


def framing_camera(
    stage, time_code: float, aspect: float, azimuth_deg: float, elevation_deg: float
) -> tuple[np.ndarray, float, float, float]:
    """(camera-to-world 4x4 row-vector matrix, vertical aperture mm, near, far) of a camera
    looking at the centre of the stage's bounds (``gprim_bounds``) from
    ``azimuth_deg``/``elevation_deg`` about the up axis, at the nearest distance where the
    8 corners of the bounds project inside ``FILL`` of the image window. The clipping range
    is wide (``CLIP_NEAR`` of the distance to ``CLIP_FAR`` sizes beyond): skinned or
    animated geometry may leave the bounds, and clipping it would hide that.

    Raises ValueError when the stage has no finite, non-empty bounds."""
    from pxr import Gf, UsdGeom

    box = gprim_bounds(stage, time_code)
    if box.IsEmpty():
        raise ValueError("the stage has no geometry bounds to frame")
    low, high = np.array(box.GetMin()), np.array(box.GetMax())
    if not (np.isfinite(low).all() and np.isfinite(high).all()):
        raise ValueError(f"the stage's bounds are not finite: {box}")
    centre = (low + high) / 2.0
    # a point still needs a positive size to place the camera at
    size = max(float(np.linalg.norm(high - low)), 1e-6 * max(1.0, float(np.abs(centre).max())))
    vaperture = HAPERTURE_MM / aspect
    tan_h, tan_v = HAPERTURE_MM / 2.0 / FOCAL_MM * FILL, vaperture / 2.0 / FOCAL_MM * FILL
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    # (right, up, towards the eye) in the up-axis convention: Y-up looks from +Z, Z-up from
    # -Y (as USD's own viewers frame a stage)
    if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z:
        world_up, world_front, world_right = np.eye(3)[2], -np.eye(3)[1], np.eye(3)[0]
    else:
        world_up, world_front, world_right = np.eye(3)[1], np.eye(3)[2], np.eye(3)[0]
    towards = (
        math.cos(el) * (math.sin(az) * world_right + math.cos(az) * world_front)
        + math.sin(el) * world_up
    )
    right = np.cross(world_up, towards)
    right /= max(np.linalg.norm(right), 1e-12)  # elevation of +-90 deg: no right, any works
    up = np.cross(towards, right)
    corners = np.array([[x, y, z] for x in (low[0], high[0]) for y in (low[1], high[1])
                        for z in (low[2], high[2])]) - centre  # fmt: skip
    x, y, z = corners @ right, corners @ up, corners @ towards
    # a corner at depth (d - z) projects inside the window when |x| <= tan_h (d - z)
    distance = float(np.max(np.maximum(z + np.abs(x) / tan_h, z + np.abs(y) / tan_v)))
    distance = max(distance, float(z.max()) + 0.05 * size)  # the eye outside the bounds
    eye = centre + distance * towards
    view = Gf.Matrix4d().SetLookAt(Gf.Vec3d(*eye), Gf.Vec3d(*centre), Gf.Vec3d(*world_up))
    # never past the nearest corner (the eye is outside the bounds), never zero
    near = max(min(CLIP_NEAR * distance, 0.5 * (distance - float(z.max()))), 1e-6 * distance)
    far = distance - float(z.min()) + CLIP_FAR * size
    return np.array(view.GetInverse()), vaperture, near, far


def gprim_bounds(stage, time_code: float):
    """The world-space ``Gf.Range3d`` of what the stage draws: every default or render
    purpose gprim's extent computed from its points (``ComputeExtentFromPlugins``: an
    authored ``extent`` may be wrong, empty or inverted) and every PointInstancer's bound
    (``UsdGeom.BBoxCache``), instance proxies included.

    Gprim by gprim rather than the pseudo-root's bound: a ``SkelRoot``'s computed extent is
    its skeleton's joints (UsdSkel's extent rule), which can be a sliver of the skinned mesh;
    a skinned mesh's own points are its rest pose, the closer estimate."""
    from pxr import Gf, Usd, UsdGeom

    purposes = [UsdGeom.Tokens.default_, UsdGeom.Tokens.render]
    cache = UsdGeom.BBoxCache(time_code, purposes, useExtentsHint=True)
    xforms = UsdGeom.XformCache(time_code)
    box = Gf.Range3d()
    predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
    prims = iter(Usd.PrimRange(stage.GetPseudoRoot(), predicate))
    for prim in prims:
        if prim.IsA(UsdGeom.PointInstancer):
            box.UnionWith(cache.ComputeWorldBound(prim).ComputeAlignedRange())
            prims.PruneChildren()  # the prototypes are placed by the instancer
        elif prim.IsA(UsdGeom.Gprim):
            imageable = UsdGeom.Imageable(prim)
            if imageable.ComputePurpose() not in purposes:
                continue
            if imageable.ComputeVisibility(time_code) == UsdGeom.Tokens.invisible:
                continue
            extent = UsdGeom.Boundable.ComputeExtentFromPlugins(
                UsdGeom.Boundable(prim), Usd.TimeCode(time_code)
            )
            if extent is None or len(extent) != 2:
                box.UnionWith(cache.ComputeWorldBound(prim).ComputeAlignedRange())
                continue
            local = Gf.Range3d(Gf.Vec3d(*extent[0]), Gf.Vec3d(*extent[1]))
            world = Gf.BBox3d(local, xforms.GetLocalToWorldTransform(prim))
            box.UnionWith(world.ComputeAlignedRange())
    return box


def wrapper_stage(asset_stage, asset_path: Path, variants):
    """An in-memory stage whose root layer sublayers ``asset_path`` and authors the
    ``variants`` selections (over prims), with the asset's ``upAxis``, ``metersPerUnit``
    and time range (stage metadata a sublayer does not carry)."""
    from pxr import Sdf, Usd

    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.subLayerPaths.append(str(asset_path.resolve()))
    stage = Usd.Stage.Open(layer, Usd.Stage.LoadAll)
    for key in ("upAxis", "metersPerUnit"):  # copied as authored, even if invalid
        if asset_stage.HasAuthoredMetadata(key):
            stage.SetMetadata(key, asset_stage.GetMetadata(key))
    if asset_stage.HasAuthoredTimeCodeRange():
        stage.SetStartTimeCode(asset_stage.GetStartTimeCode())
        stage.SetEndTimeCode(asset_stage.GetEndTimeCode())
    stage.SetTimeCodesPerSecond(asset_stage.GetTimeCodesPerSecond())
    default = asset_stage.GetRootLayer().defaultPrim
    if default:
        layer.defaultPrim = default
    for text in variants:
        prim_path, variant_set, name = parse_variant(text)
        prim = stage.GetPrimAtPath(prim_path)
        if not prim or not prim.GetVariantSets().HasVariantSet(variant_set):
            raise ValueError(f"{text}: the asset has no variant set {variant_set} on {prim_path}")
        if name not in prim.GetVariantSet(variant_set).GetVariantNames():
            raise ValueError(f"{text}: no variant {name} in {prim_path}'s {variant_set}")
        stage.OverridePrim(prim_path).GetVariantSet(variant_set).SetVariantSelection(name)
    return stage


def add_camera(stage, resolution: tuple[int, int], view) -> float:
    """Define ``WRAPPER_CAMERA`` framing the stage's bounds. Returns the time code to
    render (the bounds are those at that time)."""
    from pxr import Gf, UsdGeom

    time_code = frame_time(stage)
    width, height = resolution
    matrix, vaperture, near, far = framing_camera(
        stage, time_code, width / height, view[0], view[1]
    )
    camera = UsdGeom.Camera.Define(stage, WRAPPER_CAMERA)
    camera.CreateFocalLengthAttr(FOCAL_MM)
    camera.CreateHorizontalApertureAttr(HAPERTURE_MM)
    camera.CreateVerticalApertureAttr(vaperture)
    camera.CreateClippingRangeAttr(Gf.Vec2f(near, far))
    camera.AddTransformOp().Set(Gf.Matrix4d(matrix.tolist()))
    return time_code


# --- rendering one asset -----------------------------------------------------------------


def render_asset(asset: Asset, out: Path, resolution, modes, view) -> AssetResult:
    """Render ``asset`` in each mode and write its contact sheet ``out/NAME.png``."""
    from pxr import Usd

    import phrt_usd  # noqa: F401 - registers the Phrt schemas before any stage opens
    from phrt_usd.errors import PhrtError

    result = AssetResult(asset.name, str(asset.stage), str(asset.reference or "") or None)
    try:
        if not asset.stage.is_file():
            raise FileNotFoundError(f"{asset.stage}: no such file")
        source = Usd.Stage.Open(str(asset.stage), Usd.Stage.LoadAll)
        if source is None:
            raise RuntimeError(f"{asset.stage}: USD cannot open it")
        result.variants = list(asset.variants)
        result.exposure = asset.exposure
        stage = wrapper_stage(source, asset.stage, asset.variants) if asset.variants else source
        if has_camera(stage):
            camera, result.camera = None, "own"
            result.time_code = frame_time(stage)
        else:
            if stage is source:
                stage = wrapper_stage(source, asset.stage, ())
            result.time_code = add_camera(stage, resolution, asset.view or view)
            camera, result.camera = WRAPPER_CAMERA, "wrapper"
        if stage is source:
            stage_file = asset.stage
        else:  # the wrapper layer, in OUT: the asset's own files are never written
            stage_file = out / "wrappers" / f"{asset.name}.usda"
            stage_file.parent.mkdir(parents=True, exist_ok=True)
            stage.GetRootLayer().comment = f"conformance wrapper of {asset.stage.name}"
            stage.GetRootLayer().Export(str(stage_file))
        del source, stage
    except Exception as error:  # noqa: BLE001 - any failure is this asset's record
        result.error = one_line(error)
        return result
    images, covered = {}, {}
    for mode in modes:
        record = ModeResult(mode)
        started = time.perf_counter()
        try:
            with phrt_usd.open(
                str(stage_file), frames=[result.time_code], mode=mode,
                resolution=resolution, camera=camera, budget_ms=math.inf,
                exposure=asset.exposure,
            ) as renderer:  # fmt: skip
                frame = renderer.render(result.time_code)
                for warning in renderer.stage_scene.warnings:
                    if warning not in result.warnings:
                        result.warnings.append(warning)
            record.seconds = time.perf_counter() - started
            covered[mode] = np.asarray(frame.alpha) > 0
            record.covered = float(np.mean(covered[mode]))
            images[mode] = np.asarray(frame.beauty, dtype=np.float32)
        except Exception as error:  # noqa: BLE001 - recorded, the next mode still runs
            record.seconds = time.perf_counter() - started
            record.error = one_line(error)
            if not isinstance(error, PhrtError):
                record.traceback = traceback.format_exc()
        result.modes.append(record)
    if len(covered) >= 2:
        first, second = list(covered.values())[:2]
        result.agreement = float(np.mean(first == second))
    try:
        sheet = out / f"{asset.name}.png"
        write_sheet(sheet, images, modes, asset.reference, resolution)
        result.sheet = sheet.name
    except Exception as error:  # noqa: BLE001
        result.error = f"contact sheet: {one_line(error)}"
    return result


def one_line(error: BaseException) -> str:
    text = " ".join(str(error).split()) or type(error).__name__
    return f"{type(error).__name__}: {text}"


def render_isolated(asset: Asset, out: Path, resolution, modes, view, timeout) -> AssetResult:
    """``render_asset`` in a child process, so that a crash or a hang is this asset's record."""
    record = out / "wrappers" / f"{asset.name}.result.json"
    record.parent.mkdir(parents=True, exist_ok=True)
    record.unlink(missing_ok=True)
    job = {"asset": [asset.name, str(asset.stage), str(asset.reference or ""),
                     list(asset.variants), asset.view, asset.exposure],
           "out": str(out), "resolution": list(resolution), "modes": list(modes),
           "view": list(view), "record": str(record)}  # fmt: skip
    command = [sys.executable, str(Path(__file__).resolve()), "--one", json.dumps(job)]
    fallback = AssetResult(asset.name, str(asset.stage), str(asset.reference or "") or None)
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        fallback.error = f"timed out after {timeout:g} s"
        return fallback
    if done.returncode != 0 or not record.is_file():
        tail = (done.stderr.strip().splitlines() or [f"exit code {done.returncode}"])[-1]
        fallback.error = f"child process failed (exit {done.returncode}): {tail}"
        return fallback
    try:
        data = json.loads(record.read_text())
        data["modes"] = [ModeResult(**m) for m in data["modes"]]
        return AssetResult(**data)
    except (ValueError, TypeError, KeyError) as error:
        fallback.error = f"unreadable result of the child process: {one_line(error)}"
        return fallback


def run_one(job_text: str) -> None:
    job = json.loads(job_text)
    name, stage, reference, variants, own_view, exposure = job["asset"]
    asset = Asset(name, Path(stage), Path(reference) if reference else None, tuple(variants),
                  tuple(own_view) if own_view else None, exposure)  # fmt: skip
    result = render_asset(
        asset, Path(job["out"]), tuple(job["resolution"]), job["modes"], tuple(job["view"])
    )
    Path(job["record"]).write_text(json.dumps(asdict(result)))


# --- the contact sheet -------------------------------------------------------------------


def write_sheet(path: Path, images: dict, modes, reference: Path | None, resolution) -> None:
    """One row: a panel per mode (its render, sRGB previews as the run writes them) and the
    reference picture fitted into a panel, each labelled underneath."""
    import OpenImageIO as oiio

    from phrt_usd.run.images import tonemap_ldr, write_png_atomic

    width, height = resolution
    panel_height = round(PANEL_WIDTH * height / width)
    panels, labels = [], []
    for mode in modes:
        if mode in images:
            panels.append(resize(tonemap_ldr(images[mode]), PANEL_WIDTH, panel_height))
            labels.append(f"phrt {mode}")
        else:
            panels.append(None)
            labels.append(f"phrt {mode}: failed")
    picture = read_picture(reference) if reference is not None else None
    if picture is not None:  # fitted into the panel's box, its aspect kept
        h, w = picture.shape[:2]
        scale = min(PANEL_WIDTH / w, panel_height / h)
        fitted = resize(picture, max(1, round(w * scale)), max(1, round(h * scale)))
        box = np.full((panel_height, PANEL_WIDTH, 3), 0.12, np.float32)
        top, left = (panel_height - fitted.shape[0]) // 2, (PANEL_WIDTH - fitted.shape[1]) // 2
        box[top : top + fitted.shape[0], left : left + fitted.shape[1]] = fitted
        panels.append(box)
        labels.append(f"reference: {reference.name}"[:40])
    else:
        panels.append(None)
        labels.append("no reference picture")
    tallest = max([p.shape[0] for p in panels if p is not None] + [panel_height])
    count = len(panels)
    sheet = np.full(
        (tallest + LABEL_HEIGHT, count * PANEL_WIDTH + (count - 1) * GAP, 3), 0.12, np.float32
    )
    for index, (panel, label) in enumerate(zip(panels, labels, strict=True)):
        x = index * (PANEL_WIDTH + GAP)
        if panel is not None:
            sheet[: panel.shape[0], x : x + PANEL_WIDTH] = panel[:tallest]
        buf = oiio.ImageBuf(sheet)
        oiio.ImageBufAlgo.render_text(buf, x + 3, tallest + LABEL_HEIGHT - 5, label, 13)
        sheet = np.asarray(buf.get_pixels(oiio.FLOAT)).reshape(sheet.shape)
    write_png_atomic(path, np.rint(np.clip(sheet, 0, 1) * 255).astype(np.uint8))


def resize(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W, 3) float32 display values resized to (height, width, 3) (OIIO's filter)."""
    import OpenImageIO as oiio

    source = oiio.ImageBuf(np.ascontiguousarray(pixels, dtype=np.float32))
    roi = oiio.ROI(0, width, 0, height, 0, 1, 0, 3)
    scaled = oiio.ImageBufAlgo.resize(source, roi=roi)
    return np.asarray(scaled.get_pixels(oiio.FLOAT)).reshape(height, width, 3)


def read_picture(path: Path) -> np.ndarray | None:
    """(H, W, 3) float32 display values of an image file's first subimage (alpha composited
    over the sheet's grey); None when it cannot be read."""
    import OpenImageIO as oiio

    image = oiio.ImageInput.open(str(path))
    if image is None:
        return None
    try:
        data = np.asarray(image.read_image(oiio.FLOAT), dtype=np.float32)  # every channel
    finally:
        image.close()
    if data.ndim == 2:
        data = data[..., None]
    rgb = data[..., :3] if data.shape[2] >= 3 else np.repeat(data[..., :1], 3, axis=2)
    if data.shape[2] in (2, 4):
        alpha = data[..., -1:]
        rgb = rgb * alpha + 0.12 * (1 - alpha)
    return np.ascontiguousarray(rgb, dtype=np.float32)


# --- the index ---------------------------------------------------------------------------


def write_index(
    out: Path, results: list[AssetResult], settings: dict, assets_dir: Path | None = None
) -> None:
    """``out/index.md`` and ``out/results.json``. In the index, paths under ``out`` and
    ``assets_dir`` read ``OUT/...`` and ``ASSETS/...`` (the run's folders, wherever they
    were), so a committed index names no machine's paths."""

    def named(text: str) -> str:
        for folder, name in ((out, "OUT"), (assets_dir, "ASSETS")):
            if folder is not None:
                for form in {str(folder.resolve()), str(folder)}:
                    text = text.replace(form + "/", name + "/")
        return text

    rows = [
        "| asset | status | camera | EV | warnings | " + " | ".join(
            f"{m} s / covered" for m in settings["modes"]) + " | coverage agrees |",
        "|---|---|---|---|---|" + "---|" * (len(settings["modes"]) + 1),
    ]  # fmt: skip
    for r in results:
        cells = [f"[{r.name}]({r.sheet})" if r.sheet else r.name, r.status, r.camera or "–",
                 f"{r.exposure:g}"]  # fmt: skip
        notes = [r.error] if r.error else []
        notes += [f"{m.mode}: {m.error}" for m in r.modes if m.error]
        notes += r.warnings
        cells.append("<br>".join(md(named(n)) for n in notes) if notes else "none")
        by_mode = {m.mode: m for m in r.modes}
        for mode in settings["modes"]:
            m = by_mode.get(mode)
            if m is None or m.error:
                cells.append("–")
            else:
                cells.append(f"{m.seconds:.1f} / {100 * m.covered:.0f} %")
        cells.append("–" if r.agreement is None else f"{100 * r.agreement:.2f} %")
        rows.append("| " + " | ".join(cells) + " |")
    header = [
        "# Conformance run",
        "",
        f"Made by `tools/conformance.py` at {settings['resolution']} "
        f"({', '.join(settings['modes'])}), commit {settings['commit']}, "
        f"{settings['date']}. Time: wall seconds of reading the stage and rendering one "
        "frame (a shared machine: indicative only; raster includes creating the OpenGL "
        "context). OUT and ASSETS: the run's output and asset folders. "
        "EV: the render's `--exposure` from the asset list (where the render's "
        "clipping warning advised one). Covered: pixels with geometry. Coverage agrees: "
        "pixels covered in both of the first two modes or in neither.",
        "",
    ]
    (out / "index.md").write_text("\n".join(header + rows) + "\n")
    (out / "results.json").write_text(
        json.dumps({"settings": settings, "assets": [asdict(r) for r in results]}, indent=1)
    )


def md(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def git_commit() -> str:
    """The commit rendered with, and whether the package had uncommitted edits."""
    root = Path(__file__).resolve().parent.parent
    done = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=root
    )
    edits = subprocess.run(
        ["git", "status", "--porcelain", "--", "phrt_usd"], capture_output=True, text=True,
        cwd=root,
    )  # fmt: skip
    commit = done.stdout.strip() or "unknown"
    return commit + (" with uncommitted edits under phrt_usd/" if edits.stdout.strip() else "")


# --- command line ------------------------------------------------------------------------


def parse_resolution(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH, got {text!r}") from None
    if width < 8 or height < 8:
        raise argparse.ArgumentTypeError(f"resolution must be at least 8x8, got {text!r}")
    return width, height


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--one"]:
        run_one(argv[1])
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("assets_dir", type=Path)
    parser.add_argument("out_dir", type=Path)
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--list", type=Path, help="NAME | STAGE | REFERENCE lines")
    which.add_argument("--glob", default="**/*.usd*", help="stages under ASSETS_DIR")
    parser.add_argument("--resolution", type=parse_resolution, default=(256, 192))
    parser.add_argument("--mode", default="raster,rt", help="comma-separated render modes")
    parser.add_argument("--view", default="20,15", help="wrapper camera AZIMUTH,ELEVATION deg")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds per asset")
    parser.add_argument("--no-isolate", action="store_true", help="render in this process")
    args = parser.parse_args(argv)
    modes = [m.strip() for m in args.mode.split(",") if m.strip()]
    view = parse_view(args.view)
    if view is None:
        parser.error(f"--view: expected AZIMUTH,ELEVATION degrees, |EL| < 89: {args.view!r}")
    if not args.assets_dir.is_dir():
        parser.error(f"{args.assets_dir}: not a folder")
    assets = (
        read_list(args.assets_dir, args.list)
        if args.list
        else glob_assets(args.assets_dir, args.glob)
    )
    if not assets:
        parser.error(f"no stages under {args.assets_dir}")
    out = args.out_dir
    if out.resolve() == args.assets_dir.resolve() or args.assets_dir.resolve() in [
        *out.resolve().parents
    ]:
        parser.error("OUT_DIR must not be inside ASSETS_DIR: the assets are read only")
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for asset in assets:
        print(f"{asset.name}: {asset.stage}", file=sys.stderr, flush=True)
        try:
            if args.no_isolate:
                result = render_asset(asset, out, args.resolution, modes, view)
            else:
                result = render_isolated(asset, out, args.resolution, modes, view, args.timeout)
        except Exception as error:  # noqa: BLE001 - last resort: record, go on
            result = AssetResult(asset.name, str(asset.stage), None, error=one_line(error))
            traceback.print_exc()
        print(f"  {result.status}" + (f": {result.error}" if result.error else ""),
              file=sys.stderr, flush=True)  # fmt: skip
        results.append(result)
    settings = {
        "resolution": "x".join(map(str, args.resolution)), "modes": modes,
        "view": list(view), "commit": git_commit(), "date": time.strftime("%Y-%m-%d"),
    }  # fmt: skip
    write_index(out, results, settings, args.assets_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
