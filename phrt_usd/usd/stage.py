"""Open a USD stage and read it into the in-memory ``phrt_usd.model.scene.Scene``.

This module holds ``open_stage`` (opens a stage file with the one ``open_usd`` of
``phrt_usd.usd.stage_file``, re-exported here, and reads it), the camera choice, the
traversal, and ``StageScene``, which places the readers' elements in the world and
moves them in ``set_time`` (the camera's values at a time: ``phrt_usd.usd.stage_camera``).
The readers:
``phrt_usd.usd.meshes`` (gprims, primvars, PointInstancers), ``phrt_usd.usd.materials``
(UsdPreviewSurface, textures), ``phrt_usd.usd.lights`` (UsdLux),
``phrt_usd.usd.values`` (attribute values, time), ``phrt_usd.usd.composition``
(missing sublayers, references, payloads).

Pipeline (``read_stage``):

1. **Camera.** Explicit prim path or camera name (``--camera``) > the render settings'
   ``camera`` relationship (``renderSettingsPrimPath`` stage metadata, else the first
   ``UsdRenderSettings``) > the first ``UsdGeomCamera`` > a default camera framing the
   stage's bounds (``phrt_usd.usd.default_camera``, one warning). A ``PhrtCameraPath``
   whose ``phrt:camera`` targets the chosen camera drives it
   (``phrt_usd.usd.camera_path``); otherwise the camera's own (possibly time-sampled)
   world transform does. Apertures, offsets and the settings' conform policy, pixel
   aspect and data window: ``CameraFrame.image_window``.
2. **Traversal.** ``phrt_usd.usd.traversal``: ``Usd.PrimRange`` with instance proxies,
   default predicate; invisible subtrees pruned; a prim is read when its
   ``ComputePurpose`` is one of the render settings' ``includedPurposes`` (fallback
   ``default``, ``render``). Visibility and purpose are evaluated once, at the start of
   the frame range: animated visibility is not supported.
3. **Geometry.** Every gprim the render draws (``meshes.RENDERED_GPRIM_TYPES``) and every
   PointInstancer instance × gprim of its prototype, at any depth of nesting
   (``phrt_usd.usd.instancers``), becomes one element, its triangles
   prepared once in local space (``phrt_usd.usd.meshes``; the meshes all together, in
   one numpy pass, ``phrt_usd.usd.mesh_batch``), then transformed into one
   world-space batch in **metres** (many elements at a time, ``phrt_usd.usd.placement``).
   Elements whose transform or points may vary in time are re-transformed in
   ``StageScene.set_time``, which returns what moved or deformed
   (``model.scene.SceneChange``) and bumps ``Scene.versions``, the counters the
   renderer's caches compare; the others are never touched again.
   Element vertex / triangle ranges stay fixed (topology must not change over time).
   Meshes bound to a UsdSkel skeleton are skinned by USD's own skinning at every time
   (``phrt_usd.usd.skinning``), placed by the skeleton's transform.
4. **Materials.** Read once into one ``MaterialTable`` (``phrt_usd.usd.materials``).
5. **Lights.** Read once at the start of the frame range (``phrt_usd.usd.lights``).

Refusals and warnings: every reason ``read_stage`` refuses a stage is a one-line
``PhrtError`` ``"<where>: <what>"``; the rules that ``phrt validate`` must agree with are
functions returning those messages (here ``stage_problems``, ``choose_camera``,
``camera_problems``, ``reflector_problems``; ``phrt_usd.usd.meshes.mesh_problems`` /
``mesh_problems_in_range``; ``phrt_usd.usd.camera_path.camera_path_problems``), and the
render raises their first message. The camera is checked at the start of the frame range
before any geometry is read, and again at every ``camera(time)``. Sublayers, references
and payloads USD could not open do not stop the render: ``StageScene.warnings`` holds one
line per missing asset (``phrt_usd.usd.composition``).

Decisions where USD leaves room:

- A transform with negative determinant flips the winding (as Hydra does), so the front
  face stays consistent with the transformed normals.
- ``Scene.origin`` is the centre of all geometry bounds at the first time and is kept
  fixed afterwards, so float32 buffers built from it stay valid.

Limits: visibility, purpose, materials and lights are read once (first time code);
topology (point, face and instance counts) must not change over time (``PhrtError`` if
it does). ``doubleSided`` is not represented: front faces are counter-clockwise, culling
is the renderer's choice. Orthographic cameras are rejected.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from pxr import Sdf, Tf, Usd, UsdGeom, UsdRender

from phrt_usd import progress
from phrt_usd.errors import BadOption, PhrtError, UnreadableInput
from phrt_usd.model.scene import CameraFrame, Element, Geometry, Lights, Scene, SceneChange
from phrt_usd.small_pages import small_pages
from phrt_usd.usd import schema
from phrt_usd.usd.camera_path import CameraPath, find_camera_path
from phrt_usd.usd.composition import composition_problems, composition_warnings
from phrt_usd.usd.default_camera import DEFAULT_CAMERA_NAME, default_camera
from phrt_usd.usd.default_lights import DEFAULT_RIG_NAME, default_light_rig
from phrt_usd.usd.instancers import expand_instancer
from phrt_usd.usd.lights import read_light
from phrt_usd.usd.materials import MaterialBank, binding_purposes, bound_material, material_key
from phrt_usd.usd.mesh_batch import MeshBatch, PendingMesh, read_gprim
from phrt_usd.usd.meshes import (
    SHAPE_ATTRS,
    LocalMesh,
    ShapeAt,
    is_subdivided,
    local_shape_fn,
    smooth_corner_normals,
)
from phrt_usd.usd.placement import place_parts
from phrt_usd.usd.render_settings import camera_settings, included_purposes
from phrt_usd.usd.skinning import SkinningReader
from phrt_usd.usd.stage_camera import (  # noqa: F401 (camera_check_times: re-export)
    StageCamera,
    camera_check_times,
    camera_problems,
    same_camera,
)
from phrt_usd.usd.stage_controls import StageControls
from phrt_usd.usd.stage_file import USD_EXTENSIONS, open_usd  # noqa: F401 (re-export)
from phrt_usd.usd.traversal import rendered_gprims, walk_subtree  # noqa: F401 (re-export)
from phrt_usd.usd.values import (
    AnimationProbe,
    TimeContext,
    normal_matrix,
    safe_normalize,
    stage_up_axis,
    varies,
)

# --------------------------------------------------------------------------------------
# Camera
# --------------------------------------------------------------------------------------


def choose_camera(stage: Usd.Stage, camera: str | None = None) -> Usd.Prim | None:
    """The camera the render uses (module doc, step 1); None when the stage has no
    UsdGeomCamera at all (the render then frames the stage with ``default_camera``).

    ``camera`` is a prim path, or the name of a camera prim (unique on the stage,
    instance proxies included). Raises ``BadOption`` when ``camera`` holds no
    UsdGeomCamera or names several (listing the cameras), ``PhrtError`` when the render
    settings' target is not one."""
    if camera:
        return _camera_by_name_or_path(stage, camera)
    settings_prim = schema.find_render_settings(stage)
    if settings_prim is not None:
        settings = UsdRender.Settings(settings_prim)
        targets = settings.GetCameraRel().GetForwardedTargets()
        if targets:
            prim = stage.GetPrimAtPath(targets[0])
            if not prim or not prim.IsA(UsdGeom.Camera):
                raise PhrtError(
                    f"{settings.GetPath()}.camera: target {targets[0]} is not a UsdGeomCamera"
                )
            return prim
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Camera):
            return prim
    return None


