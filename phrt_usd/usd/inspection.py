"""What a stage holds for phrt: reflectors, camera paths, render settings, lights,
stage metadata, the camera a render uses, and which render passes a render of it needs.

Reflectors are listed with instance proxies (``rules.stage_reflectors``): a reflector
inside an instanced reference once per instance, at its per-instance path (the render's
element path), with its instance root and prototype prim.

Everything is read at the default time code (bounds too) and returned as plain
JSON-ready dicts/lists; ``phrt inspect`` prints them as tables or one JSON object.

Passes: ``gbuffer`` always; ``shadows`` iff a DistantLight/SphereLight/RectLight exists;
``reflections`` iff any reflector; ``refraction`` iff some UsdPreviewSurface has an
authored opacity < 1; ``environment`` iff a DomeLight exists.
"""

from __future__ import annotations

from dataclasses import asdict

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdLux, UsdShade

from phrt_usd.errors import PhrtError, UnreadableInput
from phrt_usd.usd import schema
from phrt_usd.usd.authoring import instance_root
from phrt_usd.usd.camera_path import find_camera_path_prim
from phrt_usd.usd.default_camera import DEFAULT_CAMERA_NAME
from phrt_usd.usd.lights import READ_LIGHT_TYPE_NAMES
from phrt_usd.usd.render_settings import read_render_settings
from phrt_usd.usd.rules import stage_reflectors
from phrt_usd.usd.stage import choose_camera, meters_per_unit
from phrt_usd.usd.support_report import support_report

SHADOW_LIGHT_TYPES = ("DistantLight", "SphereLight", "RectLight")
ENVIRONMENT_LIGHT_TYPES = ("DomeLight", "DomeLight_1")


def _triangle_count(prim: Usd.Prim) -> int | None:
    """Triangles of a Mesh after fan triangulation, sum(count - 2) over faces with >= 3
    vertices; None for implicit gprims (Sphere, Cube, ...) whose tessellation is the
    renderer's choice."""
    if not prim.IsA(UsdGeom.Mesh):
        return None
    counts = UsdGeom.Mesh(prim).GetFaceVertexCountsAttr().Get()
    c = np.asarray(counts if counts is not None else [], dtype=np.int64)
    return int(np.clip(c - 2, 0, None).sum())


