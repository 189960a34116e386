"""UsdRender outputs: the render settings prim a render uses, its products and their vars.

``read_render_settings(stage, settings)`` reads, as plain data (no pxr objects out):

* **Which settings prim.** ``settings`` (``--settings PRIM``) if given, else the stage's
  ``renderSettingsPrimPath`` metadata, else the first ``UsdRenderSettings`` prim in
  traversal order (the only one on most stages) — the rule
  ``phrt_usd.usd.schema.find_render_settings`` applies to the camera and the Phrt
  parameters, so outputs, camera and parameters always come from the same prim. ``None``
  when the stage has no settings prim and none is asked for.
* **Products.** The settings' ``products`` relationship, in order: each
  ``UsdRenderProduct``'s ``productName`` (the file name template, frame tokens
  unexpanded), ``productType``, ``resolution`` and ``camera`` when authored on the product,
  its ``orderedVars`` and ``driver:parameters:OpenEXR:multipart`` (bool: write one EXR
  part per var; a single part when unauthored).
* **Vars.** Each ``UsdRenderVar``'s ``sourceName``, ``sourceType``, ``dataType`` and the
  channel name a pipeline asked for (``driver:parameters:aov:name``, the attribute
  Houdini's Solaris authors), as authored or their schema fallbacks.

* **Purposes.** ``included_purposes(stage, settings)``: the settings' ``includedPurposes``
  (the UsdGeomImageable purposes a render draws; UsdRender's fallback ``default``,
  ``render`` when unauthored or when the stage has no settings prim), with one warning
  line for a token that is no purpose.

What the vars mean and which channels they become is ``phrt_usd.run.products``' business.
A target that is not a RenderProduct / RenderVar, or a settings path that is no
RenderSettings prim, raises a one-line ``PhrtError`` naming the prim.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pxr import Sdf, Usd, UsdGeom, UsdRender

from phrt_usd.errors import BadOption, PhrtError
from phrt_usd.model.scene import CONFORM_POLICIES
from phrt_usd.usd import schema
from phrt_usd.usd.traversal import DEFAULT_INCLUDED_PURPOSES

#: The product attribute that asks for one EXR part per var (bool, not a schema attribute).
MULTIPART_ATTR = "driver:parameters:OpenEXR:multipart"
#: The var attribute naming its channels in the file (string or token).
AOV_NAME_ATTR = "driver:parameters:aov:name"


@dataclass(frozen=True)
class RenderVarSpec:
    """One ``UsdRenderVar`` as authored (schema fallbacks where unauthored)."""

    path: str
    source_name: str  # sourceName: "color", "depth", "N", "phrt:traced", ...
    source_type: str  # sourceType: raw | primvar | lpe | intrinsic
    data_type: str  # dataType: color3f, half, float, normal3f, int, ...
    aov_name: str | None = None  # driver:parameters:aov:name, None when unauthored


@dataclass(frozen=True)
class RenderProductSpec:
    """One ``UsdRenderProduct`` of the settings, in the settings' order."""

    path: str
    product_name: str  # productName, frame tokens unexpanded ("" when unauthored)
    product_type: str  # productType: "raster" (the fallback), "deepRaster", ...
    resolution: tuple[int, int] | None  # (width, height) when authored on the product
    camera: str | None  # the product's camera target when authored on the product
    vars: tuple[RenderVarSpec, ...]  # orderedVars, in order
    multipart: bool = False  # MULTIPART_ATTR


@dataclass(frozen=True)
class RenderSettingsSpec:
    """The render settings prim a render uses and its products."""

    path: str
    resolution: tuple[int, int]  # the settings' resolution (its schema fallback if unset)
    camera: str | None  # the settings' camera target, None when it has none
    products: tuple[RenderProductSpec, ...]


def read_render_settings(
    stage: Usd.Stage, settings: str | None = None
) -> RenderSettingsSpec | None:
    """The render settings a render of ``stage`` uses (see the module docstring).

    ``settings`` not a prim path: ``BadOption``; no RenderSettings prim there, or a
    product or var target of the wrong kind: ``PhrtError`` naming the prim."""
    if settings is not None and not (
        Sdf.Path.IsValidPathString(settings) and Sdf.Path(settings).IsAbsolutePath()
    ):
        raise BadOption(f"--settings {settings!r}: not an absolute prim path")
    prim = schema.find_render_settings(stage, settings)
    if prim is None:
        return None
    rs = UsdRender.Settings(prim)
    where = str(prim.GetPath())
    products = []
    for target in rs.GetProductsRel().GetForwardedTargets():
        product = stage.GetPrimAtPath(target)
        if not product or not product.IsA(UsdRender.Product):
            raise PhrtError(f"{where}.products: target {target} is not a RenderProduct prim")
        products.append(_read_product(stage, UsdRender.Product(product)))
    return RenderSettingsSpec(
        path=where,
        resolution=_resolution(rs.GetResolutionAttr(), where, authored_only=False),
        camera=_camera(rs.GetCameraRel()),
        products=tuple(products),
    )