def _all_cameras(stage: Usd.Stage) -> list[Usd.Prim]:
    """Every UsdGeomCamera of the stage, instance proxies included, in traversal order."""
    return [
        p
        for p in Usd.PrimRange(stage.GetPseudoRoot(), Usd.TraverseInstanceProxies())
        if p.IsA(UsdGeom.Camera)
    ]


def _camera_by_name_or_path(stage: Usd.Stage, camera: str) -> Usd.Prim:
    """The camera ``--camera`` names: a prim path (starts with ``/``) or a prim name."""
    cameras = _all_cameras(stage)
    have = ", ".join(str(p.GetPath()) for p in cameras) or "none"
    if camera.startswith("/"):
        prim = stage.GetPrimAtPath(camera) if Sdf.Path.IsValidPathString(camera) else None
        if not prim or not prim.IsA(UsdGeom.Camera):
            raise BadOption(f"--camera {camera}: no UsdGeomCamera prim at this path "
                            f"(cameras: {have})")  # fmt: skip
        return prim
    named = [p for p in cameras if p.GetName() == camera]
    if len(named) == 1:
        return named[0]
    if named:
        paths = ", ".join(str(p.GetPath()) for p in named)
        raise BadOption(f"--camera {camera}: {len(named)} cameras have this name ({paths})")
    raise BadOption(f"--camera {camera}: no UsdGeomCamera of this name (cameras: {have})")


