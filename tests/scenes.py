"""Scene builders for tests: every stage and in-memory scene a test renders, reads or
selects on, each documented with the geometry it makes so that a test's analytic
expectation can be read from its builder.

USD stages (files, or in memory): the common camera/light set-up, a mirror floor, a
mirror gallery on a camera path, a validating quad mirror, a lone cube, a stage with
composition arcs, a camera-only stage and a camera-path stage.

In-memory ``Scene``s (no USD): triangle soups from trimesh parts (``parts_scene`` with
``box``, ``box_between``, ``sphere``, ``quad``) and ``CameraFrame``s (``look_at``); the
analytic sphere's rays (``ray_sphere_hit``). World space is
metres, +Y up, unless a builder says otherwise.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender, Vt

import phrt_usd  # noqa: F401  (registers the schema before any stage opens)
from phrt_usd.model.scene import CameraFrame, Element, Geometry, Lights, MaterialTable, Scene
from phrt_usd.usd import schema

# ---------------------------------------------------------------- USD stages

#: mirror_floor_stage's red ball (world metres) and its fixed camera's eye and target.
SPHERE_CENTER = np.array([0.0, 1.0, 0.0])
SPHERE_RADIUS = 0.5
EYE = np.array([0.0, 2.0, 5.0])
TARGET = np.array([0.0, 0.2, 0.0])


def _look_at_matrix(eye: np.ndarray, target: np.ndarray) -> Gf.Matrix4d:
    """World-from-camera for a USD camera (looks down -Z, +Y up) at eye, facing target."""
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 1.0, 0.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3], m[3, :3] = r, u, -f, eye  # USD: row vectors
    return Gf.Matrix4d(m.tolist())


def _quad(stage: Usd.Stage, path: str, half: float, color) -> UsdGeom.Mesh:
    """A square mesh of side 2 ``half`` in its local y = 0 plane, centred on the origin,
    facing +Y (one quad face, 2 triangles), with one display colour."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([(-half, 0, -half), (-half, 0, half), (half, 0, half), (half, 0, -half)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateDisplayColorAttr([color])
    return mesh


def _common(stage: Usd.Stage, width: int, height: int) -> UsdGeom.Camera:
    """The common set-up: Y-up, 1 m per unit, default prim /World; a sun /World/Sun
    (DistantLight, intensity 2, rotateXYZ (-60, 30, 0)) and a sky /World/Sky (DomeLight,
    colour (0.3, 0.5, 0.9), intensity 0.5); the camera /World/Camera (focal 24 mm,
    horizontal aperture 36 mm, so a 73.7° horizontal field of view; clipping 0.01 to
    100 m; no transform yet) named by /Render/Settings (width x height, 1000 ms budget),
    the stage's render settings. Returns the camera."""
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    sun.CreateIntensityAttr(2.0)
    UsdGeom.Xformable(sun).AddRotateXYZOp().Set(Gf.Vec3f(-60, 30, 0))
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateColorAttr(Gf.Vec3f(0.3, 0.5, 0.9))
    dome.CreateIntensityAttr(0.5)
    cam = UsdGeom.Camera.Define(stage, "/World/Camera")
    cam.CreateFocalLengthAttr(24.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(36.0 * height / width)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.01, 100.0))
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateResolutionAttr(Gf.Vec2i(width, height))
    settings.CreateCameraRel().SetTargets([cam.GetPath()])
    schema.apply_render_settings(settings.GetPrim(), budget_ms=1000.0)
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    return cam


def render_var(stage: Usd.Stage, name: str, source: str, data_type: str,
               aov: str | None = None) -> Sdf.Path:  # fmt: skip
    """A RenderVar /Render/Vars/``name`` reading ``source`` as ``data_type``, renamed
    ``aov`` (``driver:parameters:aov:name``) when given; its path."""
    var = UsdRender.Var.Define(stage, f"/Render/Vars/{name}")
    var.CreateSourceNameAttr(source)
    var.CreateDataTypeAttr(data_type)
    if aov:
        var.GetPrim().CreateAttribute(
            "driver:parameters:aov:name", Sdf.ValueTypeNames.String
        ).Set(aov)
    return var.GetPath()