def included_purposes(
    stage: Usd.Stage, settings: str | None = None
) -> tuple[tuple[str, ...], list[str]]:
    """(the purposes a render of ``stage`` draws, warnings): the ``includedPurposes`` of
    the settings prim the render uses (``schema.find_render_settings``), else UsdRender's
    fallback. Tokens that are no UsdGeomImageable purpose draw nothing and give a
    warning naming the attribute."""
    prim = schema.find_render_settings(stage, settings)
    if prim is None:
        return DEFAULT_INCLUDED_PURPOSES, []
    attr = UsdRender.Settings(prim).GetIncludedPurposesAttr()
    value = attr.Get()
    if value is None:
        return DEFAULT_INCLUDED_PURPOSES, []
    purposes = tuple(str(t) for t in value)
    known = set(UsdGeom.Imageable.GetOrderedPurposeTokens())
    unknown = [t for t in purposes if t not in known]
    warnings = []
    if unknown:
        warnings.append(
            f"{attr.GetPath()}: {', '.join(map(repr, unknown))} "
            f"{'is' if len(unknown) == 1 else 'are'} no purpose "
            f"(purposes: {', '.join(sorted(known))}); ignored"
        )
    return purposes, warnings


@dataclass(frozen=True)
class CameraSettings:
    """What the settings prim says about the camera's image (UsdRenderSettingsBase):
    ``aspectRatioConformPolicy`` (``CONFORM_POLICIES`` of ``phrt_usd.model.scene``),
    ``pixelAspectRatio`` (> 0) and ``dataWindowNDC`` (xmin, ymin, xmax, ymax), their
    schema fallbacks where unauthored or without a settings prim."""

    conform_policy: str = "expandAperture"
    pixel_aspect: float = 1.0
    data_window: tuple[float, float, float, float] = (0.0, 0.0, 1.0, 1.0)


def camera_settings(stage: Usd.Stage, settings: str | None = None) -> CameraSettings:
    """The ``CameraSettings`` of the settings prim a render of ``stage`` uses
    (``schema.find_render_settings``), with what its products author over it: a
    RenderProduct is a UsdRenderSettingsBase too, and its authored
    ``aspectRatioConformPolicy``, ``pixelAspectRatio`` or ``dataWindowNDC`` overrides the
    settings' for its image. One render has one image window, so products that author
    different values are refused, as for ``resolution`` and ``camera``.

    ``PhrtError`` naming the attribute for a policy that is not one of UsdRender's, a
    pixelAspectRatio not finite and > 0, a data window that is not finite with
    min < max, or products that disagree."""
    prim = schema.find_render_settings(stage, settings)
    if prim is None:
        return CameraSettings()
    values = _camera_values(UsdRender.SettingsBase(prim), authored_only=False)
    overrides: dict[str, tuple[object, str]] = {}
    for target in UsdRender.Settings(prim).GetProductsRel().GetForwardedTargets():
        product = stage.GetPrimAtPath(target)
        if not product or not product.IsA(UsdRender.Product):
            continue  # read_render_settings refuses it with its own message
        for name, value in _camera_values(UsdRender.SettingsBase(product), True).items():
            if name in overrides and overrides[name][0] != value:
                other, path = overrides[name][1], str(target)
                raise PhrtError(
                    f"products differ in {_CAMERA_ATTRS[name]} ({other}: "
                    f"{overrides[name][0]}, {path}: {value}); phrt renders one image "
                    "window per run"
                )
            overrides[name] = (value, str(target))
    values.update({name: value for name, (value, _) in overrides.items()})
    return CameraSettings(**values)


#: ``CameraSettings`` field → the UsdRenderSettingsBase attribute it comes from.
_CAMERA_ATTRS = {
    "conform_policy": "aspectRatioConformPolicy",
    "pixel_aspect": "pixelAspectRatio",
    "data_window": "dataWindowNDC",
}


