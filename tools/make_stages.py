"""Generate the example USD stages of phrt-usd (farm, sewer, extreme cases).

Run ``uv run python tools/make_stages.py [OUT_DIR]`` (default: ``stages/`` next to this
file's parent). The output is deterministic: every random choice comes from a fixed seed,
so re-running writes byte-identical files.

Layout of what is written (all paths relative to OUT_DIR):

- ``farm.usda`` + ``farm_geometry.usdc``: outdoor cartoon farm, Y-up, metres, 17 reflectors.
- ``sewer.usda`` + ``sewer_geometry.usdc``: sewer tunnel network, Z-up, centimetres
  (``metersPerUnit = 0.01``), 33 reflectors.
- ``assets/*.usda``: small assets referenced (and instanced) by the farm.
- ``textures/sky.exr`` (lat-long sky, half float), ``textures/planks.png``.
- ``extreme/*.usda``: tiny stages for stiff cases and planted validation problems.

The root ``.usda`` layers hold everything a reader wants to see (cameras, lights, render
settings, camera paths, materials and their bindings, ``PhrtReflectorAPI`` opinions); the
bulky non-reflective meshes live in the referenced ``*_geometry.usdc`` layers.

The phrt schema is authored with plain USD calls (``AddAppliedSchema`` + custom attributes
with the schema's exact names and types), so this script works with or without the schema
plugin registered.

Geometry helpers build meshes as :class:`Mesh` (points, face counts, face indices) with
vectorised numpy; every helper builds in a local **Y-up, metres** frame with outward
(or camera-facing) counter-clockwise faces, i.e. USD's default ``rightHanded`` orientation.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender, UsdShade, Vt

# Phrt attributes are schema properties (non-custom) whether or not the plugin is loaded,
# so the generated files are the same either way.

#: Frame range of every animated stage (time codes), at 24 time codes per second.
START_FRAME = 1.0
END_FRAME = 720.0
FPS = 24.0

#: Image size written into every stage's UsdRenderSettings (the paper's 320x240).
RESOLUTION = (320, 240)

#: Seeds of the random generators (one per stage, so editing one stage leaves the others
#: byte-identical).
FARM_SEED = 17
SEWER_SEED = 33

#: Camera film back in millimetres (4:3 like RESOLUTION); focal lengths are per stage.
HORIZONTAL_APERTURE_MM = 36.0
VERTICAL_APERTURE_MM = 27.0

#: Timestamp written into image headers so that regenerated textures are byte-identical.
FIXED_DATETIME = "2014:10:01 00:00:00"

REFLECTOR_API = "PhrtReflectorAPI"
RENDER_SETTINGS_API = "PhrtRenderSettingsAPI"


# --------------------------------------------------------------------------------------
# Mesh building (numpy, local Y-up metres)
# --------------------------------------------------------------------------------------


@dataclass
class Mesh:
    """A polygon mesh in USD's layout.

    points  : (n, 3) float64, local space
    counts  : (f,) int32, vertices per face
    indices : (sum(counts),) int32 into ``points``; faces are counter-clockwise seen from
              their front side
    uv      : optional (sum(counts), 2) float32 face-varying texture coordinates
    """

    points: np.ndarray
    counts: np.ndarray
    indices: np.ndarray
    uv: np.ndarray | None = None

    @property
    def triangle_count(self) -> int:
        """Triangles after fan triangulation of every face."""
        return int(np.sum(self.counts - 2))

    def transformed(self, matrix: np.ndarray) -> Mesh:
        """Apply a (4, 4) column-vector affine matrix to the points."""
        pts = self.points @ matrix[:3, :3].T + matrix[:3, 3]
        return Mesh(pts, self.counts, self.indices, self.uv)

    def moved(self, offset: Sequence[float], yaw_deg: float = 0.0, scale: float = 1.0) -> Mesh:
        """Scale uniformly, rotate about +Y by ``yaw_deg``, then translate by ``offset``."""
        return self.transformed(trs_matrix(offset, yaw_deg, scale))


def trs_matrix(offset: Sequence[float], yaw_deg: float = 0.0, scale: float = 1.0) -> np.ndarray:
    """(4, 4) column-vector matrix: uniform scale, then yaw about +Y, then translation."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    m = np.eye(4)
    m[:3, :3] = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]) * scale
    m[:3, 3] = offset
    return m


def merge(meshes: Sequence[Mesh]) -> Mesh:
    """Concatenate meshes into one (uv kept only if every part has uv)."""
    offsets = np.cumsum([0] + [len(m.points) for m in meshes[:-1]])
    uv = None
    if all(m.uv is not None for m in meshes):
        uv = np.concatenate([m.uv for m in meshes])
    return Mesh(
        np.concatenate([m.points for m in meshes]),
        np.concatenate([m.counts for m in meshes]).astype(np.int32),
        np.concatenate([m.indices + o for m, o in zip(meshes, offsets, strict=True)]).astype(
            np.int32
        ),
        uv,
    )


def grid_faces(nu: int, nv: int, wrap_v: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Quad faces of a (nu + 1) x (nv [+ 1]) vertex grid indexed ``u * stride + v``.

    Each quad is (u, v), (u, v+1), (u+1, v+1), (u+1, v): counter-clockwise when the
    surface's front is along d(pos)/dv x d(pos)/du. With ``wrap_v`` the v direction is
    closed (nv vertices per row, the last quad connects back to v = 0).
    """
    stride = nv if wrap_v else nv + 1
    u, v = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    u, v = u.ravel(), v.ravel()
    v1 = (v + 1) % stride if wrap_v else v + 1
    quads = np.stack([u * stride + v, u * stride + v1, (u + 1) * stride + v1, (u + 1) * stride + v])
    return np.full(len(u), 4, np.int32), quads.T.ravel().astype(np.int32)


def box(size: Sequence[float], center: Sequence[float] = (0, 0, 0), uv_scale: float = 0.0) -> Mesh:
    """Axis-aligned box, outward faces; ``uv_scale`` > 0 adds uv = world size * uv_scale."""
    sx, sy, sz = np.asarray(size, float) / 2
    corners = np.array(
        [[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (-sz, sz)]
    ) + np.asarray(center, float)
    # corner index = 4*ix + 2*iy + iz
    faces = np.array(
        [
            [4, 6, 7, 5],  # +x
            [0, 1, 3, 2],  # -x
            [2, 3, 7, 6],  # +y
            [0, 4, 5, 1],  # -y
            [1, 5, 7, 3],  # +z
            [0, 2, 6, 4],  # -z
        ],
        np.int32,
    )
    uv = None
    if uv_scale > 0:
        # Each face's uv spans its two in-plane extents.
        extents = [(2 * sz, 2 * sy), (2 * sz, 2 * sy), (2 * sx, 2 * sz)] * 2
        unit = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
        uv = np.concatenate([unit * np.array(e, np.float32) * uv_scale for e in extents[:6]])
    return Mesh(corners, np.full(6, 4, np.int32), faces.ravel(), uv)


def quad(width: float, height: float, normal_axis: str = "+z") -> Mesh:
    """One rectangle centred at the origin facing ``normal_axis`` ("+y", "+z" or "-z")."""
    w, h = width / 2, height / 2
    if normal_axis == "+y":
        pts = np.array([[-w, 0, h], [w, 0, h], [w, 0, -h], [-w, 0, -h]], float)
    else:
        pts = np.array([[-w, -h, 0], [w, -h, 0], [w, h, 0], [-w, h, 0]], float)
        if normal_axis == "-z":
            pts = pts[::-1].copy()
    return Mesh(pts, np.array([4], np.int32), np.arange(4, dtype=np.int32))


def lathe(profile: np.ndarray, segments: int) -> Mesh:
    """Surface of revolution about +Y of a (m, 2) (radius, height) profile, bottom to top.

    Faces point away from the axis. A first or last profile point with radius 0 becomes a
    single pole vertex joined to its neighbouring ring by triangles.
    """
    r, y = profile[:, 0], profile[:, 1]
    bottom_pole, top_pole = r[0] == 0.0, r[-1] == 0.0
    rings = profile[int(bottom_pole) : len(profile) - int(top_pole)]
    m = len(rings)
    ang = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring_pts = np.stack(
        [
            np.outer(np.cos(ang), rings[:, 0]),
            np.broadcast_to(rings[:, 1], (segments, m)),
            -np.outer(np.sin(ang), rings[:, 0]),
        ],
        axis=-1,
    )  # (segments, m, 3), vertex index = u * m + v
    pts = [ring_pts.reshape(-1, 3)]
    counts, idx = grid_faces(segments - 1, m - 1)
    # close the seam: quads between the last and the first angle
    v = np.arange(m - 1)
    u_last = segments - 1
    seam = np.stack([u_last * m + v, u_last * m + v + 1, v + 1, v], axis=1).ravel()
    counts = np.concatenate([counts, np.full(m - 1, 4, np.int32)])
    idx = np.concatenate([idx, seam])
    # reverse winding so that the faces point away from the axis
    faces = [idx.reshape(-1, 4)[:, ::-1].ravel()]
    face_counts = [counts]
    u = np.arange(segments)
    u1 = (u + 1) % segments
    n = segments * m
    if bottom_pole:
        pts.append([[0.0, y[0], 0.0]])
        faces.append(np.stack([np.full(segments, n), u1 * m, u * m], axis=1).ravel())
        face_counts.append(np.full(segments, 3, np.int32))
        n += 1
    if top_pole:
        pts.append([[0.0, y[-1], 0.0]])
        top = np.stack([np.full(segments, n), u * m + m - 1, u1 * m + m - 1], axis=1)
        faces.append(top.ravel())
        face_counts.append(np.full(segments, 3, np.int32))
    return Mesh(
        np.vstack(pts),
        np.concatenate(face_counts).astype(np.int32),
        np.concatenate(faces).astype(np.int32),
    )


def cylinder(radius: float, height: float, segments: int, rings: int = 1) -> Mesh:
    """Closed cylinder along +Y from y = 0 to y = height (n-gon caps)."""
    ys = np.linspace(0.0, height, rings + 1)
    side = lathe(np.stack([np.full(rings + 1, radius), ys], axis=1), segments)
    ang = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([radius * np.cos(ang), np.zeros(segments), -radius * np.sin(ang)], axis=1)
    top = Mesh(ring + [0, height, 0], np.array([segments], np.int32), np.arange(segments))
    bottom = Mesh(ring, np.array([segments], np.int32), np.arange(segments)[::-1].copy())
    return merge([side, top, bottom])


def cone(radius: float, height: float, segments: int, base_y: float = 0.0) -> Mesh:
    """Closed cone along +Y with its base at ``base_y``."""
    return lathe(np.array([[0.0, base_y], [radius, base_y], [0.0, base_y + height]]), segments)


def sphere(radius: float, segments: int, stacks: int) -> Mesh:
    """UV sphere centred at the origin."""
    theta = np.linspace(np.pi, 0.0, stacks + 1)  # bottom pole to top pole
    profile = np.stack([radius * np.sin(theta), radius * np.cos(theta)], axis=1)
    profile[[0, -1], 0] = 0.0
    return lathe(profile, segments)


def disc(radius_fn: Callable[[np.ndarray], np.ndarray], segments: int) -> Mesh:
    """Flat +Y-facing polygon fan at y = 0 whose radius varies with the angle."""
    ang = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    r = radius_fn(ang)
    rim = np.stack([r * np.cos(ang), np.zeros(segments), -r * np.sin(ang)], axis=1)
    pts = np.vstack([[0.0, 0.0, 0.0], rim])
    i = np.arange(segments)
    tris = np.stack([np.zeros(segments, int), 1 + i, 1 + (i + 1) % segments], axis=1)
    return Mesh(pts, np.full(segments, 3, np.int32), tris.ravel().astype(np.int32))


def gable_roof(width: float, depth: float, rise: float, overhang: float, thickness: float) -> Mesh:
    """Two sloped slabs meeting at a ridge along z, eaves at y = 0, centred at x = z = 0."""
    half = width / 2 + overhang
    length = math.hypot(half, rise)
    angle = math.degrees(math.atan2(rise, half))
    slabs = []
    for side in (-1.0, 1.0):
        slab = box((length, thickness, depth + 2 * overhang))
        c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
        rot = np.eye(4)
        # rotate about z so the slab rises toward the ridge at x = 0
        rot[:2, :2] = [[c, side * s], [-side * s, c]]
        rot[:3, 3] = [side * half / 2, rise / 2, 0.0]
        slabs.append(slab.transformed(rot))
    gables = []
    for zsign in (-1.0, 1.0):
        tri = np.array(
            [
                [-width / 2, 0, zsign * depth / 2],
                [width / 2, 0, zsign * depth / 2],
                [0, rise * width / 2 / half, zsign * depth / 2],
            ]
        )
        order = [0, 1, 2] if zsign > 0 else [2, 1, 0]
        gables.append(Mesh(tri, np.array([3], np.int32), np.array(order, np.int32)))
    return merge(slabs + gables)


def tunnel_shell(
    width: float,
    wall_height: float,
    length: float,
    arc_segments: int,
    length_segments: int,
    floor_y: float,
) -> Mesh:
    """Inside of a tunnel along +x (walls + half-round arched ceiling), faces inward.

    The cross-section (y, z) goes from the floor at z = -width/2 up the wall, over the arch
    and down to the floor at z = +width/2; x runs from 0 to ``length``.
    """
    half = width / 2
    theta = np.linspace(np.pi, 0.0, arc_segments + 1)
    arch = np.stack([wall_height + half * np.sin(theta), half * np.cos(theta)], axis=1)
    wall_steps = 4
    wall_y = np.linspace(floor_y, wall_height, wall_steps, endpoint=False)
    left = np.stack([wall_y, np.full(wall_steps, -half)], axis=1)
    right = np.stack([wall_y[::-1], np.full(wall_steps, half)], axis=1)
    section = np.vstack([left, arch, right])  # (m, 2) as (y, z)
    m = len(section)
    xs = np.linspace(0.0, length, length_segments + 1)
    pts = np.stack(
        [np.repeat(xs, m), np.tile(section[:, 0], len(xs)), np.tile(section[:, 1], len(xs))],
        axis=1,
    )
    counts, idx = grid_faces(length_segments, m - 1)
    # grid order faces outward here; reverse so the inside of the tunnel is the front
    return Mesh(pts, counts, idx.reshape(-1, 4)[:, ::-1].ravel().copy())


# --------------------------------------------------------------------------------------
# USD authoring helpers
# --------------------------------------------------------------------------------------


def new_stage(path: Path, up_axis: str, meters_per_unit: float, default_prim: str) -> Usd.Stage:
    """Create a fresh stage with the common metadata (up axis, units, time range)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists():
        path.unlink()
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    world = UsdGeom.Xform.Define(stage, f"/{default_prim}")
    stage.SetDefaultPrim(world.GetPrim())
    return stage


def set_time_range(stage: Usd.Stage, start: float, end: float) -> None:
    stage.SetStartTimeCode(start)
    stage.SetEndTimeCode(end)
    stage.SetTimeCodesPerSecond(FPS)
    stage.SetFramesPerSecond(FPS)


def author_mesh(
    stage: Usd.Stage, path: str, mesh: Mesh, color: Sequence[float] | None = None
) -> UsdGeom.Mesh:
    """Define a UsdGeomMesh (subdivisionScheme none, extent, optional constant colour)."""
    prim = UsdGeom.Mesh.Define(stage, path)
    pts = mesh.points.astype(np.float32)
    prim.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
    prim.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(mesh.counts.astype(np.int32)))
    prim.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(mesh.indices.astype(np.int32)))
    prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    if len(pts):
        finite = pts[np.isfinite(pts).all(axis=1)]
        if len(finite):
            prim.CreateExtentAttr(
                Vt.Vec3fArray(
                    [Gf.Vec3f(*finite.min(0).tolist()), Gf.Vec3f(*finite.max(0).tolist())]
                )
            )
    if color is not None:
        prim.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(*color)]))
    if mesh.uv is not None:
        st = UsdGeom.PrimvarsAPI(prim).CreatePrimvar(
            "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying
        )
        st.Set(Vt.Vec2fArray.FromNumpy(mesh.uv.astype(np.float32)))
    return prim