def mirror_floor_stage(path: Path, width: int = 160, height: int = 120) -> Path:
    """A 10 m mirror floor at y = 0 (F = 1), a red sphere above it, a fixed camera."""
    stage = Usd.Stage.CreateNew(str(path))
    cam = _common(stage, width, height)
    UsdGeom.Xformable(cam).AddTransformOp().Set(_look_at_matrix(EYE, TARGET))
    floor = _quad(stage, "/World/Floor", 5.0, (0.2, 0.2, 0.2))
    schema.apply_reflector(floor.GetPrim(), priority=1.0, reflectivity=1.0)
    sphere = UsdGeom.Sphere.Define(stage, "/World/Ball")
    sphere.CreateRadiusAttr(SPHERE_RADIUS)
    sphere.CreateDisplayColorAttr([(0.9, 0.05, 0.05)])
    UsdGeom.Xformable(sphere).AddTranslateOp().Set(Gf.Vec3d(*SPHERE_CENTER))
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(1)
    stage.GetRootLayer().Save()
    return path


def mirror_gallery_stage(path: Path, frames: int = 40, width: int = 64, height: int = 48) -> Path:
    """Five mirror panels of different priorities around a floor, and a camera path that
    sweeps past them over ``frames`` frames (for render-job and heuristic tests)."""
    stage = Usd.Stage.CreateNew(str(path))
    cam = _common(stage, width, height)
    _quad(stage, "/World/Ground", 20.0, (0.4, 0.6, 0.3))
    for i in range(5):
        x = -8.0 + 4.0 * i
        panel = _quad(stage, f"/World/Mirror{i}", 1.0, (0.5, 0.5, 0.5))
        xf = UsdGeom.Xformable(panel)
        xf.AddTranslateOp().Set(Gf.Vec3d(x, 1.0, -3.0 + (i % 2)))
        xf.AddRotateXOp().Set(80.0)
        schema.apply_reflector(panel.GetPrim(), priority=1.0 + i, reflectivity=0.8)
        ball = UsdGeom.Sphere.Define(stage, f"/World/Ball{i}")
        ball.CreateRadiusAttr(0.4)
        ball.CreateDisplayColorAttr([(0.2 * i, 0.3, 1.0 - 0.2 * i)])
        UsdGeom.Xformable(ball).AddTranslateOp().Set(Gf.Vec3d(x + 1.0, 0.4, 0.0))
    keys = np.array([1.0, 1.0 + 0.5 * (frames - 1), frames])
    positions = [(-10.0, 1.6, 6.0), (0.0, 1.8, 5.0), (10.0, 1.6, 6.0)]
    targets = [(-6.0, 1.0, -3.0), (0.0, 1.0, -3.0), (6.0, 1.0, -3.0)]
    schema.define_camera_path(
        stage, "/World/CameraPath", cam.GetPath(), positions, targets, keys, 1.0, float(frames)
    )
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(frames)
    stage.GetRootLayer().Save()
    return path


def mirrored_sphere_pixels(camera, width: int, height: int) -> np.ndarray:
    """(H, W) bool: pixels whose ray, mirrored in the plane y = 0, hits the sphere.

    A ray reflected by the floor hits the sphere exactly where the straight ray from the
    eye hits the sphere mirrored through the floor (centre (x, -y, z)), provided the ray
    reaches the floor first, which holds for every hit of the mirrored sphere (it lies
    below the plane)."""
    origins, dirs = camera.pixel_rays(width, height)
    c = SPHERE_CENTER * np.array([1.0, -1.0, 1.0])
    oc = origins - c
    b = np.sum(oc * dirs, axis=1)
    disc = b * b - (np.sum(oc * oc, axis=1) - SPHERE_RADIUS**2)
    return ((disc > 0) & (-b - np.sqrt(np.maximum(disc, 0)) > 0)).reshape(height, width)