def stage_problems(stage: Usd.Stage) -> list[str]:
    """Render refusals of the stage metadata: metersPerUnit must be a finite number > 0
    (``meters_per_unit``)."""
    return meters_per_unit(stage)[1]


def meters_per_unit(stage: Usd.Stage) -> tuple[float, list[str]]:
    """(the stage's ``metersPerUnit`` as a float, [the one-line problem, if any]).

    Read tolerantly: any numeric value a layer holds counts (a float, an int), whatever
    USD's schema type for it (double); a value that is no number, not finite or not
    > 0 is a problem naming the layer that authors it (the session layer, else the root
    layer), and the value is then USD's fallback, 0.01."""
    layer = stage.GetSessionLayer()
    if not (layer and layer.pseudoRoot.HasInfo(_MPU)):
        layer = stage.GetRootLayer()
    try:
        value = UsdGeom.GetStageMetersPerUnit(stage)
    except Tf.ErrorException:  # a value USD cannot convert: read the layer's own
        value = layer.pseudoRoot.GetInfo(_MPU)
    mpu = _number(value)
    if mpu is not None and np.isfinite(mpu) and mpu > 0:
        return mpu, []
    got = value if mpu is None else mpu
    problem = f"{layer.identifier}: layer metadata {_MPU} must be a finite number > 0, got {got!r}"
    return float(UsdGeom.LinearUnits.centimeters), [problem]


_MPU = "metersPerUnit"


def _number(value) -> float | None:
    """``value`` as a float when it is a number (of any numeric type), else None."""
    if value is None or isinstance(value, (str, bytes, bool)):
        return None
    try:
        return float(value)
    except (TypeError, ValueError, OverflowError):
        return None


def frame_range(stage: Usd.Stage, path_driver: CameraPath | None) -> tuple[float, float]:
    """(start, end) time codes rendered by default: the driving camera path's, else the
    stage's start/end time codes."""
    if path_driver is not None:
        return (path_driver.start_frame, path_driver.end_frame)
    return (float(stage.GetStartTimeCode()), float(stage.GetEndTimeCode()))


# --------------------------------------------------------------------------------------
# Elements: reflector flags and how each is placed
# --------------------------------------------------------------------------------------


#: What ``StageScene._place`` found changed in an element: its points or normals
#: (deformed), or only its rigid transform (moved).
DEFORMED = "deformed"
MOVED = "moved"


@dataclass
class _Part:
    """One element's geometry: its local mesh and how to place it at a time."""

    element: int
    path: str
    mesh: LocalMesh  # a PendingMesh of the scene's MeshBatch until it is resolved
    matrix_at: Callable[[TimeContext], np.ndarray]  # (4, 4) row-vector, stage units
    shape_at: ShapeAt | None  # deforming points / normals, or None
    animated: bool
    v0: int = 0
    t0: int = 0
    matrix: np.ndarray | None = None
    flipped: bool = False  # winding flipped for a negative-determinant transform


def reflector_problems(prim: Usd.Prim, path: str | None = None) -> list[str]:
    """Every reason the render refuses a reflector gprim's K and F (``path`` names the
    element, default the prim path): K must be finite and >= 0, F finite (F outside
    [0, 1] is clamped, not refused). ``[]`` for a valid reflector or a non-reflector."""
    if not schema.is_reflector(prim):
        return []
    path = str(prim.GetPath()) if path is None else path
    k = schema.reflector_priority(prim)
    f = schema.reflector_reflectivity(prim)
    problems = []
    if not np.isfinite(k) or k < 0:
        problems.append(f"{path}.{schema.PRIORITY}: must be a finite number >= 0, got {k}")
    if not np.isfinite(f):
        problems.append(f"{path}.{schema.REFLECTIVITY}: must be finite, got {f}")
    return problems