def place(
    prim: UsdGeom.Xformable,
    translate: Sequence[float],
    yaw_deg: float = 0.0,
    scale: float = 1.0,
    yaw_axis: str = "Y",
) -> None:
    """Author translate (double precision), rotate about the up axis, uniform scale."""
    prim.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*translate))
    if yaw_deg:
        op = prim.AddRotateYOp() if yaw_axis == "Y" else prim.AddRotateZOp()
        op.Set(float(yaw_deg))
    if scale != 1.0:
        prim.AddScaleOp().Set(Gf.Vec3f(scale, scale, scale))


def make_material(
    stage: Usd.Stage,
    path: str,
    diffuse: Sequence[float],
    roughness: float = 0.6,
    metallic: float = 0.0,
    texture: str | None = None,
) -> UsdShade.Material:
    """A UsdPreviewSurface material; ``texture`` (asset path) drives diffuseColor via st."""
    mat = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, f"{path}/PreviewSurface")
    shader.CreateIdAttr("UsdPreviewSurface")
    diffuse_in = shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f)
    diffuse_in.Set(Gf.Vec3f(*diffuse))
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(float(roughness))
    shader.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(float(metallic))
    mat.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    if texture is not None:
        reader = UsdShade.Shader.Define(stage, f"{path}/StReader")
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
        tex = UsdShade.Shader.Define(stage, f"{path}/DiffuseTexture")
        tex.CreateIdAttr("UsdUVTexture")
        tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(texture))
        tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("repeat")
        tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("repeat")
        tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
        tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
            reader.ConnectableAPI(), "result"
        )
        rgb = tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
        diffuse_in.ConnectToSource(rgb)
    return mat


def bind(prim: Usd.Prim | Usd.SchemaBase, material: UsdShade.Material) -> None:
    target = prim.GetPrim() if hasattr(prim, "GetPrim") else prim
    UsdShade.MaterialBindingAPI.Apply(target).Bind(material)


def make_reflector(prim: Usd.Prim | Usd.SchemaBase, priority: float, reflectivity: float) -> None:
    """Apply PhrtReflectorAPI with K = ``priority`` and F = ``reflectivity``."""
    target = prim.GetPrim() if hasattr(prim, "GetPrim") else prim
    target.AddAppliedSchema(REFLECTOR_API)
    target.CreateAttribute("phrt:priority", Sdf.ValueTypeNames.Float, custom=False).Set(
        float(priority)
    )
    target.CreateAttribute("phrt:reflectivity", Sdf.ValueTypeNames.Float, custom=False).Set(
        float(reflectivity)
    )


def look_at_matrix(
    eye: Sequence[float], target: Sequence[float], up: Sequence[float]
) -> Gf.Matrix4d:
    """Camera-to-world matrix (USD row-vector convention) looking down -Z at ``target``."""
    eye_v, tgt, up_v = (np.asarray(v, float) for v in (eye, target, up))
    fwd = tgt - eye_v
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up_v)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, fwd)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3], m[3, :3] = right, true_up, -fwd, eye_v
    return Gf.Matrix4d(*m.ravel().tolist())


def make_camera(
    stage: Usd.Stage,
    path: str,
    focal_mm: float,
    clip: tuple[float, float],
    eye: Sequence[float],
    target: Sequence[float],
    up: Sequence[float],
) -> UsdGeom.Camera:
    """A perspective camera with a static ``xformOp:transform`` looking at ``target``."""
    cam = UsdGeom.Camera.Define(stage, path)
    cam.CreateFocalLengthAttr(float(focal_mm))
    cam.CreateHorizontalApertureAttr(HORIZONTAL_APERTURE_MM)
    cam.CreateVerticalApertureAttr(VERTICAL_APERTURE_MM)
    cam.CreateClippingRangeAttr(Gf.Vec2f(*clip))
    cam.CreateProjectionAttr(UsdGeom.Tokens.perspective)
    cam.AddTransformOp().Set(look_at_matrix(eye, target, up))
    return cam


def make_camera_path(
    stage: Usd.Stage,
    path: str,
    camera_path: str,
    positions: np.ndarray,
    targets: np.ndarray,
    key_times: np.ndarray,
    interpolation: str = "catmullRom",
) -> Usd.Prim:
    """Author a ``PhrtCameraPath`` prim (plain USD: typed prim + the schema's attributes)."""
    prim = stage.DefinePrim(path, "PhrtCameraPath")
    prim.CreateRelationship("phrt:camera", custom=False).SetTargets([Sdf.Path(camera_path)])
    prim.CreateAttribute("phrt:positions", Sdf.ValueTypeNames.Point3dArray, custom=False).Set(
        Vt.Vec3dArray.FromNumpy(np.asarray(positions, np.float64))
    )
    prim.CreateAttribute("phrt:targets", Sdf.ValueTypeNames.Point3dArray, custom=False).Set(
        Vt.Vec3dArray.FromNumpy(np.asarray(targets, np.float64))
    )
    prim.CreateAttribute("phrt:keyTimes", Sdf.ValueTypeNames.DoubleArray, custom=False).Set(
        Vt.DoubleArray.FromNumpy(np.asarray(key_times, np.float64))
    )
    prim.CreateAttribute("phrt:startFrame", Sdf.ValueTypeNames.Double, custom=False).Set(
        float(key_times[0])
    )
    prim.CreateAttribute("phrt:endFrame", Sdf.ValueTypeNames.Double, custom=False).Set(
        float(key_times[-1])
    )
    prim.CreateAttribute("phrt:interpolation", Sdf.ValueTypeNames.Token, custom=False).Set(
        interpolation
    )
    return prim


def make_render_settings(stage: Usd.Stage, camera_path: str, **phrt: object) -> None:
    """UsdRenderSettings at /Render/Settings with PhrtRenderSettingsAPI and stage metadata."""
    UsdGeom.Scope.Define(stage, "/Render")
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateResolutionAttr(Gf.Vec2i(*RESOLUTION))
    settings.CreateCameraRel().SetTargets([Sdf.Path(camera_path)])
    prim = settings.GetPrim()
    prim.AddAppliedSchema(RENDER_SETTINGS_API)
    types = {
        "heuristic": Sdf.ValueTypeNames.Token,
        "mode": Sdf.ValueTypeNames.Token,
        "selectionWeight": Sdf.ValueTypeNames.Float,
        "budgetMs": Sdf.ValueTypeNames.Float,
        "budgetRays": Sdf.ValueTypeNames.Int,
        "bounceLimit": Sdf.ValueTypeNames.Int,
    }
    values = {
        "heuristic": "heu1",
        "mode": "hybrid",
        "selectionWeight": 0.0001,
        "budgetMs": 10.0,
        "bounceLimit": 5,
        **phrt,
    }
    for name, value in values.items():
        prim.CreateAttribute(f"phrt:{name}", types[name], custom=False).Set(value)
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")


def evaluate_camera_path(
    points: np.ndarray, key_times: np.ndarray, frames: np.ndarray, interpolation: str = "catmullRom"
) -> np.ndarray:
    """Evaluate a camera path's control points at ``frames``.

    points    : (k, 3) control points (positions or targets), stage units
    key_times : (k,) increasing time codes
    frames    : (n,) time codes, clamped to [key_times[0], key_times[-1]]
    returns   : (n, 3)

    Uniform Catmull-Rom per segment (end points duplicated), or piecewise linear. This is
    the reference evaluation used by the preview and the tests.
    """
    pts = np.asarray(points, float)
    kt = np.asarray(key_times, float)
    f = np.clip(np.asarray(frames, float), kt[0], kt[-1])
    seg = np.clip(np.searchsorted(kt, f, side="right") - 1, 0, len(kt) - 2)
    t = ((f - kt[seg]) / (kt[seg + 1] - kt[seg]))[:, None]
    p1, p2 = pts[seg], pts[seg + 1]
    if interpolation == "linear":
        return p1 + (p2 - p1) * t
    p0 = pts[np.maximum(seg - 1, 0)]
    p3 = pts[np.minimum(seg + 2, len(pts) - 1)]
    return 0.5 * (
        2 * p1
        + (-p0 + p2) * t
        + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t**2
        + (-p0 + 3 * p1 - 3 * p2 + p3) * t**3
    )