def clean_stage(path: Path) -> Usd.Stage:
    """A stage that validates clean, created at ``path`` but not saved (callers edit or
    save it). Y-up, 1 m per unit, default prim /World. /World/Mirror: the unit quad
    (0, 0, 0)-(1, 1, 0) in the z = 0 plane facing +Z (2 triangles), a reflector with
    priority K = 2 and reflectivity F = 0.5. /World/Cam, without a transform of its own,
    driven by the camera path /World/Path: from (0, 1, 5) at frame 1 to (1, 1, 5) at frame
    24, looking at the origin. /World/Render: 320 x 240, heuristic heu1, 10 ms budget."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, "Y")
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    mesh = UsdGeom.Mesh.Define(stage, "/World/Mirror")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    schema.apply_reflector(mesh.GetPrim(), priority=2.0, reflectivity=0.5)
    UsdGeom.Camera.Define(stage, "/World/Cam")
    schema.define_camera_path(
        stage, "/World/Path", "/World/Cam", [(0, 1, 5), (1, 1, 5)], [(0, 0, 0), (0, 0, 0)], [1, 24]
    )
    settings = UsdRender.Settings.Define(stage, "/World/Render")
    settings.CreateResolutionAttr(Gf.Vec2i(320, 240))
    schema.apply_render_settings(settings.GetPrim(), heuristic="heu1", budget_ms=10.0)
    return stage


def cube_stage(path: Path, fmt: str | None = None) -> Path:
    """A saved stage with one cube and nothing else (no camera, light or reflector):
    /World (Xform) and /World/Box (Cube, USD's default size 2, centred on the origin).
    ``fmt`` ('usda' or 'usdc') chooses the encoding of a ``.usd`` path."""
    layer = Sdf.Layer.CreateAnonymous(".usda")
    stage = Usd.Stage.Open(layer)
    UsdGeom.Xform.Define(stage, "/World")
    UsdGeom.Cube.Define(stage, "/World/Box")
    assert layer.Export(str(path), args={"format": fmt} if fmt else {})
    return path


def composed_stage(directory: Path) -> Path:
    """``directory``/scene.usda with every kind of composition arc, each layer holding one
    cube at /<Name> (its default prim): scene.usda sublayers sub.usda (which sublayers
    deep.usda), references ref.usda at /World/Ref, payloads pay.usda at /World/Pay and,
    only in the unselected variant 'fancy' of /World/Var's variant set 'look',
    references var.usda (which sublayers vardeep.usda). Its own prim: the cube
    /World/Box."""
    for name in ("deep", "sub", "ref", "pay", "var", "vardeep"):
        layer = Sdf.Layer.CreateNew(str(directory / f"{name}.usda"))
        stage = Usd.Stage.Open(layer)
        UsdGeom.Cube.Define(stage, f"/{name.capitalize()}")
        layer.defaultPrim = name.capitalize()
        if name in ("sub", "var"):
            layer.subLayerPaths.append("deep.usda" if name == "sub" else "vardeep.usda")
        layer.Save()
    path = directory / "scene.usda"
    stage = Usd.Stage.CreateNew(str(path))
    stage.GetRootLayer().subLayerPaths.append("sub.usda")
    UsdGeom.Cube.Define(stage, "/World/Box")
    stage.DefinePrim("/World/Ref").GetReferences().AddReference("ref.usda")
    stage.DefinePrim("/World/Pay").GetPayloads().AddPayload("pay.usda")
    holder = stage.DefinePrim("/World/Var")
    variants = holder.GetVariantSets().AddVariantSet("look")
    variants.AddVariant("plain")
    variants.AddVariant("fancy")
    variants.SetVariantSelection("fancy")
    with variants.GetVariantEditContext():
        holder.GetReferences().AddReference("var.usda")
    variants.SetVariantSelection("plain")
    stage.GetRootLayer().Save()
    return path


def _units_stage(up: str, mpu: float) -> Usd.Stage:
    """An empty in-memory stage with up axis ``up`` ('Y' or 'Z') and ``mpu`` metres per
    stage unit."""
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up == "Y" else UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    return stage


def camera_stage(up: str = "Y", mpu: float = 1.0) -> Usd.Stage:
    """An in-memory stage holding only the camera /Cam (USD defaults: focal 50 mm,
    aperture 20.955 mm) translated to (0, 0, 10) stage units, looking down -Z at the
    origin; up axis ``up`` ('Y' or 'Z'), ``mpu`` metres per unit. Tests add prims."""
    stage = _units_stage(up, mpu)
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.AddTranslateOp().Set(Gf.Vec3d(0, 0, 10))
    return stage


def camera_path_stage(positions, targets, keys, interp="linear", up="Y", mpu=1.0, **extra):
    """An in-memory stage: the camera /Cam (focal 35 mm, no transform) and the
    PhrtCameraPath /CameraPath driving it, authored attribute by attribute (no
    validation): phrt:positions and phrt:targets ((n, 3) stage units), phrt:keyTimes
    ``keys`` (left unauthored when None), phrt:interpolation ``interp``, and each
    ``extra`` name=value as a double attribute phrt:<name>. Up axis ``up``, ``mpu``
    metres per unit."""
    stage = _units_stage(up, mpu)
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.CreateFocalLengthAttr(35.0)
    p = stage.DefinePrim("/CameraPath", "PhrtCameraPath")
    p.CreateRelationship("phrt:camera").SetTargets([cam.GetPath()])
    p.CreateAttribute("phrt:positions", Sdf.ValueTypeNames.Point3dArray).Set(
        Vt.Vec3dArray([Gf.Vec3d(*x) for x in positions])
    )
    p.CreateAttribute("phrt:targets", Sdf.ValueTypeNames.Point3dArray).Set(
        Vt.Vec3dArray([Gf.Vec3d(*x) for x in targets])
    )
    if keys is not None:
        p.CreateAttribute("phrt:keyTimes", Sdf.ValueTypeNames.DoubleArray).Set(keys)
    p.CreateAttribute("phrt:interpolation", Sdf.ValueTypeNames.Token).Set(interp)
    for name, value in extra.items():
        p.CreateAttribute(f"phrt:{name}", Sdf.ValueTypeNames.Double).Set(value)
    return stage


# ---------------------------------------------------------------- in-memory scenes


def box(extents, center) -> trimesh.Trimesh:
    """Closed axis-aligned box (12 triangles, outward normals) of size ``extents`` (3,)
    centred on ``center`` (3,)."""
    return trimesh.creation.box(
        extents=extents, transform=trimesh.transformations.translation_matrix(center)
    )


def box_between(lo, hi) -> trimesh.Trimesh:
    """``box`` spanning the corners ``lo`` (3,) to ``hi`` (3,)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    return box(hi - lo, 0.5 * (lo + hi))


def sphere(radius, center, subdivisions: int = 4) -> trimesh.Trimesh:
    """Icosphere of ``radius`` centred on ``center`` (3,): 20 * 4**subdivisions triangles
    with outward normals, its vertices on the exact sphere."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    m.apply_translation(center)
    return m


def quad(size: float, center=(0.0, 0.0, 0.0), axis: str = "y") -> trimesh.Trimesh:
    """Square of side ``size`` facing +axis (y: floor facing up, z: wall facing +z)."""
    h = 0.5 * size
    if axis == "y":
        v = np.array([[-h, 0, -h], [h, 0, -h], [h, 0, h], [-h, 0, h]], dtype=np.float64)
        f = np.array([[0, 2, 1], [0, 3, 2]])
    else:
        v = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]], dtype=np.float64)
        f = np.array([[0, 1, 2], [0, 2, 3]])
    return trimesh.Trimesh(v + np.asarray(center), f, process=False)


def ray_sphere_hit(origin, dirs, center, radius) -> np.ndarray:
    """(n,) bool: rays from ``origin`` along unit ``dirs`` hit the analytic sphere."""
    oc = np.asarray(origin) - np.asarray(center)
    b = dirs @ oc
    c = oc @ oc - radius**2
    disc = b * b - c
    return (disc >= 0) & (-b + np.sqrt(np.maximum(disc, 0)) > 0)


def parts_scene(parts: list[dict], lights: Lights | None = None, offset=None) -> Scene:
    """A Scene with one element and one material per part, in the order given.

    Part keys: "mesh" (trimesh.Trimesh, world metres), "albedo" ((3,) linear RGB, default
    0.5 grey; also the material's diffuse), "F" (reflectivity; None or absent: not a
    reflector; a reflector gets priority K = 1), "smooth" (corner normals from the
    mesh's vertex normals; default: face normals), "path" (default /World/part<i>),
    "emissive" ((3,), default black), "opacity" (default 1), "ior" (default 1.5).
    Materials are rough (roughness 1) dielectrics (metallic 0) without textures.
    ``offset`` (3,) metres, if given, translates every part. ``lights`` default to none;
    Scene.origin is the centre of the vertices' bounding box."""
    verts, tris, tri_elem, corner_n, corner_a, elements = [], [], [], [], [], []
    n_mat = len(parts)
    diffuse = np.zeros((n_mat, 3), np.float32)
    emissive = np.zeros((n_mat, 3), np.float32)
    opacity = np.ones(n_mat, np.float32)
    ior = np.full(n_mat, 1.5, np.float32)
    base = 0
    for i, part in enumerate(parts):
        mesh = part["mesh"]
        v = np.asarray(mesh.vertices, dtype=np.float64)
        if offset is not None:
            v = v + np.asarray(offset, dtype=np.float64)
        f = np.asarray(mesh.faces, dtype=np.int64)
        verts.append(v)
        tris.append(f + base)
        base += len(v)
        tri_elem.append(np.full(len(f), i, np.int32))
        if part.get("smooth"):
            corner_n.append(np.asarray(mesh.vertex_normals, np.float32)[f])
        else:
            fn = np.asarray(mesh.face_normals, np.float32)
            corner_n.append(np.repeat(fn[:, None], 3, axis=1))
        albedo = np.asarray(part.get("albedo", (0.5, 0.5, 0.5)), np.float32)
        corner_a.append(np.broadcast_to(albedo, (len(f), 3, 3)).copy())
        diffuse[i] = albedo
        emissive[i] = part.get("emissive", (0.0, 0.0, 0.0))
        opacity[i] = part.get("opacity", 1.0)
        ior[i] = part.get("ior", 1.5)
        refl = part.get("F")
        elements.append(
            Element(
                path=part.get("path", f"/World/part{i}"),
                is_reflector=refl is not None,
                priority=1.0 if refl is not None else 0.0,
                reflectivity=float(refl or 0.0),
                bounds_min=v.min(axis=0),
                bounds_max=v.max(axis=0),
            )
        )
    all_v = np.concatenate(verts)
    tri_elem_all = np.concatenate(tri_elem)
    geometry = Geometry(
        vertices=all_v,
        triangles=np.concatenate(tris),
        tri_element=tri_elem_all,
        tri_material=tri_elem_all.copy(),
        corner_normals=np.concatenate(corner_n),
        corner_albedo=np.concatenate(corner_a),
    )
    materials = MaterialTable(
        diffuse=diffuse,
        metallic=np.zeros(n_mat, np.float32),
        roughness=np.ones(n_mat, np.float32),
        opacity=opacity,
        ior=ior,
        emissive=emissive,
        textures=[None] * n_mat,
    )
    origin = 0.5 * (all_v.min(axis=0) + all_v.max(axis=0))
    return Scene(elements, geometry, materials, lights or Lights(), origin)


def look_at(
    eye, target, up=(0.0, 1.0, 0.0), focal=35.0, aperture=36.0, near=0.01, far=1000.0
) -> CameraFrame:
    """CameraFrame at ``eye`` (3,) looking at ``target`` (3,), ``up`` (3,) up (world
    metres; camera space looks down -Z, +Y up): ``focal`` mm over a horizontal
    ``aperture`` mm (35 over 36: a 54.4° horizontal field of view), clipping ``near``
    to ``far`` metres."""
    eye = np.asarray(eye, dtype=np.float64)
    f = np.asarray(target, dtype=np.float64) - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, u, -f, eye
    return CameraFrame(m, focal, aperture, near=near, far=far)


def shaded_both_ways(pos, nrm, albedo, view, lights: Lights, vis, terms):
    """``shading.shade_local`` of points (n, 3 each) from a visibility matrix ``vis``
    (n, L) and from the shadow maps' light ``terms`` (``Rasterizer.light_terms``): the
    two (n, 3) radiances, which must agree."""
    from phrt_usd.engine import shading

    expected = shading.shade_local(pos, nrm, albedo, view, np.zeros(3), lights, vis)
    got = shading.shade_local(
        pos, nrm, albedo, view, np.zeros(3), lights, terms.distant_visibility,
        local_pairs=terms.local_pairs, lit_sums=terms.lit_sums,
    )  # fmt: skip
    return expected, got


def grey_square_stage(albedo: float, half: float = 2.0, eye=(0.0, 0.0, 2.0),
                      meters_per_unit: float = 1.0) -> Usd.Stage:  # fmt: skip
    """An in-memory stage (y up) of a grey square of ``albedo`` (displayColor), ``half``
    m from its centre to each side in the plane z = 0, and the camera /World/Cam at
    ``eye`` looking down -z (20 mm lens, 20 x 15 mm aperture, clipping 0.1-100 m).
    Authored in units of ``meters_per_unit`` (every length in metres / it)."""
    s = 1.0 / meters_per_unit
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    h = half * s
    quad = UsdGeom.Mesh.Define(stage, "/World/Square")
    quad.CreatePointsAttr([(-h, -h, 0), (h, -h, 0), (h, h, 0), (-h, h, 0)])
    quad.CreateFaceVertexCountsAttr([4])
    quad.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    quad.CreateDisplayColorAttr([(albedo, albedo, albedo)])
    cam = UsdGeom.Camera.Define(stage, "/World/Cam")
    cam.CreateFocalLengthAttr(20.0)
    cam.CreateHorizontalApertureAttr(20.0)
    cam.CreateVerticalApertureAttr(15.0)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1 * s, 100.0 * s))
    cam.AddTranslateOp().Set(Gf.Vec3d(*(np.asarray(eye, float) * s)))
    return stage