def _bounds(cache: UsdGeom.BBoxCache, prim: Usd.Prim, meters_per_unit: float) -> dict:
    """World-space axis-aligned bounds, stage units and metres; None for empty bounds
    and for a corner beyond float64's range (JSON holds finite numbers only)."""
    box = cache.ComputeWorldBound(prim).ComputeAlignedRange()
    if box.IsEmpty():
        return {"min": None, "max": None, "min_m": None, "max_m": None}
    lo = np.array(box.GetMin(), dtype=np.float64)
    hi = np.array(box.GetMax(), dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        corners = {"min": lo, "max": hi, "min_m": lo * meters_per_unit,
                   "max_m": hi * meters_per_unit}  # fmt: skip
    return {k: v.tolist() if np.all(np.isfinite(v)) else None for k, v in corners.items()}


def _traverse(stage: Usd.Stage) -> Usd.PrimRange:
    """The composed stage as the render walks it: instance proxies included."""
    return Usd.PrimRange(stage.GetPseudoRoot(), Usd.TraverseInstanceProxies())


def _prototype_uses(stage: Usd.Stage) -> dict[Sdf.Path, tuple[str, int]]:
    """Prototype root path → (PointInstancer path, instances drawn) for every
    PointInstancer prototype: the instances of that prototype the mask leaves
    (``ComputeMaskAtTime`` at the first time code, as the render reads it), times the
    instances of the instancer itself when it lies in an outer prototype (nesting)."""
    uses: dict[Sdf.Path, tuple[str, list[int]]] = {}
    code = Usd.TimeCode(stage.GetStartTimeCode())
    for prim in _traverse(stage):
        if not prim.IsA(UsdGeom.PointInstancer):
            continue
        pi = UsdGeom.PointInstancer(prim)
        protos = pi.GetPrototypesRel().GetForwardedTargets()
        idx = np.asarray(pi.GetProtoIndicesAttr().Get(code) or [], dtype=np.int64)
        mask = pi.ComputeMaskAtTime(code)
        drawn = idx[np.asarray(mask, bool)] if mask else idx
        counts = np.bincount(drawn[(drawn >= 0) & (drawn < len(protos))], minlength=len(protos))
        for path, n in zip(protos, counts, strict=True):
            uses[path] = (str(prim.GetPath()), int(n))

    def total(path: Sdf.Path, depth: int = 0) -> int:
        instancer, n = uses[path]
        outer = _prototype_root(Sdf.Path(instancer), uses)
        if outer is None or depth > len(uses):  # depth: a cycle the render refuses
            return n
        return n * total(outer, depth + 1)

    return {path: (instancer, total(path)) for path, (instancer, _) in uses.items()}


def _prototype_root(path: Sdf.Path, uses: dict) -> Sdf.Path | None:
    """The nearest PointInstancer prototype root at or above ``path``, or None."""
    for ancestor in path.GetAncestorsRange():
        if ancestor in uses:
            return ancestor
    return None


def _lights(stage: Usd.Stage) -> list[dict]:
    return [
        {"path": str(p.GetPath()), "type": p.GetTypeName() or "LightAPI"}
        for p in _traverse(stage)
        if p.HasAPI(UsdLux.LightAPI)
    ]


def _has_translucent_preview_surface(stage: Usd.Stage) -> bool:
    """Some UsdPreviewSurface shader has an authored inputs:opacity < 1."""
    for prim in _traverse(stage):
        if not prim.IsA(UsdShade.Shader):
            continue
        shader = UsdShade.Shader(prim)
        if shader.GetShaderId() != "UsdPreviewSurface":
            continue
        opacity = shader.GetInput("opacity")
        # Its value as the render reads it: through Material and NodeGraph inputs.
        attrs = opacity.GetValueProducingAttributes() if opacity else []
        if attrs and attrs[0].HasAuthoredValue():
            value = attrs[0].Get()
            if isinstance(value, float) and value < 1.0:
                return True
    return False


def render_camera(stage: Usd.Stage) -> dict:
    """The camera ``phrt render`` (without ``--camera`` or ``--settings``) renders
    through, by the render's rule (``run.render_job.prepare_job``, ``stage.choose_camera``):
    the camera the render settings' products author, else the settings' ``camera``, else
    the first UsdGeomCamera in traversal order, else the default camera framing the
    stage's bounds. Keys: ``path`` (``DEFAULT_CAMERA_NAME`` for the default camera, None
    when the render refuses the choice), ``source`` (which step chose it), ``driven_by``
    (the PhrtCameraPath driving it, or None) and ``problem`` (the render's one-line
    refusal, or None)."""
    out = {"path": None, "source": None, "driven_by": None, "problem": None}
    try:
        settings = read_render_settings(stage)
        products = {p.camera for p in settings.products if p.camera} if settings else set()
        if len(products) > 1:
            raise PhrtError(
                f"{settings.path}: products differ in camera ({', '.join(sorted(products))}); "
                "phrt renders one per run"
            )
        product_camera = products.pop() if products else None
        prim = choose_camera(stage, product_camera)
    except PhrtError as problem:
        out["problem"] = str(problem)
        return out
    if prim is None:
        out.update(path=DEFAULT_CAMERA_NAME, source="default camera (the stage has none)")
        return out
    if product_camera:
        source = "render product"
    elif settings is not None and settings.camera:
        source = f"render settings {settings.path}"
    else:
        source = "first UsdGeomCamera"
    path_prim = find_camera_path_prim(stage, str(prim.GetPath()))
    out.update(path=str(prim.GetPath()), source=source,
               driven_by=str(path_prim.GetPath()) if path_prim else None)  # fmt: skip
    return out


def required_passes(stage: Usd.Stage, lights: list[dict], n_reflectors: int) -> list[str]:
    """Render passes the stage needs, in pipeline order."""
    types = {light["type"] for light in lights}
    passes = ["gbuffer"]
    if types & set(SHADOW_LIGHT_TYPES):
        passes.append("shadows")
    if n_reflectors:
        passes.append("reflections")
    if _has_translucent_preview_surface(stage):
        passes.append("refraction")
    if types & set(ENVIRONMENT_LIGHT_TYPES):
        passes.append("environment")
    return passes


def inspect_stage(stage: Usd.Stage, label: str | None = None) -> dict:
    """Summary of an open stage as one JSON-ready dict (keys: stage, metadata, reflectors,
    instanced_reflectors (their count), camera (the camera a render uses,
    ``render_camera``), camera_paths, render_settings, lights,
    default_light_rig (no light the render reads: usd/default_lights.py), passes,
    support: what the render ignores or approximates, ``support_report.support_report``).
    ``UnreadableInput`` (one line naming the layer) when the stage's ``metersPerUnit``
    is no finite number > 0 (``stage.meters_per_unit``): nothing can be measured."""
    mpu, problems = meters_per_unit(stage)
    for problem in problems:
        raise UnreadableInput(problem)
    cache = UsdGeom.BBoxCache(
        Usd.TimeCode.Default(), [UsdGeom.Tokens.default_, UsdGeom.Tokens.render]
    )
    uses = _prototype_uses(stage)

    def instancer_of(prim: Usd.Prim) -> tuple[str, int] | tuple[None, None]:
        root = _prototype_root(prim.GetPath(), uses)
        return (None, None) if root is None else uses[root]

    reflectors = [
        {
            "path": str(p.GetPath()),
            "type": p.GetTypeName(),
            "priority": schema.reflector_priority(p),
            "reflectivity": schema.reflector_reflectivity(p),
            "triangles": _triangle_count(p),
            "bounds": _bounds(cache, p, mpu),
            # Inside an instance: the instance root and the prototype prim it shows.
            "instance": str(instance_root(p).GetPath()) if p.IsInstanceProxy() else None,
            "prototype": str(p.GetPrimInPrototype().GetPath()) if p.IsInstanceProxy() else None,
            # Inside a PointInstancer prototype: the instancer and how many instances
            # the render draws of it (one element each, ``instancers.py``).
            "point_instancer": instancer_of(p)[0],
            "instances": instancer_of(p)[1],
        }
        for p in stage_reflectors(stage)
    ]
    camera_paths = []
    for prim in schema.find_camera_paths(stage):
        data = schema.read_camera_path(prim)
        camera_paths.append(
            {
                "path": data.path,
                "camera": data.camera,
                "start": data.start,
                "end": data.end,
                "control_points": int(len(data.positions)),
                "interpolation": data.interpolation,
            }
        )
    lights = _lights(stage)
    return {
        "stage": label or stage.GetRootLayer().identifier,
        "metadata": {
            "upAxis": str(UsdGeom.GetStageUpAxis(stage)),
            "metersPerUnit": mpu,
            "startTimeCode": stage.GetStartTimeCode(),
            "endTimeCode": stage.GetEndTimeCode(),
            "timeCodesPerSecond": stage.GetTimeCodesPerSecond(),
            "defaultPrim": str(stage.GetDefaultPrim().GetPath())
            if stage.GetDefaultPrim()
            else None,
        },
        "reflectors": reflectors,
        "instanced_reflectors": sum(r["instance"] is not None for r in reflectors),
        "camera": render_camera(stage),
        "camera_paths": camera_paths,
        "render_settings": asdict(schema.read_render_params(stage)),
        "lights": lights,
        # No light the render reads: it lights the stage with the default rig
        # (usd/default_lights.py, a dim dome and a headlight), as usd/stage.py does.
        "default_light_rig": not any(li["type"] in READ_LIGHT_TYPE_NAMES for li in lights),
        "passes": required_passes(stage, lights, len(reflectors)),
        "support": support_report(stage),
    }