def resample_polyline(waypoints: np.ndarray, count: int) -> np.ndarray:
    """(count, d) points evenly spaced by arc length along a (w, d) polyline."""
    seg = np.linalg.norm(np.diff(waypoints, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    q = np.linspace(0.0, s[-1], count)
    return np.stack([np.interp(q, s, waypoints[:, i]) for i in range(waypoints.shape[1])], axis=1)


def smooth_polyline(waypoints: np.ndarray, iterations: int = 3) -> np.ndarray:
    """Chaikin corner cutting: rounds the corners of a (w, d) polyline, keeps end points."""
    pts = np.asarray(waypoints, float)
    for _ in range(iterations):
        a, b = pts[:-1], pts[1:]
        cut = np.empty((2 * len(a), pts.shape[1]))
        cut[0::2] = 0.75 * a + 0.25 * b
        cut[1::2] = 0.25 * a + 0.75 * b
        pts = np.vstack([pts[:1], cut, pts[-1:]])
    return pts


def subsets_by_face(
    stage: Usd.Stage,
    mesh: UsdGeom.Mesh,
    groups: dict[str, np.ndarray],
    materials: dict[str, UsdShade.Material],
) -> None:
    """Author materialBind GeomSubsets (face index lists) and bind one material to each."""
    for name, faces in groups.items():
        subset = UsdGeom.Subset.CreateGeomSubset(
            UsdGeom.Imageable(mesh),
            name,
            UsdGeom.Tokens.face,
            Vt.IntArray.FromNumpy(np.asarray(faces, np.int32)),
            "materialBind",
            UsdGeom.Tokens.nonOverlapping,
        )
        bind(subset, materials[name])


def count_mesh_triangles(stage: Usd.Stage) -> tuple[int, int]:
    """(triangles of every mesh on the composed stage incl. instances, implicit gprims).

    Instance proxies are traversed, so an instanced asset counts once per instance.
    Implicit gprims (sphere, cube, cylinder, cone) are counted separately: their
    triangle count depends on the reader's tessellation.
    """
    triangles, implicit = 0, 0
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        if prim.IsA(UsdGeom.Mesh):
            counts = np.asarray(UsdGeom.Mesh(prim).GetFaceVertexCountsAttr().Get() or [])
            triangles += int(np.sum(np.maximum(counts - 2, 0)))
        elif prim.IsA(UsdGeom.Gprim):
            implicit += 1
    return triangles, implicit


# --------------------------------------------------------------------------------------
# Textures
# --------------------------------------------------------------------------------------


def write_sky_exr(path: Path, sun_dir: np.ndarray, width: int = 256, height: int = 128) -> None:
    """Lat-long sky (half float RGB): zenith-to-horizon gradient, sun disc, dark ground.

    Mapping follows the OpenEXR lat-long convention used by UsdLuxDomeLight (+Y up):
    column u in [0, 1) is longitude pi - 2 pi u, row v is latitude pi/2 - pi v, and the
    direction is (cos(lat) sin(lon), sin(lat), cos(lat) cos(lon)).
    sun_dir : (3,) unit vector toward the sun in dome space.
    """
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    lon = np.pi - 2 * np.pi * u[None, :]
    lat = np.pi / 2 - np.pi * v[:, None]
    d = np.stack(
        np.broadcast_arrays(np.cos(lat) * np.sin(lon), np.sin(lat), np.cos(lat) * np.cos(lon)),
        axis=-1,
    )
    elevation = d[..., 1]
    zenith = np.array([0.18, 0.35, 0.85])
    horizon = np.array([0.75, 0.85, 1.0])
    ground = np.array([0.20, 0.18, 0.14])
    t = np.clip(elevation, 0.0, 1.0)[..., None] ** 0.5
    sky = horizon * (1 - t) + zenith * t
    below = np.clip(-elevation * 8.0, 0.0, 1.0)[..., None]  # blend into the ground quickly
    rgb = sky * (1 - below) + ground * below
    cos_sun = d @ np.asarray(sun_dir, float)
    sun_disc_cos = math.cos(math.radians(3.0))  # a 3-degree disc: wider than the real sun
    rgb = rgb + np.where(cos_sun[..., None] > sun_disc_cos, 40.0, 0.0) * np.array([1.0, 0.95, 0.85])
    rgb = rgb + (np.clip(cos_sun, 0, 1) ** 64)[..., None] * np.array([1.5, 1.3, 1.0])  # glow
    spec = oiio.ImageSpec(width, height, 3, "half")
    spec.attribute("DateTime", FIXED_DATETIME)  # else OpenEXR stamps the current time
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(rgb.astype(np.float32))
    out.close()


def write_planks_png(path: Path, size: int = 64) -> None:
    """Wooden plank texture (8-bit sRGB PNG): 4 boards with grain and dark seams."""
    rng = np.random.default_rng(FARM_SEED)
    y, x = np.mgrid[0:size, 0:size] / size
    board = np.floor(y * 4)
    grain = 0.5 + 0.5 * np.sin(40 * x + 6 * np.sin(7 * y + board) + board * 3)
    base = np.array([0.55, 0.36, 0.20]) * (0.85 + 0.15 * grain[..., None])
    base *= 0.9 + 0.2 * rng.random(4)[board.astype(int)][..., None]
    seam = (y * 4 - board) < 0.06
    base[seam] *= 0.35
    img = np.clip(base * 255 + 0.5, 0, 255).astype(np.uint8)
    spec = oiio.ImageSpec(size, size, 3, "uint8")
    spec.attribute("DateTime", FIXED_DATETIME)
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(img)
    out.close()


# --------------------------------------------------------------------------------------
# Farm (Y-up, metres)
# --------------------------------------------------------------------------------------

#: Ground: FARM_GROUND_SIZE metres square, FARM_GROUND_QUADS quads per side.
FARM_GROUND_SIZE = 160.0
FARM_GROUND_QUADS = 110
#: Ponds: (name, centre x, centre z, mean radius m, K, F).
FARM_PONDS = [("PondA", 22.0, 16.0, 7.0, 8.0, 0.7), ("PondB", 8.5, 28.0, 5.0, 6.0, 0.7)]
#: Camera eye height above the ground and the height of its look-at targets (metres).
FARM_EYE_HEIGHT = 3.5
FARM_TARGET_HEIGHT = 1.2
#: Waypoints (x, z) of the farm walk before smoothing; forward-only by construction.
FARM_ROUTE = np.array([[-30.0, -45.0], [52.0, -45.0], [52.0, 48.0], [0.0, 48.0], [0.0, -22.0]])


def pond_radius(mean_radius: float, seed: int) -> Callable[[np.ndarray], np.ndarray]:
    """A wobbly closed outline r(angle) for a pond (low-frequency, deterministic)."""
    rng = np.random.default_rng(seed)
    amps = rng.uniform(0.04, 0.12, 3)
    phases = rng.uniform(0, 2 * np.pi, 3)

    def radius(angle: np.ndarray) -> np.ndarray:
        wobble = sum(
            a * np.sin((k + 2) * angle + p)
            for k, (a, p) in enumerate(zip(amps, phases, strict=True))
        )
        return mean_radius * (1.0 + wobble)

    return radius


def farm_route() -> np.ndarray:
    """(w, 2) smoothed (x, z) route of the farm camera, densely sampled."""
    return smooth_polyline(FARM_ROUTE, iterations=5)


def ground_mesh(route_xz: np.ndarray) -> tuple[Mesh, np.ndarray]:
    """Farm ground grid and its per-vertex displayColor (n, 3).

    Flat farmyard in the middle, rolling hills beyond ~55 m, depressions under the ponds,
    dirt where the route runs (a farm track) and noisy grass elsewhere.
    """
    n = FARM_GROUND_QUADS
    half = FARM_GROUND_SIZE / 2
    xs = np.linspace(-half, half, n + 1)
    x, z = np.meshgrid(xs, xs, indexing="ij")  # vertex (i, j) = i * (n + 1) + j
    r = np.hypot(x, z)
    hills = np.clip((r - 55.0) / 25.0, 0.0, 1.0) ** 2
    y = hills * (2.5 + 1.5 * np.sin(x / 13.0) * np.cos(z / 17.0))
    for k, (_, cx, cz, radius, _, _) in enumerate(FARM_PONDS):
        outline = pond_radius(radius, FARM_SEED + k)
        ang = np.arctan2(-(z - cz), x - cx)
        inside = np.hypot(x - cx, z - cz) / outline(ang)
        y -= 0.6 * np.clip(1.2 - inside, 0.0, 1.0) / 1.2
    rng = np.random.default_rng(FARM_SEED)
    grass = np.array([0.25, 0.55, 0.18]) * (0.85 + 0.3 * rng.random((n + 1, n + 1, 1)))
    dirt = np.array([0.55, 0.42, 0.26])
    flat = np.stack([x.ravel(), z.ravel()], axis=1)
    # distance of every vertex to the densely sampled route (chunked to bound memory)
    dist = np.min(np.linalg.norm(flat[:, None, :] - route_xz[None, ::4, :], axis=2), axis=1)
    track = np.clip(1.0 - (dist - 1.5) / 1.5, 0.0, 1.0).reshape(n + 1, n + 1, 1)
    colors = grass * (1 - track) + dirt * track
    pts = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    counts, idx = grid_faces(n, n)
    return Mesh(pts, counts, idx), colors.reshape(-1, 3)


def write_farm_assets(out: Path) -> dict[str, str]:
    """Write the referenced farm assets; returns name -> relative asset path."""
    assets = {}
    rng = np.random.default_rng(FARM_SEED + 100)

    def asset_stage(name: str) -> Usd.Stage:
        stage = new_stage(out / "assets" / f"{name}.usda", "Y", 1.0, "Asset")
        Usd.ModelAPI(stage.GetDefaultPrim()).SetKind("component")
        assets[name] = f"./assets/{name}.usda"
        return stage

    # Pine: trunk cylinder (implicit) + three stacked cones (mesh).
    stage = asset_stage("tree_pine")
    looks = "/Asset/Looks"
    bark = make_material(stage, f"{looks}/Bark", (0.35, 0.22, 0.12), 0.9)
    needles = make_material(stage, f"{looks}/Needles", (0.10, 0.38, 0.16), 0.8)
    trunk = UsdGeom.Cylinder.Define(stage, "/Asset/Trunk")
    trunk.CreateRadiusAttr(0.25)
    trunk.CreateHeightAttr(2.0)
    trunk.CreateAxisAttr("Y")
    place(trunk, (0, 1.0, 0))
    bind(trunk, bark)
    crown = merge([cone(2.2 - 0.5 * k, 2.6, 10, base_y=1.6 + 1.5 * k) for k in range(3)])
    bind(author_mesh(stage, "/Asset/Crown", crown), needles)
    stage.GetRootLayer().Save()

    # Round tree: trunk cylinder + squashed sphere crown with vertex colours.
    stage = asset_stage("tree_round")
    bark = make_material(stage, f"{looks}/Bark", (0.40, 0.26, 0.14), 0.9)
    trunk = UsdGeom.Cylinder.Define(stage, "/Asset/Trunk")
    trunk.CreateRadiusAttr(0.3)
    trunk.CreateHeightAttr(2.6)
    trunk.CreateAxisAttr("Y")
    place(trunk, (0, 1.3, 0))
    bind(trunk, bark)
    crown = sphere(2.2, 10, 7).transformed(np.diag([1.0, 1.15, 1.0, 1.0]))
    crown = crown.moved((0, 4.4, 0))
    crown_prim = author_mesh(stage, "/Asset/Crown", crown)
    shade = 0.75 + 0.25 * (crown.points[:, 1] - 2.0) / 5.0  # lighter toward the top
    jitter = 0.9 + 0.2 * rng.random(len(crown.points))
    colors = np.array([0.22, 0.50, 0.15]) * (shade * jitter)[:, None]
    pv = crown_prim.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex)
    pv.Set(Vt.Vec3fArray.FromNumpy(colors.astype(np.float32)))
    stage.GetRootLayer().Save()

    # Fence section: one post and two rails, 3 m long along +x.
    stage = asset_stage("fence_section")
    wood = make_material(stage, f"{looks}/Wood", (0.60, 0.48, 0.32), 0.8)
    fence = merge(
        [
            box((0.18, 1.3, 0.18), (0, 0.65, 0)),
            box((3.0, 0.12, 0.06), (1.5, 0.5, 0.0)),
            box((3.0, 0.12, 0.06), (1.5, 1.0, 0.0)),
        ]
    )
    bind(author_mesh(stage, "/Asset/Fence", fence), wood)
    stage.GetRootLayer().Save()
    return assets


def open_trough(length: float, width: float, height: float, wall: float) -> Mesh:
    """Open-topped box (bottom and four walls), base at y = 0."""
    return merge(
        [
            box((length, wall, width), (0, wall / 2, 0)),
            box((length, height, wall), (0, height / 2, (width - wall) / 2)),
            box((length, height, wall), (0, height / 2, -(width - wall) / 2)),
            box((wall, height, width), ((length - wall) / 2, height / 2, 0)),
            box((wall, height, width), (-(length - wall) / 2, height / 2, 0)),
        ]
    )


def build_farm_geometry(path: Path, route_xz: np.ndarray) -> dict[str, str]:
    """Write farm_geometry.usdc (non-reflective bulk meshes) under /Geometry.

    Returns prim name -> path relative to /Geometry of prims that the root layer binds
    materials to (bindings are authored in the root layer so they stay readable).
    """
    stage = new_stage(path, "Y", 1.0, "Geometry")
    rng = np.random.default_rng(FARM_SEED + 1)
    ground, colors = ground_mesh(route_xz)
    g = author_mesh(stage, "/Geometry/Ground", ground)
    g.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(
        Vt.Vec3fArray.FromNumpy(colors.astype(np.float32))
    )

    # Barn body: walls box + white trim (door frame, corner posts), one mesh with subsets.
    walls = box((12.0, 7.0, 18.0), (0, 3.5, 0))
    trims = [box((0.3, 7.0, 0.3), (sx * 6.05, 3.5, sz * 9.05)) for sx in (-1, 1) for sz in (-1, 1)]
    trims += [box((0.3, 5.0, 0.3), (6.1, 2.5, dz)) for dz in (-2.6, 2.6)]
    trims += [box((0.3, 0.3, 5.5), (6.1, 5.1, 0)), box((0.2, 4.8, 5.0), (6.02, 2.4, 0))]
    barn = merge([walls] + trims)
    barn_prim = author_mesh(stage, "/Geometry/Barn/Body", barn.moved((-20.0, 0, -10.0)))
    UsdGeom.Xform.Define(stage, "/Geometry/Barn")
    n_wall_faces = len(walls.counts)
    for name, faces in (
        ("Walls", np.arange(n_wall_faces)),
        ("Trim", np.arange(n_wall_faces, len(barn.counts))),
    ):
        UsdGeom.Subset.CreateGeomSubset(
            UsdGeom.Imageable(barn_prim),
            name,
            UsdGeom.Tokens.face,
            Vt.IntArray.FromNumpy(faces.astype(np.int32)),
            "materialBind",
            UsdGeom.Tokens.partition,  # walls + trim cover every face once
        )
    author_mesh(
        stage,
        "/Geometry/Barn/Roof",
        gable_roof(12.0, 18.0, 4.0, 0.6, 0.25).moved((-20.0, 7.0, -10.0)),
    )

    # House: textured plank walls (uv), roof, chimney, door.
    UsdGeom.Xform.Define(stage, "/Geometry/House")
    author_mesh(stage, "/Geometry/House/Walls", box((10.0, 5.0, 8.0), (18.0, 2.5, -14.0), 0.5))
    author_mesh(
        stage,
        "/Geometry/House/Roof",
        gable_roof(10.0, 8.0, 3.0, 0.5, 0.2).moved((18.0, 5.0, -14.0)),
    )
    author_mesh(stage, "/Geometry/House/Chimney", box((0.9, 3.0, 0.9), (21.0, 7.0, -15.0)))
    author_mesh(stage, "/Geometry/House/Door", box((1.2, 2.2, 0.1), (18.0, 1.1, -9.95)))

    # Silo: implicit cylinder + sphere dome.
    UsdGeom.Xform.Define(stage, "/Geometry/Silo")
    silo = UsdGeom.Cylinder.Define(stage, "/Geometry/Silo/Tower")
    silo.CreateRadiusAttr(3.0)
    silo.CreateHeightAttr(12.0)
    silo.CreateAxisAttr("Y")
    place(silo, (-34.0, 6.0, -22.0))
    dome = UsdGeom.Sphere.Define(stage, "/Geometry/Silo/Dome")
    dome.CreateRadiusAttr(3.0)
    place(dome, (-34.0, 12.0, -22.0))

    # Shed and a stable (cubes, implicit), trough yard walls.
    shed = UsdGeom.Cube.Define(stage, "/Geometry/Shed")
    shed.CreateSizeAttr(1.0)
    shed.AddTranslateOp().Set(Gf.Vec3d(-9.0, 1.75, -27.0))
    shed.AddScaleOp().Set(Gf.Vec3f(6.0, 3.5, 4.0))
    author_mesh(
        stage,
        "/Geometry/TroughYardWall",
        merge([box((12.0, 0.6, 0.4), (-5.5, 0.3, -0.5)), box((0.4, 0.6, 12.0), (-11.8, 0.3, 5.5))]),
    )

    # Hay bales: implicit cylinders lying along x, in two stacks.
    UsdGeom.Xform.Define(stage, "/Geometry/HayBales")
    bale_pos = [
        (-16.0, 0.75, -24.0),
        (-14.3, 0.75, -24.0),
        (-15.15, 2.2, -24.0),
        (30.0, 0.75, 2.0),
        (30.0, 0.75, 3.7),
        (31.7, 0.75, 2.8),
        (12.0, 0.75, -26.0),
    ]
    for k, pos in enumerate(bale_pos):
        bale = UsdGeom.Cylinder.Define(stage, f"/Geometry/HayBales/Bale{k:02d}")
        bale.CreateRadiusAttr(0.75)
        bale.CreateHeightAttr(1.5)
        bale.CreateAxisAttr("X")
        place(bale, pos)

    # Vegetable field: rows of low-poly cabbages (one merged mesh, uniform displayColor).
    cabbage = sphere(0.35, 6, 4).transformed(np.diag([1.0, 0.7, 1.0, 1.0]))
    heads, face_colors = [], []
    for row in range(12):
        for col in range(22):
            jitter = rng.uniform(-0.15, 0.15, 2)
            pos = (-40.0 + col * 1.6 + jitter[0], 0.2, 12.0 + row * 1.5 + jitter[1])
            heads.append(cabbage.moved(pos, yaw_deg=float(rng.uniform(0, 360))))
            face_colors.append(
                np.tile(
                    rng.uniform(0.8, 1.1) * np.array([0.45, 0.70, 0.30]), (len(cabbage.counts), 1)
                )
            )
    field = author_mesh(stage, "/Geometry/CabbageField", merge(heads))
    field.CreateDisplayColorPrimvar(UsdGeom.Tokens.uniform).Set(
        Vt.Vec3fArray.FromNumpy(np.concatenate(face_colors).astype(np.float32))
    )

    # Trough bodies (the water surfaces are reflectors, authored in the root layer).
    for k, (x, z) in enumerate(FARM_TROUGHS):
        author_mesh(
            stage,
            f"/Geometry/TroughBody{k}",
            open_trough(3.0, 1.0, 0.8, 0.08).moved((x, 0.0, z)),
            (0.45, 0.45, 0.47),
        )

    # Pond banks: mud rings around each pond.
    for k, (name, cx, cz, radius, _, _) in enumerate(FARM_PONDS):
        outline = pond_radius(radius, FARM_SEED + k)
        ang = np.linspace(0.0, 2 * np.pi, 40, endpoint=False)
        r_in, r_out = outline(ang) * 0.98, outline(ang) + 1.2
        ring = np.concatenate(
            [
                np.stack([r_in * np.cos(ang), np.full(40, 0.0), -r_in * np.sin(ang)], axis=1),
                np.stack([r_out * np.cos(ang), np.full(40, 0.05), -r_out * np.sin(ang)], axis=1),
            ]
        ) + [cx, 0.0, cz]
        i = np.arange(40)
        j = (i + 1) % 40
        faces = np.stack([i, 40 + i, 40 + j, j], axis=1).ravel()
        author_mesh(
            stage,
            f"/Geometry/{name}Bank",
            Mesh(ring, np.full(40, 4, np.int32), faces.astype(np.int32)),
            (0.40, 0.32, 0.22),
        )
    stage.GetRootLayer().Save()
    return {}


#: Trough centres (x, z); each has a water surface reflector (K 2).
FARM_TROUGHS = [(-8.0, 3.5), (-3.5, 3.5), (-8.0, 8.5), (-3.5, 8.5)]
#: Mesh barrels (x, z) and implicit cylinder barrels (x, z); the floating barrel is extra.
FARM_MESH_BARRELS = [(-10.6, 1.3), (-11.1, 2.2), (-10.2, 2.3), (-2.4, 1.0), (3.2, 11.5)]
FARM_CYL_BARRELS = [(-11.0, 11.0), (3.4, 0.6)]


def fence_transforms() -> list[tuple[tuple[float, float, float], float]]:
    """(position, yaw degrees) of every 3 m fence section around the farmyard.

    The yard fence is a rectangle x in [-45, 45], z in [-32, 40] with a 9 m gate in the
    south side at x = 0 (the camera walks through it).
    """
    placements = []
    for x0 in np.arange(-45.0, 45.0, 3.0):
        placements.append(((float(x0), 0.0, -32.0), 0.0))
        if abs(x0 + 1.5) > 4.5:
            placements.append(((float(x0), 0.0, 40.0), 0.0))
    for z0 in np.arange(-32.0, 40.0, 3.0):
        # yaw -90 turns the section's +x run into +z
        placements.append(((-45.0, 0.0, float(z0)), -90.0))
        placements.append(((45.0, 0.0, float(z0)), -90.0))
    return placements


def tree_positions(route_xz: np.ndarray, count: int) -> list[tuple[float, float, int]]:
    """(x, z, kind) tree spots: outside the buildings, off the route, kind 0 pine 1 round."""
    rng = np.random.default_rng(FARM_SEED + 2)
    keep_out = [
        (-20.0, -10.0, 12.0),
        (18.0, -14.0, 9.0),
        (-34.0, -22.0, 5.0),
        (-6.0, 6.0, 9.0),
        (22.0, 16.0, 10.0),
        (8.5, 28.0, 8.0),
        (-9.0, -27.0, 5.0),
        (-23.0, 20.0, 20.0),
    ]
    spots: list[tuple[float, float, int]] = []
    while len(spots) < count:
        x, z = rng.uniform(-72.0, 72.0, 2)
        if np.min(np.hypot(route_xz[:, 0] - x, route_xz[:, 1] - z)) < 6.0:
            continue
        if any(math.hypot(x - cx, z - cz) < r for cx, cz, r in keep_out):
            continue
        if any(math.hypot(x - sx, z - sz) < 4.0 for sx, sz, _ in spots):
            continue
        if min(abs(abs(x) - 45.0), abs(z + 32.0), abs(z - 40.0)) < 2.0:
            continue  # not on a fence line
        spots.append((float(x), float(z), int(rng.integers(0, 2))))
    return spots


def sun_direction(light: UsdLux.DistantLight) -> np.ndarray:
    """(3,) unit vector toward the light (opposite of its -Z emission axis), world space."""
    xf = UsdGeom.Xformable(light).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    d = xf.TransformDir(Gf.Vec3d(0.0, 0.0, -1.0))
    v = -np.array(d, float)
    return v / np.linalg.norm(v)


def farm_camera_keys(route_xz: np.ndarray, n_keys: int = 37) -> tuple[np.ndarray, ...]:
    """Control points of the farm camera path: (positions (k,3), targets (k,3), times (k,)).

    Positions are evenly spaced along the smoothed route (so the speed is constant);
    targets look 12 m ahead along the route, with a glance toward the ponds on the east
    side of the loop.
    """
    pos_xz = resample_polyline(route_xz, n_keys)
    ahead = resample_polyline(route_xz, 4 * n_keys)
    tangent = np.gradient(ahead, axis=0)[::4][:n_keys]
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    s = np.linspace(0.0, 1.0, n_keys)
    # glance right (toward the yard) on the east leg, a smooth bump in yaw, radians
    glance = 0.55 * np.exp(-(((s - 0.42) / 0.07) ** 2))
    c, sn = np.cos(glance), np.sin(glance)
    # positive yaw turns the view to the right of travel (x, z) -> rotate toward -x when
    # travelling +z
    look = np.stack(
        [c * tangent[:, 0] - sn * tangent[:, 1], sn * tangent[:, 0] + c * tangent[:, 1]], axis=1
    )
    positions = np.stack([pos_xz[:, 0], np.full(n_keys, FARM_EYE_HEIGHT), pos_xz[:, 1]], axis=1)
    tgt_xz = pos_xz + 12.0 * look
    targets = np.stack([tgt_xz[:, 0], np.full(n_keys, FARM_TARGET_HEIGHT), tgt_xz[:, 1]], axis=1)
    times = np.linspace(START_FRAME, END_FRAME, n_keys)
    return positions, targets, times


def build_farm(out: Path) -> Path:
    """Write stages/farm.usda (+ geometry layer, assets, textures). Returns the root path."""
    (out / "textures").mkdir(parents=True, exist_ok=True)
    route = farm_route()
    assets = write_farm_assets(out)
    build_farm_geometry(out / "farm_geometry.usdc", route)
    write_planks_png(out / "textures" / "planks.png")

    stage = new_stage(out / "farm.usda", "Y", 1.0, "World")
    set_time_range(stage, START_FRAME, END_FRAME)
    stage.GetRootLayer().documentation = (
        "phrt-usd example: outdoor cartoon farm, 17 reflectors (PhrtReflectorAPI). "
        "Generated by tools/make_stages.py; do not edit by hand."
    )

    # Materials
    looks = "/World/Looks"
    UsdGeom.Scope.Define(stage, looks)
    mats = {
        "BarnRed": make_material(stage, f"{looks}/BarnRed", (0.62, 0.12, 0.08), 0.8),
        "Trim": make_material(stage, f"{looks}/Trim", (0.92, 0.90, 0.85), 0.7),
        "Roof": make_material(stage, f"{looks}/Roof", (0.30, 0.22, 0.20), 0.9),
        "Planks": make_material(
            stage, f"{looks}/Planks", (1.0, 1.0, 1.0), 0.8, texture="./textures/planks.png"
        ),
        "Brick": make_material(stage, f"{looks}/Brick", (0.55, 0.25, 0.18), 0.9),
        "Door": make_material(stage, f"{looks}/Door", (0.25, 0.35, 0.55), 0.6),
        "Silo": make_material(stage, f"{looks}/Silo", (0.75, 0.75, 0.72), 0.4, 0.6),
        "Shed": make_material(stage, f"{looks}/Shed", (0.55, 0.50, 0.40), 0.8),
        "Stone": make_material(stage, f"{looks}/Stone", (0.55, 0.55, 0.52), 0.9),
        "Hay": make_material(stage, f"{looks}/Hay", (0.85, 0.72, 0.30), 0.9),
        "Water": make_material(stage, f"{looks}/Water", (0.05, 0.20, 0.28), 0.05),
        "Metal": make_material(stage, f"{looks}/Metal", (0.50, 0.52, 0.55), 0.3, 1.0),
        "Glass": make_material(stage, f"{looks}/Glass", (0.10, 0.12, 0.15), 0.05),
        "Mirror": make_material(stage, f"{looks}/Mirror", (0.80, 0.80, 0.80), 0.02, 1.0),
    }

    # Bulk geometry, referenced; material bindings authored here as overs.
    scenery = stage.DefinePrim("/World/Scenery", "Xform")
    scenery.GetReferences().AddReference("./farm_geometry.usdc")
    for prim_path, mat in [
        ("Barn/Body/Walls", "BarnRed"),
        ("Barn/Body/Trim", "Trim"),
        ("Barn/Roof", "Roof"),
        ("House/Walls", "Planks"),
        ("House/Roof", "Roof"),
        ("House/Chimney", "Brick"),
        ("House/Door", "Door"),
        ("Silo/Tower", "Silo"),
        ("Silo/Dome", "Silo"),
        ("Shed", "Shed"),
        ("TroughYardWall", "Stone"),
        ("HayBales", "Hay"),
    ]:
        bind(stage.GetPrimAtPath(f"/World/Scenery/{prim_path}"), mats[mat])

    # Instanced assets: trees and fence sections.
    UsdGeom.Xform.Define(stage, "/World/Trees")
    for k, (x, z, kind) in enumerate(tree_positions(route, 60)):
        tree = UsdGeom.Xform.Define(stage, f"/World/Trees/Tree_{k:03d}")
        tree.GetPrim().GetReferences().AddReference(
            assets["tree_pine" if kind == 0 else "tree_round"]
        )
        rng_scale = 0.8 + 0.4 * ((k * 7919) % 100) / 100.0  # deterministic variety
        place(tree, (x, 0.0, z), yaw_deg=(k * 47.0) % 360.0, scale=rng_scale)
        tree.GetPrim().SetInstanceable(True)
    UsdGeom.Xform.Define(stage, "/World/Fences")
    for k, (pos, yaw) in enumerate(fence_transforms()):
        fence = UsdGeom.Xform.Define(stage, f"/World/Fences/Fence_{k:03d}")
        fence.GetPrim().GetReferences().AddReference(assets["fence_section"])
        place(fence, pos, yaw_deg=yaw)
        # the sections next to the gate stay editable (not instanced): a mixed case
        fence.GetPrim().SetInstanceable(not (pos[2] == 40.0 and abs(pos[0]) < 10.0))

    # ---- Reflectors (17) ----
    UsdGeom.Xform.Define(stage, "/World/Water")
    for k, (name, cx, cz, radius, priority, refl) in enumerate(FARM_PONDS):
        pond = author_mesh(
            stage, f"/World/Water/{name}", disc(pond_radius(radius, FARM_SEED + k), 40)
        )
        place(pond, (cx, 0.02, cz))
        bind(pond, mats["Water"])
        make_reflector(pond, priority, refl)
    floater = UsdGeom.Cylinder.Define(stage, "/World/Water/FloatingBarrel")
    floater.CreateRadiusAttr(0.35)
    floater.CreateHeightAttr(1.0)
    floater.CreateAxisAttr("X")
    translate = floater.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble)
    spin = floater.AddRotateYOp()
    cx, cz = FARM_PONDS[0][1], FARM_PONDS[0][2]
    for f in np.arange(START_FRAME, END_FRAME + 1, 4.0):
        phase = 2 * np.pi * (f - START_FRAME) / (END_FRAME - START_FRAME)
        translate.Set(
            Gf.Vec3d(
                cx + 3.0 * math.cos(phase),
                0.12 + 0.05 * math.sin(6 * phase),
                cz - 3.0 * math.sin(phase),
            ),
            Usd.TimeCode(float(f)),
        )
        spin.Set(float(math.degrees(phase) + 90.0), Usd.TimeCode(float(f)))
    bind(floater, mats["Metal"])
    make_reflector(floater, 1.0, 0.5)

    UsdGeom.Xform.Define(stage, "/World/TroughYard")
    for k, (x, z) in enumerate(FARM_TROUGHS):
        water = author_mesh(stage, f"/World/TroughYard/TroughWater{k}", quad(2.84, 0.84, "+y"))
        place(water, (x, 0.62, z))
        bind(water, mats["Water"])
        make_reflector(water, 2.0, 0.6)
    barrel = cylinder(0.35, 1.0, 16)
    for k, (x, z) in enumerate(FARM_MESH_BARRELS):
        b = author_mesh(stage, f"/World/TroughYard/Barrel{k}", barrel)
        place(b, (x, 0.0, z), yaw_deg=float(k * 23))
        bind(b, mats["Metal"])
        make_reflector(b, 1.0, 0.5)
    for k, (x, z) in enumerate(FARM_CYL_BARRELS):
        b = UsdGeom.Cylinder.Define(stage, f"/World/TroughYard/CylBarrel{k}")
        b.CreateRadiusAttr(0.35)
        b.CreateHeightAttr(1.0)
        b.CreateAxisAttr("Y")
        place(b, (x, 0.5, z))
        bind(b, mats["Metal"])
        make_reflector(b, 1.0, 0.5)

    UsdGeom.Xform.Define(stage, "/World/HouseWindows")
    for k, x in enumerate((15.3, 20.7)):
        w = author_mesh(stage, f"/World/HouseWindows/Window{k}", quad(1.4, 1.2, "+z"))
        place(w, (x, 2.9, -9.96))
        bind(w, mats["Glass"])
        make_reflector(w, 3.0, 0.8)
    mirror = author_mesh(stage, "/World/BarnMirror", quad(2.0, 2.5, "+z"))
    place(mirror, (-13.95, 2.5, -16.0), yaw_deg=90.0)
    bind(mirror, mats["Mirror"])
    make_reflector(mirror, 4.0, 0.9)

    # ---- Lights ----
    UsdGeom.Xform.Define(stage, "/World/Lights")
    sun = UsdLux.DistantLight.Define(stage, "/World/Lights/Sun")
    sun.CreateIntensityAttr(3.0)
    sun.CreateAngleAttr(0.53)
    sun.CreateColorAttr(Gf.Vec3f(1.0, 0.95, 0.85))
    sun.AddRotateXYZOp().Set(Gf.Vec3f(-45.0, 35.0, 0.0))
    sky = UsdLux.DomeLight.Define(stage, "/World/Lights/Sky")
    sky.CreateIntensityAttr(0.6)
    sky.CreateTextureFileAttr(Sdf.AssetPath("./textures/sky.exr"))
    sky.CreateTextureFormatAttr(UsdLux.Tokens.latlong)
    write_sky_exr(out / "textures" / "sky.exr", sun_direction(sun))

    # ---- Camera and its path ----
    positions, targets, times = farm_camera_keys(route)
    make_camera(
        stage, "/World/Camera", 20.0, (0.1, 500.0), positions[0], targets[0], (0.0, 1.0, 0.0)
    )
    make_camera_path(stage, "/World/CameraPath", "/World/Camera", positions, targets, times)
    make_render_settings(stage, "/World/Camera")
    stage.GetRootLayer().Save()
    return out / "farm.usda"