def preview_shade(albedo, point, eye, normal=(0.0, 0.0, 1.0), sources=(), ambient=0.0):
    """(3,) float64 linear colour of a point (3,) of UsdPreviewSurface's fallback material
    of ``albedo`` (scalar or (3,); roughness 0.5, ior 1.5) with unit ``normal``, seen
    from ``eye`` (3,): per source (unit direction to the light (3,), E (scalar or (3,)))
    E x the BRDF's π f n·l, plus ``ambient`` (scalar or (3,)) times its directional
    albedo (the numpy model of ``tests/shading_reference.py``)."""
    from shading_reference import ambient_weight, brdf_cos

    from phrt_usd.model.preview_surface import fallback_surface

    surface = fallback_surface(np.broadcast_to(np.asarray(albedo, np.float64), (1, 3)))
    n = np.asarray(normal, np.float64).reshape(1, 3)
    to_eye = np.asarray(eye, np.float64) - np.asarray(point, np.float64)
    to_eye = (to_eye / np.linalg.norm(to_eye)).reshape(1, 3)
    out = ambient_weight(surface, n, to_eye)[0] * np.asarray(ambient, np.float64)
    for direction, e in sources:
        d = np.asarray(direction, np.float64).reshape(1, 3)
        brdf = brdf_cos(surface, n, to_eye, d / np.linalg.norm(d))[0]
        out = out + np.asarray(e, np.float64) * brdf
    return out