def _camera_values(base: UsdRender.SettingsBase, authored_only: bool) -> dict:
    """The ``CameraSettings`` fields ``base`` (a settings or product prim) gives: every
    field (schema fallbacks where unauthored) or, with ``authored_only``, those it
    authors. PhrtError naming the attribute for a value out of its domain."""
    values: dict = {}
    policy_attr = base.GetAspectRatioConformPolicyAttr()
    if not authored_only or policy_attr.HasAuthoredValue():
        policy = str(policy_attr.Get() or CameraSettings.conform_policy)
        if policy not in CONFORM_POLICIES:
            raise PhrtError(
                f"{policy_attr.GetPath()}: {policy!r} is not one of {', '.join(CONFORM_POLICIES)}"
            )
        values["conform_policy"] = policy
    par_attr = base.GetPixelAspectRatioAttr()
    if not authored_only or par_attr.HasAuthoredValue():
        par = par_attr.Get()
        par = float(CameraSettings.pixel_aspect if par is None else par)
        if not (math.isfinite(par) and par > 0):
            raise PhrtError(f"{par_attr.GetPath()}: must be finite and > 0, got {par}")
        values["pixel_aspect"] = par
    window_attr = base.GetDataWindowNDCAttr()
    if not authored_only or window_attr.HasAuthoredValue():
        window = window_attr.Get()
        window = CameraSettings.data_window if window is None else tuple(float(x) for x in window)
        x0, y0, x1, y1 = window
        if not (all(math.isfinite(x) for x in window) and x0 < x1 and y0 < y1):
            raise PhrtError(
                f"{window_attr.GetPath()}: need finite xmin < xmax and ymin < ymax, got {window}"
            )
        values["data_window"] = window
    return values


def _read_product(stage: Usd.Stage, product: UsdRender.Product) -> RenderProductSpec:
    where = str(product.GetPath())
    variables = []
    for target in product.GetOrderedVarsRel().GetForwardedTargets():
        var = stage.GetPrimAtPath(target)
        if not var or not var.IsA(UsdRender.Var):
            raise PhrtError(f"{where}.orderedVars: target {target} is not a RenderVar prim")
        variables.append(_read_var(UsdRender.Var(var)))
    multipart = product.GetPrim().GetAttribute(MULTIPART_ATTR)
    value = multipart.Get() if multipart and multipart.HasAuthoredValue() else False
    if not isinstance(value, bool):
        raise PhrtError(f"{where}.{MULTIPART_ATTR}: {value!r} is not a bool")
    return RenderProductSpec(
        path=where,
        product_name=str(product.GetProductNameAttr().Get() or ""),
        product_type=str(product.GetProductTypeAttr().Get() or "raster"),
        resolution=_resolution(product.GetResolutionAttr(), where, authored_only=True),
        camera=_camera(product.GetCameraRel()),
        vars=tuple(variables),
        multipart=value,
    )


def _read_var(var: UsdRender.Var) -> RenderVarSpec:
    aov = var.GetPrim().GetAttribute(AOV_NAME_ATTR)
    aov_name = aov.Get() if aov and aov.HasAuthoredValue() else None
    if aov_name is not None and not isinstance(aov_name, str):
        raise PhrtError(f"{var.GetPath()}.{AOV_NAME_ATTR}: {aov_name!r} is not a string")
    return RenderVarSpec(
        path=str(var.GetPath()),
        source_name=str(var.GetSourceNameAttr().Get() or ""),
        source_type=str(var.GetSourceTypeAttr().Get() or "raw"),
        data_type=str(var.GetDataTypeAttr().Get() or "color3f"),
        aov_name=str(aov_name) if aov_name else None,
    )


def _resolution(attr: Usd.Attribute, where: str, *, authored_only: bool):
    """(width, height) of a ``resolution`` attribute; None if ``authored_only`` and it is
    not authored. PhrtError unless both are positive."""
    if authored_only and not attr.HasAuthoredValue():
        return None
    value = attr.Get()
    if value is None:
        return None
    width, height = int(value[0]), int(value[1])
    if width <= 0 or height <= 0:
        raise PhrtError(f"{where}.resolution: {width}x{height} is not a positive size")
    return width, height


def _camera(rel: Usd.Relationship) -> str | None:
    targets = rel.GetForwardedTargets()
    return str(targets[0]) if targets else None