# --------------------------------------------------------------------------------------
# Sewer (built in a local Y-up metre frame, written Z-up in centimetres)
# --------------------------------------------------------------------------------------

#: Stage units per metre in the sewer (metersPerUnit = 0.01).
SEWER_UNITS_PER_METRE = 100.0
#: Local (Y-up, metres) -> sewer world (Z-up, cm): x' = x, y' = -z, z' = y (a rotation).
SEWER_FROM_LOCAL = np.diag([1.0, 1.0, 1.0, 1.0])
SEWER_FROM_LOCAL[:3, :3] = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]) * 100.0

#: Main (wet) tunnel: along local x, centred on z = 0; walkways on both sides of a channel.
MAIN_WIDTH, MAIN_WALL, CHANNEL_HALF = 4.0, 2.2, 0.8
WATER_Y, CHANNEL_FLOOR_Y = -0.4, -0.9
#: Dry service tunnels: width and wall height.
DRY_WIDTH, DRY_WALL = 3.0, 2.2
#: Chambers: centre x (local), half size, ceiling height.
JUNCTION_X, SUMP_X, CHAMBER_HALF, CHAMBER_HEIGHT = 0.0, 28.0, 3.0, 5.0
#: Chamber wall thickness (m). Tunnel shells stop at the chamber's *outer* wall face
#: (CHAMBER_HALF + CHAMBER_WALL from the centre): running them on to the inner face would
#: make their walls coincide with the door jambs over the wall's thickness (z-fighting).
CHAMBER_WALL = 0.2
WEST_END_X, NORTH_END_Z, SOUTH_END_Z = -16.0, -24.0, 22.0
#: Length of one tunnel subdivision along its axis (metres); sets the triangle count.
TUNNEL_STEP = 0.1