def sky_view_stage(path: Path, sky, eye, target) -> Usd.Stage:
    """A new stage at ``path`` (y up, metres, default prim /World) lit by a DomeLight
    /World/Sky of colour ``sky`` (intensity 1), its camera /World/Camera (24 mm lens,
    36 x 27 mm aperture, clipping 0.01-100 m) at ``eye`` looking at ``target``; no
    geometry."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    UsdLux.DomeLight.Define(stage, "/World/Sky").CreateColorAttr(Gf.Vec3f(*sky))
    cam = UsdGeom.Camera.Define(stage, "/World/Camera")
    cam.CreateFocalLengthAttr(24.0)
    cam.CreateHorizontalApertureAttr(36.0)
    cam.CreateVerticalApertureAttr(27.0)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.01, 100.0))
    UsdGeom.Xformable(cam).AddTransformOp().Set(
        _look_at_matrix(np.asarray(eye, np.float64), np.asarray(target, np.float64))
    )
    return stage


def front_view_stage(path: Path) -> Usd.Stage:
    """A new stage at ``path`` (y up, metres) with the camera /Cam at (0, 0, 5) looking
    down -z (50 mm lens, 20 x 20 mm aperture: the 2 x 2 ``st_quad`` at the origin just
    fills the image; clipping 0.1-100 m) and a white DomeLight /Sky of intensity 1; no
    geometry."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.CreateFocalLengthAttr(50.0)
    cam.CreateHorizontalApertureAttr(20.0)
    cam.CreateVerticalApertureAttr(20.0)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.1, 100.0))
    cam.AddTranslateOp().Set(Gf.Vec3d(0, 0, 5))
    dome = UsdLux.DomeLight.Define(stage, "/Sky")
    dome.CreateIntensityAttr(1.0)
    dome.CreateColorAttr(Gf.Vec3f(1, 1, 1))
    return stage