def _element_flags(prim: Usd.Prim, path: str) -> tuple[bool, float, float]:
    """(is_reflector, K, F) of a gprim; K and F are 0 for non-reflectors."""
    if not schema.is_reflector(prim):
        return False, 0.0, 0.0
    for problem in reflector_problems(prim, path):
        raise PhrtError(problem)
    k = schema.reflector_priority(prim)
    f = schema.reflector_reflectivity(prim)
    return True, k, float(np.clip(f, 0.0, 1.0))  # F is a blend weight: clamp to [0, 1]


# --------------------------------------------------------------------------------------
# What the render reads
# --------------------------------------------------------------------------------------


# Traversal, visibility and purposes: ``phrt_usd.usd.traversal`` (``walk_subtree``;
# ``rendered_gprims`` is re-exported here for the validation rules).


# --------------------------------------------------------------------------------------
# The stage scene
# --------------------------------------------------------------------------------------


class StageScene:
    """A USD stage read for rendering.

    stage                 : the opened ``Usd.Stage``
    scene                 : ``phrt_usd.model.scene.Scene``, valid at the last ``set_time``
    camera_path           : prim path of the camera used
    frame_range           : (start, end) time codes — the PhrtCameraPath's if one drives
                            the camera, else the stage's start/end time codes
    time_codes_per_second : from the stage
    warnings              : list[str], one line each: what the render goes on without
                            (missing sublayers, references, payloads; ``composition_warnings``)
    included_purposes     : the purposes drawn (the settings' ``includedPurposes``)
    subdivided_meshes     : prim paths of the drawn meshes that are subdivision surfaces
                            (drawn as their cage; ``meshes.is_subdivided``)

    ``settings`` names the render settings prim (``--settings``), else the stage's.
    """

    def __init__(self, stage: Usd.Stage, camera: str | None = None, settings: str | None = None):
        self.stage = stage
        self.meters_per_unit, problems = meters_per_unit(stage)
        for problem in problems:  # nothing can be measured in it: unusable input
            raise UnreadableInput(problem)
        self.up_axis, up_warning = stage_up_axis(stage)
        self.time_codes_per_second = float(stage.GetTimeCodesPerSecond())
        self.warnings: list[str] = composition_warnings(composition_problems(stage))
        self.warnings += [up_warning] if up_warning else []
        self.included_purposes, purpose_warnings = included_purposes(stage, settings)
        self.warnings += purpose_warnings
        #: UsdRender ``materialBindingPurposes`` (``materials.binding_purposes``).
        self.binding_purposes = binding_purposes(stage, settings)
        cam_prim = choose_camera(stage, camera)
        self.camera_settings = camera_settings(stage, settings)
        self.camera_path = DEFAULT_CAMERA_NAME if cam_prim is None else str(cam_prim.GetPath())
        self.path_driver: CameraPath | None = (
            None if cam_prim is None else find_camera_path(stage, self.camera_path)
        )
        self.frame_range = frame_range(stage, self.path_driver)
        self._time = self.frame_range[0]
        # Refuse a camera that cannot render the first frame before reading any geometry.
        if cam_prim is not None:
            for problem in camera_problems(cam_prim, self._time, self.path_driver is not None):
                raise PhrtError(problem)
        with small_pages():  # the geometry's arrays are written once: phrt_usd.small_pages
            self._build(TimeContext(self._time))
        self.warnings += [
            f"{m}; rendered with the input's fallback"
            if m not in self._dome_problems
            else f"{m}; the dome is rendered untextured, in its colour"
            for m in self.texture_problems
        ]
        self.warnings += self.material_notices
        default: CameraFrame | None = None
        if cam_prim is None:
            where = stage.GetRootLayer().identifier
            default = default_camera(self.scene, self.up_axis, where)
            self.warnings.append(
                f"{where}: stage has no UsdGeomCamera; rendering with a default camera "
                f"framing the stage's bounds from {'-Y' if self.up_axis == 'Z' else '+Z'}"
            )
        self._camera = StageCamera(
            cam_prim, self.path_driver, self.camera_settings, self.meters_per_unit, default
        )
        #: The camera at the last ``set_time`` (None: refused there), for its version.
        self._camera_seen = self._camera.at(self._time)[0]

    # ---- reading ------------------------------------------------------------------

    def _build(self, ctx: TimeContext) -> None:
        bank = MaterialBank(ctx.code, self.binding_purposes)
        probe = AnimationProbe()
        lights = Lights()
        #: What the light readers read with a fallback (also in ``warnings``).
        light_warnings: list[str] = []
        #: Dome textures that could not be read (the dome renders in its colour).
        dome_problems: list[str] = []
        parts: list[_Part] = []
        elements: list[Element] = []
        mesh_cache: dict[tuple, LocalMesh | PendingMesh] = {}
        purposes = self.included_purposes
        skinning = SkinningReader()
        subdivided: dict[str, None] = {}
        # Meshes are triangulated together once the traversal is done (usd/mesh_batch.py).
        batch = MeshBatch(ctx.code, bank)

        def prototype_gprims(root: Usd.Prim):
            return walk_subtree(root, ctx.code, purposes, top=False)

        def read_mesh(kind: str, prim: Usd.Prim) -> LocalMesh | PendingMesh:
            return batch.add(prim) if kind == "Mesh" else read_gprim(kind, prim, ctx.code, bank)

        def local_mesh(prim: Usd.Prim, kind: str) -> LocalMesh | PendingMesh:
            # Instance proxies of one prototype share their triangulation (materials
            # may differ per instance, so the binding is part of the key).
            key = None
            if prim.IsInstanceProxy():
                mat = bound_material(prim, self.binding_purposes)
                proto = prim.GetPrimInPrototype().GetPath()
                key = (str(proto), material_key(mat))
                if key in mesh_cache:
                    return mesh_cache[key]
            mesh = read_mesh(kind, prim)
            if key is not None:
                mesh_cache[key] = mesh
            return mesh

        def add(prim, path, kind, mesh, matrix_at, xform_animated, shape_at=None):
            shape_animated = shape_at is not None or varies(prim, SHAPE_ATTRS[kind])
            refl, k, f = _element_flags(prim, path)
            if kind == "Mesh" and is_subdivided(prim):
                subdivided[str(prim.GetPath())] = None
            if shape_animated and not isinstance(mesh, PendingMesh):
                mesh = dataclasses.replace(mesh)  # deforms on its own, even if shared
            elements.append(Element(path, refl, k, f, np.zeros(3), np.zeros(3)))
            parts.append(
                _Part(
                    element=len(elements) - 1,
                    path=path,
                    mesh=mesh,
                    matrix_at=matrix_at,
                    shape_at=shape_at
                    or (local_shape_fn(kind, prim) if shape_animated else None),
                    animated=xform_animated or shape_animated,
                )
            )
            elements[-1].animated = parts[-1].animated

        for kind, prim in walk_subtree(self.stage.GetPseudoRoot(), ctx.code, purposes):
            progress.step("reading prims", len(parts))
            if kind == "PointInstancer":
                expand_instancer(prim, ctx, probe, read_mesh, prototype_gprims, add)
            elif kind == "Light":
                read_light(
                    prim,
                    ctx,
                    self.meters_per_unit,
                    lights,
                    self.up_axis,
                    light_warnings,
                    dome_problems,
                )
            elif (skin := skinning.skinned(prim, kind)) is not None:
                # Skinned: skeleton-space points placed by the skeleton (usd/skinning.py).
                mesh = read_gprim(kind, prim, ctx.code, bank)
                shape_at = skin.shape_fn(mesh.smooth)
                if skin.animated(probe):
                    add(prim, str(prim.GetPath()), kind, mesh, skin.matrix_at, True, shape_at)
                else:  # a rest pose: skinned once, then static
                    mesh = dataclasses.replace(mesh)
                    mesh.points, normals = shape_at(ctx.code)
                    if normals is not None:
                        mesh.corner_normals = normals
                    elif mesh.smooth:
                        mesh.corner_normals = smooth_corner_normals(mesh.points, mesh.triangles)
                    add(prim, str(prim.GetPath()), kind, mesh, skin.matrix_at, False)
            else:
                mesh = local_mesh(prim, kind)
                add(
                    prim,
                    str(prim.GetPath()),
                    kind,
                    mesh,
                    lambda c, p=prim: c.world(p),
                    probe.xform_varies(prim),
                )

        batch.resolve()
        for p in parts:
            if isinstance(p.mesh, PendingMesh):
                p.mesh = p.mesh.resolved()
                if p.shape_at is not None:  # deforms on its own, even if shared
                    p.mesh = dataclasses.replace(p.mesh)
        self.light_warnings = light_warnings
        self.warnings += light_warnings
        # Only what moves keeps its local mesh: the others are placed once (_assemble).
        self._animated = [p for p in parts if p.animated]
        self.subdivided_meshes: list[str] = list(subdivided)
        #: Textures that could not be read (``materials.MaterialBank.texture_problems``,
        #: then the dome's): warnings of the render, errors with ``--strict`` and in
        #: ``phrt validate``.
        self.texture_problems: list[str] = list(bank.texture_problems) + dome_problems
        self._dome_problems = dome_problems
        #: One line per material rendered approximately (``MaterialBank.notices``:
        #: MaterialX-only materials, base colour only or grey).
        self.material_notices: list[str] = list(bank.notices)
        if not lights.has_direct and lights.dome is None:
            # No light at all: USD viewers' default rig instead of a near-black frame.
            lights = default_light_rig()
            self.warnings.append(
                f"{self.stage.GetRootLayer().identifier}: stage has no UsdLux lights; "
                f"rendering with the {DEFAULT_RIG_NAME} (a dim dome and a headlight "
                "from the camera)"
            )
        self._assemble(parts, elements, bank, lights, ctx)

    def _assemble(self, parts, elements, bank, lights, ctx) -> None:
        """Allocate the world-space batch and fill it at ``ctx`` (``placement.place_parts``
        for the parts that do not deform, ``_place`` for those that do)."""
        v = t = 0
        for p in parts:
            p.v0, p.t0 = v, t
            v += len(p.mesh.points)
            t += len(p.mesh.triangles)
        any_uv = any(p.mesh.corner_uv is not None for p in parts)
        counts = [len(p.mesh.triangles) for p in parts]
        geometry = Geometry(
            vertices=np.zeros((v, 3)),
            triangles=np.zeros((t, 3), np.int64),
            tri_element=np.repeat(np.array([p.element for p in parts], np.int32), counts),
            tri_material=np.concatenate([p.mesh.tri_material for p in parts]).astype(np.int32)
            if parts
            else np.zeros(0, np.int32),
            corner_normals=np.zeros((t, 3, 3), np.float32),
            corner_albedo=np.zeros((t, 3, 3), np.float32),
            corner_uv=np.zeros((t, 3, 2), np.float32) if any_uv else None,
        )
        self.scene = Scene(
            elements=elements,
            geometry=geometry,
            materials=bank.table(),
            lights=lights,
            origin=np.zeros(3),
            meters_per_unit=self.meters_per_unit,
            up_axis=self.up_axis,
        )
        rigid = [p for p in parts if p.shape_at is None]
        place_parts(rigid, ctx, geometry, elements, self.meters_per_unit)
        for p in parts:
            if p.shape_at is not None:
                self._place(p, ctx, force=True)
        if v:
            self.scene.origin = 0.5 * (
                geometry.vertices.min(axis=0) + geometry.vertices.max(axis=0)
            )

    def _place(self, p: _Part, ctx: TimeContext, force: bool = False) -> str | None:
        """Transform part ``p`` to world metres at ``ctx``. Returns what changed:
        ``DEFORMED`` (its points or normals), ``MOVED`` (only its transform) or None."""
        m = p.matrix_at(ctx)
        if not np.all(np.isfinite(m)):
            raise PhrtError(f"{p.path}: non-finite transform at time {ctx.time}")
        mesh = p.mesh
        new_points = new_normals = None
        if p.shape_at is not None:
            new_points, new_normals = p.shape_at(ctx.code)
            if len(new_points) != len(mesh.points) or (
                new_normals is not None and len(new_normals) != len(mesh.triangles)
            ):
                raise PhrtError(f"{p.path}: topology changes at time {ctx.time} (not supported)")
        same_xform = p.matrix is not None and np.array_equal(m, p.matrix)
        same_shape = new_points is None or (
            np.array_equal(new_points, mesh.points)
            and (new_normals is None or np.array_equal(new_normals, mesh.corner_normals))
        )
        if not force and same_xform and same_shape:
            return None
        if new_points is not None:
            mesh.points = new_points
            if new_normals is not None:
                mesh.corner_normals = new_normals
            elif mesh.smooth:
                mesh.corner_normals = smooth_corner_normals(new_points, mesh.triangles)
        p.matrix = m
        g = self.scene.geometry
        nv, nt = len(mesh.points), len(mesh.triangles)
        vs, ts = slice(p.v0, p.v0 + nv), slice(p.t0, p.t0 + nt)
        world = (mesh.points @ m[:3, :3] + m[3, :3]) * self.meters_per_unit
        g.vertices[vs] = world
        n = mesh.corner_normals.reshape(-1, 3) @ normal_matrix(m[:3, :3])
        corner_n = safe_normalize(n).reshape(-1, 3, 3)
        flipped = float(np.linalg.det(m[:3, :3])) < 0
        if flipped:
            corner_n = corner_n[:, [0, 2, 1]]
        if force or flipped != p.flipped:
            order = [0, 2, 1] if flipped else [0, 1, 2]
            g.triangles[ts] = mesh.triangles[:, order] + p.v0
            start = p.t0
            g.corner_albedo[ts] = mesh.corner_albedo[:, order]
            if g.corner_uv is not None and mesh.corner_uv is not None:
                g.corner_uv[start : start + nt] = mesh.corner_uv[:, order]
            p.flipped = flipped
        g.corner_normals[ts] = corner_n
        e = self.scene.elements[p.element]
        if nv:
            e.bounds_min = world.min(axis=0)
            e.bounds_max = world.max(axis=0)
        else:
            e.bounds_min = e.bounds_max = m[3, :3] * self.meters_per_unit
        return MOVED if same_shape else DEFORMED

    # ---- public API ---------------------------------------------------------------

    def set_time(self, time: float) -> SceneChange:
        """Re-evaluate animated elements and the camera at ``time``; returns what changed
        (``SceneChange``: the elements moved and deformed, the versions after it), which
        ``scene.versions`` counts too (the geometry version stamps the changed
        elements, ``Scene.geometry_changed``; the camera version is bumped when the
        camera differs from the one at the previous time).

        Static elements are never recomputed; with no animated element the geometry
        costs O(1). The camera is read once per time code (``stage_camera.StageCamera``
        keeps the last CAMERA_CACHE_SIZE); a camera the render refuses at ``time`` is not raised
        here but by ``camera``, and counts as changed.
        """
        time = float(time)
        if not np.isfinite(time):
            raise PhrtError(f"set_time: time code {time} is not finite")
        moved: list[int] = []
        deformed: list[int] = []
        if self._animated:
            ctx = TimeContext(time)
            for p in self._animated:
                kind = self._place(p, ctx)
                if kind == MOVED:
                    moved.append(p.element)
                elif kind == DEFORMED:
                    deformed.append(p.element)
        self._time = time
        versions = self.scene.versions
        self.scene.geometry_changed(moved + deformed)
        camera = self._camera.at(time)[0]
        seen = self._camera_seen
        if camera is None or seen is None or not same_camera(camera, seen):
            versions.camera += 1
        self._camera_seen = camera
        return SceneChange(
            moved=np.array(sorted(moved), dtype=np.int64),
            deformed=np.array(sorted(deformed), dtype=np.int64),
            geometry_version=versions.geometry,
            lights_version=versions.lights,
            camera_version=versions.camera,
        )

    @property
    def time(self) -> float:
        """Time code of the last ``set_time`` (the start of the frame range at first)."""
        return self._time

    def camera(self, time: float) -> CameraFrame:
        """The camera at ``time``: world metres, orthonormal rotation, the settings'
        conform policy, pixel aspect and data window (``camera_settings``). The default
        camera (``default_camera``) when the stage has no camera. Raises ``PhrtError``
        (``camera_problems``' first) for a camera the render refuses at ``time``."""
        camera, problems = self._camera.at(time)
        for problem in problems:
            raise PhrtError(problem)
        return camera


# --------------------------------------------------------------------------------------
# Opening and reading a stage file
# --------------------------------------------------------------------------------------


def read_stage(
    stage: Usd.Stage, camera: str | None = None, settings: str | None = None
) -> StageScene:
    """Read an open stage for rendering (see the module doc). Raises ``PhrtError``."""
    return StageScene(stage, camera, settings)


def open_stage(
    path: str | os.PathLike,
    camera: str | None = None,
    controls: StageControls | None = None,
    settings: str | None = None,
) -> StageScene:
    """Open a stage file (``open_usd``) and read it (``read_stage``; ``settings``: the
    render settings prim, else the stage's). Raises ``PhrtError`` (one line) for an
    unusable file, a stage without camera, or invalid data."""
    return read_stage(open_usd(path, controls), camera, settings)