def sewer_mesh(mesh: Mesh) -> Mesh:
    """Convert a local (Y-up, metres) mesh to sewer world space (Z-up, centimetres)."""
    return mesh.transformed(SEWER_FROM_LOCAL)


def sewer_point(p: Sequence[float]) -> tuple[float, float, float]:
    q = SEWER_FROM_LOCAL[:3, :3] @ np.asarray(p, float)
    return (float(q[0]), float(q[1]), float(q[2]))


def chamber_walls(cx: float, openings: dict[str, float], wall_height_open: float) -> Mesh:
    """Walls, floor slab and ceiling of a square chamber centred at (cx, 0, 0).

    openings: side ("+x", "-x", "+z", "-z") -> opening width (m); openings are
    ``wall_height_open`` high, the wall above them is solid (a lintel).
    """
    h, t, top = CHAMBER_HALF, CHAMBER_WALL, CHAMBER_HEIGHT
    parts = [box((2 * h + 2 * t, t, 2 * h + 2 * t), (cx, top + t / 2, 0))]
    for side in ("+x", "-x", "+z", "-z"):
        sign = 1.0 if side[0] == "+" else -1.0
        w = openings.get(side, 0.0)
        along_x = side[1] == "z"  # wall runs along x when it closes a z side

        def wall(
            a0: float, a1: float, y0: float, y1: float, sign: float = sign, along_x: bool = along_x
        ) -> Mesh:
            size_a, centre_a = a1 - a0, (a0 + a1) / 2
            if along_x:
                return box((size_a, y1 - y0, t), (cx + centre_a, (y0 + y1) / 2, sign * (h + t / 2)))
            return box((t, y1 - y0, size_a), (cx + sign * (h + t / 2), (y0 + y1) / 2, centre_a))

        lo = CHANNEL_FLOOR_Y
        if w == 0.0:
            parts.append(wall(-h - t, h + t, lo, top))
        else:
            parts += [
                wall(-h - t, -w / 2, lo, top),
                wall(w / 2, h + t, lo, top),
                wall(-w / 2, w / 2, wall_height_open, top),
            ]
    return merge(parts)