def st_quad(stage: Usd.Stage, path: str = "/Quad") -> UsdGeom.Mesh:
    """A 2 x 2 quad at z = 0 facing +z at ``path``, with face-varying ``st`` from (0, 0)
    at its lower left to (1, 1) at its upper right."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying
    ).Set([(0, 0), (1, 0), (1, 1), (0, 1)])
    return mesh


def first_frame(stage: Usd.Stage, mode: str, width: int, height: int | None = None):
    """``stage``'s first frame (a ``FrameOutput``) rendered in ``mode`` at ``width`` x
    ``height`` (square when None) pixels, every reflector traced, no budget."""
    from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
    from phrt_usd.usd.stage import read_stage

    scene = read_stage(stage)
    options = RenderOptions(mode=mode, heuristic="all", width=width,
                            height=height or width, budget_ms=None)  # fmt: skip
    renderer = FrameRenderer(scene, options)
    try:
        return renderer.render(scene.frame_range[0])
    finally:
        renderer.close()


def centre_pixel(stage: Usd.Stage, mode: str, size: int = 16) -> np.ndarray:
    """(3,) float64 linear colour of the centre pixel of ``stage``'s first frame rendered
    in ``mode`` at ``size`` x ``size`` pixels (``first_frame``); fails when the centre
    pixel shows no geometry (the test's expectation would be of the sky)."""
    out = first_frame(stage, mode, size)
    assert out.gbuffer.element_id[size // 2, size // 2] >= 0, "the centre pixel misses"
    return np.asarray(out.beauty[size // 2, size // 2], np.float64)