def walkway_slabs(x0: float, x1: float) -> Mesh:
    """Walkways on both sides of the channel (their inner faces are the channel walls)."""
    depth = -CHANNEL_FLOOR_Y
    width = MAIN_WIDTH / 2 - CHANNEL_HALF
    zc = CHANNEL_HALF + width / 2
    return merge(
        [
            box((x1 - x0, depth, width), ((x0 + x1) / 2, -depth / 2, zc)),
            box((x1 - x0, depth, width), ((x0 + x1) / 2, -depth / 2, -zc)),
            box((x1 - x0, 0.2, 2 * CHANNEL_HALF), ((x0 + x1) / 2, CHANNEL_FLOOR_Y - 0.1, 0.0)),
        ]
    )


def railing(x0: float, x1: float, z: float) -> Mesh:
    """Posts every 1.5 m and two rails along x at the walkway edge z."""
    posts = [box((0.06, 1.0, 0.06), (x, 0.5, z)) for x in np.arange(x0 + 0.3, x1, 1.5)]
    rails = [box((x1 - x0, 0.05, 0.05), ((x0 + x1) / 2, y, z)) for y in (0.55, 1.0)]
    return merge(posts + rails)


def grate(x: float, width: float = 1.0, bars: int = 12) -> Mesh:
    """Bars across the channel (along z) just below the walkway level, centred at x."""
    xs = x - width / 2 + (np.arange(bars) + 0.5) * width / bars
    frame = [box((width, 0.08, 0.06), (x, -0.06, sz * (CHANNEL_HALF - 0.03))) for sz in (-1, 1)]
    return merge([box((0.04, 0.08, 2 * CHANNEL_HALF), (bx, -0.06, 0.0)) for bx in xs] + frame)


def pipe_mesh(
    x0: float,
    x1: float,
    y: float,
    z: float,
    radius: float,
    segments: int = 12,
    ring_step: float = 0.5,
) -> Mesh:
    """A pipe (closed cylinder) along x from x0 to x1 at height y, offset z."""
    rings = max(1, int(round((x1 - x0) / ring_step)))
    rot = np.eye(4)
    rot[:3, :3] = [[0, 1.0, 0], [-1.0, 0, 0], [0, 0, 1.0]]  # +y axis -> +x axis
    rot[:3, 3] = [x0, y, z]
    return cylinder(radius, x1 - x0, segments, rings).transformed(rot)


def swap_xz(mesh: Mesh, x_at: float) -> Mesh:
    """Turn a mesh built along +x into one along +z (yaw -90 degrees) placed at x = x_at."""
    return mesh.moved((x_at, 0.0, 0.0), yaw_deg=-90.0)


def build_sewer_geometry(path: Path) -> None:
    """Write sewer_geometry.usdc: tunnel shells, chambers, walkways, grates, dry pipes."""
    stage = new_stage(path, "Z", 0.01, "Geometry")
    parts: dict[str, list[Mesh]] = {
        "Shell": [],
        "Walkways": [],
        "Railings": [],
        "Grates": [],
        "DryPipes": [],
        "Chambers": [],
    }
    ch = CHAMBER_HALF
    cw = ch + CHAMBER_WALL  # chamber centre to its outer wall face: where the shells stop
    # wet main tunnel: west arm and middle stretch, both along +x
    for x0, x1 in ((WEST_END_X, JUNCTION_X - ch), (JUNCTION_X + ch, SUMP_X - ch)):
        # shell ends at the chamber's outer wall face (see CHAMBER_WALL); the walkways
        # below it run on to the inner face and floor the doorway
        sx0 = x0 if x0 == WEST_END_X else x0 + CHAMBER_WALL
        sx1 = x1 - CHAMBER_WALL
        n = int(round((sx1 - sx0) / TUNNEL_STEP))
        parts["Shell"].append(
            tunnel_shell(MAIN_WIDTH, MAIN_WALL, sx1 - sx0, 16, n, 0.0).moved((sx0, 0, 0))
        )
        parts["Walkways"].append(walkway_slabs(x0, x1))
        for z in (CHANNEL_HALF + 0.05, -CHANNEL_HALF - 0.05):
            parts["Railings"].append(railing(x0, x1, z))
    # west end wall
    parts["Shell"].append(box((0.2, 7.0, MAIN_WIDTH + 0.4), (WEST_END_X - 0.1, 2.5, 0)))
    # dry tunnels along z: north of the junction (z < 0) and south of the sump (z > 0)
    for x_at, z0, z1 in ((JUNCTION_X, NORTH_END_Z, -ch), (SUMP_X, ch, SOUTH_END_Z)):
        # shell ends at the chamber's outer wall face (see CHAMBER_WALL)
        sz0, sz1 = (z0, -cw) if z1 == -ch else (cw, z1)
        n = int(round((sz1 - sz0) / TUNNEL_STEP))
        shell = tunnel_shell(DRY_WIDTH, DRY_WALL, sz1 - sz0, 14, n, 0.0)
        # built along +x from 0; rotate so it runs along +z from sz0
        parts["Shell"].append(shell.moved((x_at, 0.0, sz0), yaw_deg=-90.0))
        parts["Walkways"].append(box((DRY_WIDTH, 0.3, z1 - z0), (x_at, -0.15, (z0 + z1) / 2)))
        for dx, y in ((-1.2, 1.4), (-1.2, 1.75)):
            parts["DryPipes"].append(
                pipe_mesh(0.0, z1 - z0, y, dx, 0.1, 12, 0.25).moved((x_at, 0, z0), yaw_deg=-90.0)
            )
        end_z = z0 if z0 < -ch else z1
        parts["Shell"].append(box((DRY_WIDTH + 0.4, 6.0, 0.2), (x_at, 2.5, end_z)))
    # chambers: junction (openings west, east, north) and sump (west, south)
    parts["Chambers"].append(
        chamber_walls(JUNCTION_X, {"-x": MAIN_WIDTH, "+x": MAIN_WIDTH, "-z": DRY_WIDTH}, MAIN_WALL)
    )
    parts["Chambers"].append(chamber_walls(SUMP_X, {"-x": MAIN_WIDTH, "+z": DRY_WIDTH}, MAIN_WALL))
    # chamber floors: the junction continues the channel, the sump has a square pool
    parts["Walkways"].append(walkway_slabs(JUNCTION_X - ch, JUNCTION_X + ch))
    sump = SUMP_POOL_HALF
    for dx, dz, sx, sz in (
        (0, ch - (ch - sump) / 2, 2 * ch, ch - sump),
        (0, -ch + (ch - sump) / 2, 2 * ch, ch - sump),
        (ch - (ch - sump) / 2, 0, ch - sump, 2 * sump),
        (-ch + (ch - sump) / 2, 0, ch - sump, 2 * sump),
    ):
        parts["Walkways"].append(box((sx, 0.9, sz), (SUMP_X + dx, -0.45, dz)))
    parts["Walkways"].append(box((2 * sump, 0.2, 2 * sump), (SUMP_X, CHANNEL_FLOOR_Y - 0.1, 0)))
    # grates at the chamber entrances
    for x in (JUNCTION_X - ch - 0.6, JUNCTION_X + ch + 0.6, SUMP_X - ch - 0.6, -10.0, 12.0):
        parts["Grates"].append(grate(x))

    for name, meshes in parts.items():
        author_mesh(stage, f"/Geometry/{name}", sewer_mesh(merge(meshes)))
    # ladders in the chambers: implicit cubes (rails and rungs), Z-up centimetres
    UsdGeom.Xform.Define(stage, "/Geometry/Ladder")
    for k, (dx, size) in enumerate(((-0.25, (0.05, 0.05, 4.5)), (0.25, (0.05, 0.05, 4.5)))):
        rail = UsdGeom.Cube.Define(stage, f"/Geometry/Ladder/Rail{k}")
        rail.AddTranslateOp().Set(Gf.Vec3d(*sewer_point((JUNCTION_X + 1.5 + dx, 2.25, -2.9))))
        rail.AddScaleOp().Set(Gf.Vec3f(*(np.array(size) * 100.0)))
    for k in range(12):
        rung = UsdGeom.Cube.Define(stage, f"/Geometry/Ladder/Rung{k:02d}")
        rung.AddTranslateOp().Set(Gf.Vec3d(*sewer_point((JUNCTION_X + 1.5, 0.3 + 0.35 * k, -2.9))))
        rung.AddScaleOp().Set(Gf.Vec3f(55.0, 3.0, 3.0))
    stage.GetRootLayer().Save()


#: Half size (m) of the square sump pool in the sump chamber.
SUMP_POOL_HALF = 1.5


def sewer_route() -> np.ndarray:
    """(w, 2) local (x, z) route: north dry tunnel -> junction -> east along the south
    walkway -> sump chamber -> south dry tunnel."""
    waypoints = np.array(
        [
            [JUNCTION_X, NORTH_END_Z + 1.5],
            [JUNCTION_X, -2.5],
            [JUNCTION_X + 1.0, 1.3],
            [SUMP_X - 3.5, 1.3],
            [SUMP_X - 0.5, 1.0],
            [SUMP_X, 4.0],
            [SUMP_X, SOUTH_END_Z - 1.5],
        ]
    )
    return smooth_polyline(waypoints, iterations=5)


def sewer_camera_keys(n_keys: int = 37) -> tuple[np.ndarray, ...]:
    """Control points (positions (k,3), targets (k,3) in sewer world cm, times (k,))."""
    route = sewer_route()
    pos_xz = resample_polyline(route, n_keys)
    dense = resample_polyline(route, 8 * n_keys)
    # look 6 m ahead along the route (a point further along the curve, clamped at the end)
    step = float(np.linalg.norm(dense[1] - dense[0]))
    ahead_idx = np.minimum(np.arange(n_keys) * 8 + int(round(6.0 / step)), len(dense) - 1)
    tgt_xz = dense[ahead_idx]
    last_dir = dense[-1] - dense[-8]
    short = np.linalg.norm(tgt_xz - pos_xz, axis=1) < 3.0
    tgt_xz[short] = pos_xz[short] + 6.0 * last_dir / np.linalg.norm(last_dir)
    eye_y, tgt_y = 1.6, 1.1
    pos = np.stack([pos_xz[:, 0], np.full(n_keys, eye_y), pos_xz[:, 1]], axis=1)
    tgt = np.stack([tgt_xz[:, 0], np.full(n_keys, tgt_y), tgt_xz[:, 1]], axis=1)
    to_world = SEWER_FROM_LOCAL[:3, :3]
    return pos @ to_world.T, tgt @ to_world.T, np.linspace(START_FRAME, END_FRAME, n_keys)


def build_sewer(out: Path) -> Path:
    """Write stages/sewer.usda (+ sewer_geometry.usdc). Returns the root path."""
    build_sewer_geometry(out / "sewer_geometry.usdc")
    stage = new_stage(out / "sewer.usda", "Z", 0.01, "World")
    set_time_range(stage, START_FRAME, END_FRAME)
    stage.GetRootLayer().documentation = (
        "phrt-usd example: sewer tunnel network, Z-up, centimetres, 33 reflectors "
        "(PhrtReflectorAPI). Generated by tools/make_stages.py; do not edit by hand."
    )
    looks = "/World/Looks"
    UsdGeom.Scope.Define(stage, looks)
    mats = {
        "Concrete": make_material(stage, f"{looks}/Concrete", (0.42, 0.40, 0.36), 0.9),
        "Walkway": make_material(stage, f"{looks}/Walkway", (0.33, 0.31, 0.28), 0.9),
        "Rail": make_material(stage, f"{looks}/Rail", (0.75, 0.55, 0.10), 0.5, 0.5),
        "Grate": make_material(stage, f"{looks}/Grate", (0.15, 0.15, 0.16), 0.6, 1.0),
        "Rust": make_material(stage, f"{looks}/Rust", (0.45, 0.22, 0.10), 0.8, 0.3),
        "Water": make_material(stage, f"{looks}/Water", (0.10, 0.16, 0.10), 0.05),
        "WetTile": make_material(stage, f"{looks}/WetTile", (0.20, 0.35, 0.35), 0.15),
        "Copper": make_material(stage, f"{looks}/Copper", (0.80, 0.50, 0.35), 0.25, 1.0),
    }
    scenery = stage.DefinePrim("/World/Scenery", "Xform")
    scenery.GetReferences().AddReference("./sewer_geometry.usdc")
    for name, mat in (
        ("Shell", "Concrete"),
        ("Chambers", "Concrete"),
        ("Walkways", "Walkway"),
        ("Railings", "Rail"),
        ("Grates", "Grate"),
        ("DryPipes", "Rust"),
        ("Ladder", "Rail"),
    ):
        bind(
            stage.GetPrimAtPath(f"/World/Scenery/{name}"), mats[name == "Ladder" and "Rail" or mat]
        )

    # ---- Reflectors (33) ----
    ch = CHAMBER_HALF
    UsdGeom.Xform.Define(stage, "/World/Water")
    segments: list[tuple[float, float]] = []
    for x0, x1, n in ((WEST_END_X, JUNCTION_X - ch, 4), (JUNCTION_X + ch, SUMP_X - ch, 6)):
        edges = np.linspace(x0, x1, n + 1)
        segments += list(zip(edges[:-1], edges[1:], strict=True))
    segments.append((JUNCTION_X - ch, JUNCTION_X + ch))
    for k, (x0, x1) in enumerate(segments):
        seg = author_mesh(
            stage, f"/World/Water/Channel{k:02d}", sewer_mesh(quad(x1 - x0, 2 * CHANNEL_HALF, "+y"))
        )
        place(seg, sewer_point(((x0 + x1) / 2, WATER_Y, 0.0)))
        bind(seg, mats["Water"])
        make_reflector(seg, 0.5 + 0.5 * (k % 2), 0.6)
    pool = author_mesh(
        stage,
        "/World/Water/SumpPool",
        sewer_mesh(quad(2 * SUMP_POOL_HALF, 2 * SUMP_POOL_HALF, "+y")),
    )
    place(pool, sewer_point((SUMP_X, WATER_Y, 0.0)))
    bind(pool, mats["Water"])
    make_reflector(pool, 1.0, 0.6)

    UsdGeom.Xform.Define(stage, "/World/WetPanels")
    panel_x = np.linspace(JUNCTION_X + ch + 2.0, SUMP_X - ch - 2.0, 6)
    k = 0
    for side, z, facing in (
        ("S", MAIN_WIDTH / 2 - 0.03, "-z"),
        ("N", -MAIN_WIDTH / 2 + 0.03, "+z"),
    ):
        for j, x in enumerate(panel_x + (0.0 if side == "S" else 0.8)):
            p = author_mesh(
                stage, f"/World/WetPanels/Panel{side}{j}", sewer_mesh(quad(2.4, 1.2, facing))
            )
            place(p, sewer_point((x, 0.9, z)))
            bind(p, mats["WetTile"])
            make_reflector(p, 1.0 + (j % 3), 0.45)
            k += 1
    for j, (cx, z, facing) in enumerate(
        (
            (JUNCTION_X, ch - 0.03, "-z"),
            (JUNCTION_X + 1.0, -ch + 0.03, "+z"),
            (SUMP_X - 1.6, ch - 0.03, "-z"),
            (SUMP_X + 1.6, -ch + 0.03, "+z"),
        )
    ):
        p = author_mesh(
            stage, f"/World/WetPanels/ChamberPanel{j}", sewer_mesh(quad(2.0, 2.0, facing))
        )
        place(p, sewer_point((cx - 1.0 if j == 0 else cx, 1.3, z)))
        bind(p, mats["WetTile"])
        make_reflector(p, 2.0, 0.5)

    UsdGeom.Xform.Define(stage, "/World/Pipes")
    length = SUMP_X - JUNCTION_X - 2 * ch
    for j, (y, z) in enumerate(
        ((1.8, 1.75), (2.05, 1.5), (1.8, -1.75), (2.05, -1.5), (0.15, -1.85))
    ):
        pipe = UsdGeom.Cylinder.Define(stage, f"/World/Pipes/Pipe{j}")
        pipe.CreateAxisAttr("X")
        pipe.CreateRadiusAttr(10.0 if j < 4 else 6.0)
        pipe.CreateHeightAttr(float(length * SEWER_UNITS_PER_METRE))
        place(pipe, sewer_point((JUNCTION_X + ch + length / 2, y, z)))
        bind(pipe, mats["Copper"])
        make_reflector(pipe, 1.0 + j % 3, 0.55)

    # ---- Lights ----
    UsdGeom.Xform.Define(stage, "/World/Lights")
    lamp_spots = [(x, 0.0) for x in np.arange(WEST_END_X + 3.0, SUMP_X - ch, 7.0)]
    lamp_spots += [(JUNCTION_X, z) for z in np.arange(NORTH_END_Z + 3.0, -ch, 7.0)]
    lamp_spots += [(SUMP_X, z) for z in np.arange(ch + 3.0, SOUTH_END_Z, 7.0)]
    for j, (x, z) in enumerate(lamp_spots):
        lamp = UsdLux.SphereLight.Define(stage, f"/World/Lights/Lamp{j:02d}")
        lamp.CreateRadiusAttr(8.0)
        # Normalized: intensity 120 / 4 = 30 (usd/lights.py local_intensity), a lamp of
        # 30 at 1 m whatever its radius.
        lamp.CreateNormalizeAttr(True)
        lamp.CreateIntensityAttr(120.0)
        lamp.CreateColorAttr(Gf.Vec3f(1.0, 0.85, 0.6))
        top = (MAIN_WALL + MAIN_WIDTH / 2) if abs(z) < 0.5 else (DRY_WALL + DRY_WIDTH / 2)
        place(lamp, sewer_point((x, top - 0.25, z)))
    shaft = UsdLux.RectLight.Define(stage, "/World/Lights/ShaftLight")
    shaft.CreateWidthAttr(100.0)
    shaft.CreateHeightAttr(100.0)
    shaft.CreateIntensityAttr(15.0)
    shaft.CreateColorAttr(Gf.Vec3f(0.8, 0.9, 1.0))
    place(shaft, sewer_point((JUNCTION_X, CHAMBER_HEIGHT - 0.05, 0.0)))  # emits along -Z (down)
    ambient = UsdLux.DomeLight.Define(stage, "/World/Lights/Ambient")
    ambient.CreateIntensityAttr(0.05)
    ambient.CreateColorAttr(Gf.Vec3f(0.6, 0.7, 0.8))

    # ---- Cameras ----
    positions, targets, times = sewer_camera_keys()
    up = (0.0, 0.0, 1.0)
    make_camera(stage, "/World/Camera", 18.0, (5.0, 10000.0), positions[0], targets[0], up)
    make_camera_path(stage, "/World/CameraPath", "/World/Camera", positions, targets, times)
    inspect = UsdGeom.Camera.Define(stage, "/World/InspectionCam")
    inspect.CreateFocalLengthAttr(24.0)
    inspect.CreateHorizontalApertureAttr(HORIZONTAL_APERTURE_MM)
    inspect.CreateVerticalApertureAttr(VERTICAL_APERTURE_MM)
    inspect.CreateClippingRangeAttr(Gf.Vec2f(5.0, 10000.0))
    translate = inspect.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble)
    rotate = inspect.AddRotateXYZOp()
    frames = np.unique(np.append(np.arange(START_FRAME, END_FRAME + 1, 4.0), END_FRAME))
    s = (frames - START_FRAME) / (END_FRAME - START_FRAME)
    # walks east along the north walkway while panning from looking west to looking east;
    # rotateXYZ = (90 + pitch, 0, yaw): X by 90 turns the camera's -Z view to +Y, Z yaws
    xs = JUNCTION_X + ch + 1.0 + s * (length - 2.0)
    yaw = 90.0 - 180.0 * (0.5 - 0.5 * np.cos(np.pi * s))  # +90: looking -X (west)
    pitch = -12.0 + 6.0 * np.sin(2 * np.pi * s)
    for f, x, yw, pt in zip(frames, xs, yaw, pitch, strict=True):
        translate.Set(Gf.Vec3d(*sewer_point((x, 1.7, -1.4))), Usd.TimeCode(float(f)))
        rotate.Set(Gf.Vec3f(90.0 + float(pt), 0.0, float(yw)), Usd.TimeCode(float(f)))
    # I about the 90th percentile of the visible reflectors' V along this path (5.6e-3;
    # the farm's default 1e-4 is its own 85th): the paper's "I bigger than V most of the
    # time". The sewer's walls are near and large, so its V run ~30x the farm's.
    make_render_settings(stage, "/World/Camera", selectionWeight=0.005)
    stage.GetRootLayer().Save()
    return out / "sewer.usda"


# --------------------------------------------------------------------------------------
# Extreme stages (Y-up, metres unless said otherwise): small scenes for stiff cases
# --------------------------------------------------------------------------------------

#: Frame range of the extreme stages (static cameras; a few frames to exercise the loop).
EXTREME_END_FRAME = 8.0


def extreme_stage(
    out: Path,
    name: str,
    doc: str,
    eye: Sequence[float],
    target: Sequence[float],
    clip: tuple[float, float] = (0.01, 1000.0),
    scale: float = 1.0,
    offset: Sequence[float] = (0.0, 0.0, 0.0),
) -> tuple[Usd.Stage, dict[str, UsdShade.Material]]:
    """A stage with floor, DistantLight, static camera and render settings.

    ``scale`` multiplies every length of the floor/camera; ``offset`` (metres, double)
    translates them. Returns the stage and its materials (Grey, Mirror, Red).
    """
    stage = new_stage(out / "extreme" / f"{name}.usda", "Y", 1.0, "World")
    set_time_range(stage, START_FRAME, EXTREME_END_FRAME)
    stage.GetRootLayer().documentation = f"phrt-usd extreme case: {doc}"
    looks = "/World/Looks"
    UsdGeom.Scope.Define(stage, looks)
    mats = {
        "Grey": make_material(stage, f"{looks}/Grey", (0.6, 0.6, 0.6), 0.8),
        "Mirror": make_material(stage, f"{looks}/Mirror", (0.9, 0.9, 0.9), 0.0, 1.0),
        "Red": make_material(stage, f"{looks}/Red", (0.8, 0.1, 0.1), 0.5),
    }
    floor = author_mesh(stage, "/World/Floor", quad(6.0 * scale, 6.0 * scale, "+y"))
    place(floor, offset)
    bind(floor, mats["Grey"])
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    sun.CreateIntensityAttr(3.0)
    sun.AddRotateXYZOp().Set(Gf.Vec3f(-50.0, 30.0, 0.0))
    o = np.asarray(offset, float)
    make_camera(
        stage,
        "/World/Camera",
        20.0,
        clip,
        o + np.asarray(eye) * scale,
        o + np.asarray(target) * scale,
        (0.0, 1.0, 0.0),
    )
    make_render_settings(stage, "/World/Camera")
    return stage, mats


def mirror_and_sphere(
    stage: Usd.Stage, mats: dict[str, UsdShade.Material], scale: float, offset: Sequence[float]
) -> None:
    """A 2 x 2 mirror at z = -1 facing +z and a red sphere in front of it."""
    mirror = author_mesh(stage, "/World/Mirror", quad(2.0 * scale, 2.0 * scale, "+z"))
    place(mirror, np.asarray(offset) + np.array([0.0, 1.0, -1.0]) * scale)
    bind(mirror, mats["Mirror"])
    make_reflector(mirror, 1.0, 1.0)
    ball = UsdGeom.Sphere.Define(stage, "/World/Ball")
    ball.CreateRadiusAttr(0.4 * scale)
    place(ball, np.asarray(offset) + np.array([0.5, 0.4, 0.0]) * scale)
    bind(ball, mats["Red"])


#: name -> (what it exercises, planted problem "prim path.attribute" or None)
EXTREME_CASES: dict[str, tuple[str, str | None]] = {
    "parallel_mirrors": (
        "two facing perfect mirrors, camera between them at an angle: "
        "reflection rays bounce until the bounce limit",
        None,
    ),
    "far_from_origin": (
        "mirror + sphere scene translated to (1e6, 0, 1e6) m: float32 precision (render origin)",
        None,
    ),
    "tiny_scale": (
        "mirror + sphere scene 1e-3 m across (metersPerUnit 1): ray offsets "
        "and clipping at tiny scale",
        None,
    ),
    "camera_touching": ("camera 1e-6 m in front of a mirror looking at it: D -> 0", None),
    "zero_area_reflector": (
        "reflector whose points are collinear / coincident: zero area",
        "/World/ZeroAreaMirror.points",
    ),
    "degenerate_reflector": (
        "reflector with a faceVertexIndices entry out of range and a 2-vertex face",
        "/World/BrokenMirror.faceVertexIndices",
    ),
    "nan_points": ("reflector with a NaN coordinate in its points", "/World/NanMirror.points"),
    "priority_zero": ("reflector with K = 0 (valid: never worth tracing by R)", None),
    "priority_huge": ("reflector with K = 1e9 (valid: R must stay finite)", None),
    "negative_priority": ("reflector with K = -1", "/World/Mirror.phrt:priority"),
}


def build_extreme(out: Path) -> list[Path]:
    """Write every stage of EXTREME_CASES under out/extreme/. Returns their paths."""
    paths = []

    def done(stage: Usd.Stage) -> None:
        stage.GetRootLayer().Save()
        paths.append(Path(stage.GetRootLayer().realPath))

    doc = {name: text for name, (text, _) in EXTREME_CASES.items()}
    eye, target = (0.0, 1.2, 3.0), (0.0, 0.8, -1.0)

    stage, mats = extreme_stage(
        out, "parallel_mirrors", doc["parallel_mirrors"], (0.0, 1.5, 1.2), (0.8, 1.3, -2.0)
    )
    for k, (z, facing) in enumerate(((-2.0, "+z"), (2.0, "-z"))):
        m = author_mesh(stage, f"/World/Mirror{k}", quad(4.0, 3.0, facing))
        place(m, (0.0, 1.5, z))
        bind(m, mats["Mirror"])
        if k == 0:
            make_reflector(m, 1.0, 1.0)
        else:  # API only, no attributes: the schema defaults (K = 1, F = 1) apply
            m.GetPrim().AddAppliedSchema(REFLECTOR_API)
    ball = UsdGeom.Sphere.Define(stage, "/World/Ball")
    ball.CreateRadiusAttr(0.3)
    place(ball, (0.8, 0.3, 0.0))
    bind(ball, mats["Red"])
    done(stage)

    far = (1.0e6, 0.0, 1.0e6)
    stage, mats = extreme_stage(
        out, "far_from_origin", doc["far_from_origin"], eye, target, offset=far
    )
    mirror_and_sphere(stage, mats, 1.0, far)
    done(stage)

    tiny = 1.0e-3 / 6.0  # the floor (6 units) becomes 1e-3 m across
    stage, mats = extreme_stage(
        out, "tiny_scale", doc["tiny_scale"], eye, target, clip=(1.0e-6, 1.0), scale=tiny
    )
    mirror_and_sphere(stage, mats, tiny, (0.0, 0.0, 0.0))
    done(stage)

    stage, mats = extreme_stage(
        out,
        "camera_touching",
        doc["camera_touching"],
        (0.0, 1.0, -1.0 + 1.0e-6),
        (0.0, 1.0, -2.0),
        clip=(1.0e-7, 100.0),
    )
    mirror_and_sphere(stage, mats, 1.0, (0.0, 0.0, 0.0))
    done(stage)

    stage, mats = extreme_stage(out, "zero_area_reflector", doc["zero_area_reflector"], eye, target)
    mirror_and_sphere(stage, mats, 1.0, (0.0, 0.0, 0.0))
    flat = Mesh(
        np.array(
            [
                [0.0, 0.5, 0.0],
                [1.0, 0.5, 0.0],
                [2.0, 0.5, 0.0],
                [2.0, 0.5, 0.0],
                [0.0, 0.5, 0.0],
                [0.0, 0.5, 0.0],
            ]
        ),
        np.array([4, 3], np.int32),
        np.array([0, 1, 2, 3, 3, 4, 5], np.int32),
    )
    z = author_mesh(stage, "/World/ZeroAreaMirror", flat)
    bind(z, mats["Mirror"])
    make_reflector(z, 2.0, 1.0)
    done(stage)

    stage, mats = extreme_stage(
        out, "degenerate_reflector", doc["degenerate_reflector"], eye, target
    )
    mirror_and_sphere(stage, mats, 1.0, (0.0, 0.0, 0.0))
    broken = Mesh(
        quad(1.0, 1.0, "+z").points + [-1.0, 1.0, 0.0],
        np.array([4, 2, 3], np.int32),
        np.array([0, 1, 2, 7, 0, 1, 0, 2, 3], np.int32),
    )  # 7 is out of range
    b = author_mesh(stage, "/World/BrokenMirror", broken)
    bind(b, mats["Mirror"])
    make_reflector(b, 2.0, 1.0)
    done(stage)

    stage, mats = extreme_stage(out, "nan_points", doc["nan_points"], eye, target)
    mirror_and_sphere(stage, mats, 1.0, (0.0, 0.0, 0.0))
    pts = quad(1.0, 1.0, "+z").points + [-1.0, 1.0, 0.0]
    pts[2, 1] = np.nan
    n = author_mesh(
        stage, "/World/NanMirror", Mesh(pts, np.array([4], np.int32), np.arange(4, dtype=np.int32))
    )
    bind(n, mats["Mirror"])
    make_reflector(n, 2.0, 1.0)
    done(stage)

    for name, priority in (
        ("priority_zero", 0.0),
        ("priority_huge", 1.0e9),
        ("negative_priority", -1.0),
    ):
        stage, mats = extreme_stage(out, name, doc[name], eye, target)
        mirror_and_sphere(stage, mats, 1.0, (0.0, 0.0, 0.0))
        stage.GetPrimAtPath("/World/Mirror").GetAttribute("phrt:priority").Set(priority)
        done(stage)
    return paths


# --------------------------------------------------------------------------------------
# Checks and previews (used by main --preview and by tests/top/test_stages.py)
# --------------------------------------------------------------------------------------


def is_reflector(prim: Usd.Prim) -> bool:
    """True if ``prim`` has PhrtReflectorAPI applied.

    ``Usd.Prim.GetAppliedSchemas()`` drops API schemas that no plugin registers, so this
    reads the prim type info, which keeps every name in ``apiSchemas`` with or without
    the phrt schema plugin.
    """
    return REFLECTOR_API in prim.GetPrimTypeInfo().GetAppliedAPISchemas()


def reflector_prims(stage: Usd.Stage) -> list[Usd.Prim]:
    return [p for p in stage.Traverse() if is_reflector(p)]


def camera_path_samples(
    stage: Usd.Stage, path: str = "/World/CameraPath"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frames (n,), eyes (n, 3), targets (n, 3)) of a PhrtCameraPath, every frame."""
    prim = stage.GetPrimAtPath(path)
    positions = np.array(prim.GetAttribute("phrt:positions").Get(), float)
    targets = np.array(prim.GetAttribute("phrt:targets").Get(), float)
    key_times = np.array(prim.GetAttribute("phrt:keyTimes").Get(), float)
    interp = prim.GetAttribute("phrt:interpolation").Get()
    start = prim.GetAttribute("phrt:startFrame").Get()
    end = prim.GetAttribute("phrt:endFrame").Get()
    frames = np.arange(start, end + 1.0)
    return (
        frames,
        evaluate_camera_path(positions, key_times, frames, interp),
        evaluate_camera_path(targets, key_times, frames, interp),
    )


def reflectors_in_view(
    stage: Usd.Stage,
    frames: np.ndarray,
    eyes: np.ndarray,
    targets: np.ndarray,
    up: np.ndarray,
    max_distance: float,
    focal_mm: float,
) -> np.ndarray:
    """(n,) number of reflector bounding-box centres inside the view frustum per frame.

    A rough visibility figure: no occlusion, frustum cut at ``max_distance`` (stage units).
    """
    refl = reflector_prims(stage)
    counts = np.zeros(len(frames), int)
    tan_x = HORIZONTAL_APERTURE_MM / 2 / focal_mm
    tan_y = VERTICAL_APERTURE_MM / 2 / focal_mm
    animated = any(UsdGeom.Xformable(p).TransformMightBeTimeVarying() for p in refl)
    centres = None
    for i, f in enumerate(frames):
        if centres is None or animated:
            cache = UsdGeom.BBoxCache(Usd.TimeCode(float(f)), [UsdGeom.Tokens.default_])
            centres = np.array([cache.ComputeWorldBound(p).ComputeCentroid() for p in refl])
        fwd = targets[i] - eyes[i]
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, up)
        right /= np.linalg.norm(right)
        cam_up = np.cross(right, fwd)
        rel = centres - eyes[i]
        depth = rel @ fwd
        inside = (depth > 0) & (depth < max_distance)
        inside &= np.abs(rel @ right) < tan_x * depth
        inside &= np.abs(rel @ cam_up) < tan_y * depth
        counts[i] = int(inside.sum())
    return counts


def preview_map(
    stage: Usd.Stage,
    png: Path,
    axes: tuple[int, int],
    up: np.ndarray,
    max_distance: float,
    focal_mm: float,
) -> np.ndarray:
    """Top-down map (PNG) of the camera path, view directions and reflector positions.

    Returns the per-frame in-view reflector counts (see :func:`reflectors_in_view`).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames, eyes, targets = camera_path_samples(stage)
    counts = reflectors_in_view(stage, frames, eyes, targets, up, max_distance, focal_mm)
    cache = UsdGeom.BBoxCache(Usd.TimeCode(START_FRAME), [UsdGeom.Tokens.default_])
    a, b = axes
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(16, 8))
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Gprim) and not is_reflector(prim):
            box3 = cache.ComputeWorldBound(prim).ComputeAlignedRange()
            lo, hi = np.array(box3.GetMin()), np.array(box3.GetMax())
            if np.all(np.isfinite(lo)) and (hi - lo)[a] < 100 * (1 if up[1] else 100):
                ax.add_patch(
                    plt.Rectangle(
                        (lo[a], lo[b]), (hi - lo)[a], (hi - lo)[b], fill=False, color="0.6", lw=0.5
                    )
                )
    for prim in reflector_prims(stage):
        c = np.array(cache.ComputeWorldBound(prim).ComputeCentroid())
        ax.plot(c[a], c[b], "o", color="tab:blue")
        ax.annotate(prim.GetName(), (c[a], c[b]), fontsize=6)
    ax.plot(eyes[:, a], eyes[:, b], "-", color="tab:red")
    for i in range(0, len(frames), 24):
        d = targets[i] - eyes[i]
        ax.arrow(
            eyes[i, a],
            eyes[i, b],
            d[a] * 0.4,
            d[b] * 0.4,
            color="tab:green",
            head_width=max_distance * 0.01,
        )
        ax.annotate(str(int(frames[i])), (eyes[i, a], eyes[i, b]), fontsize=6)
    ax.set_aspect("equal")
    ax.invert_yaxis() if up[1] else None
    ax2.plot(frames, counts)
    ax2.set_xlabel("frame")
    ax2.set_ylabel("reflector centres in frustum")
    fig.savefig(png, dpi=80)
    plt.close(fig)
    return counts


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "out", nargs="?", type=Path, default=Path(__file__).resolve().parent.parent / "stages"
    )
    args = parser.parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    for path in build_extreme(out):
        print(f"extreme/{path.name}")
    for build in (build_farm, build_sewer):
        root = build(out)
        stage = Usd.Stage.Open(str(root))
        tris, implicit = count_mesh_triangles(stage)
        n_refl = len(reflector_prims(stage))
        print(
            f"{root.name}: {tris} mesh triangles, {implicit} implicit gprims, {n_refl} reflectors"
        )


if __name__ == "__main__":
    main()
