"""Materials: bound UsdPreviewSurface materials as ``MaterialTable`` rows, textures.

``MaterialBank`` reads each bound material once (``ComputeBoundMaterial`` per gprim and
per ``materialBind`` GeomSubset, ``face_materials``) and deduplicates them into one
``phrt_usd.model.scene.MaterialTable`` (row 0 = no material). UsdPreviewSurface inputs
are read with their connections followed: ``diffuseColor`` may come from a
``UsdUVTexture``, whose image ``read_texture`` loads. Materials are read once, at the
start of the frame range (not animated).

- A textured ``diffuseColor`` is stored as the texture's mean colour (the row's
  ``diffuse``) plus the texture itself (``MaterialTable.textures``).
- Textures are stored as read, row 0 = **top** of the image; USD ``st`` has v = 0 at the
  **bottom**, so a sampler reads row ``(1 - v) * h``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pxr import Usd, UsdRender, UsdShade

from phrt_usd.errors import PhrtError
from phrt_usd.model.scene import MaterialTable
from phrt_usd.usd import schema, textures

#: UsdPreviewSurface's own fallback ``diffuseColor`` (used when a material is bound but
#: its diffuseColor is unauthored and the gprim has no displayColor).
PREVIEW_SURFACE_DIFFUSE = 0.18


@dataclass
class _MaterialRow:
    diffuse: np.ndarray  # (3,) linear RGB (texture mean when textured)
    diffuse_authored: bool
    metallic: float = 0.0
    roughness: float = 0.5
    opacity: float = 1.0
    ior: float = 1.5
    emissive: np.ndarray = field(default_factory=lambda: np.zeros(3))
    texture: np.ndarray | None = None  # (h, w, 3) float32 linear, row 0 = top
    uv_primvar: str = "st"


def read_texture(value, where: str, color_space: str = "auto") -> np.ndarray:
    """A texture file (through ``usd/textures.py``, USD's resolver) as (h, w, 3)
    float32 linear RGB, row 0 = top; grey images are replicated to RGB."""
    pixels, _ = textures.read_texture(value, where, color_space)
    if pixels.shape[2] < 3:
        return np.ascontiguousarray(np.repeat(pixels[..., :1], 3, axis=2))
    return np.ascontiguousarray(pixels[..., :3])


#: UsdRender ``materialBindingPurposes`` fallback: the ``full`` binding, then the
#: all-purpose one ("").
DEFAULT_BINDING_PURPOSES = ("full", "")


def binding_purposes(stage: Usd.Stage, settings: str | None = None) -> tuple[str, ...]:
    """The ``materialBindingPurposes`` of the render settings prim a render uses
    (``schema.find_render_settings``), else ``DEFAULT_BINDING_PURPOSES``."""
    prim = schema.find_render_settings(stage, settings)
    if prim is None:
        return DEFAULT_BINDING_PURPOSES
    value = UsdRender.Settings(prim).GetMaterialBindingPurposesAttr().Get()
    return DEFAULT_BINDING_PURPOSES if value is None else tuple(str(t) for t in value)


def _binding_purpose(name: str) -> str:
    """The purpose of a binding relationship by its name: ``material:binding[:purpose]``
    or ``material:binding:collection[:purpose]:bindingName``."""
    parts = name.split(":")[2:]
    if parts and parts[0] == "collection":
        return parts[1] if len(parts) == 3 else ""
    return parts[0] if parts else ""


def bound_material(prim: Usd.Prim, purposes: tuple[str, ...]) -> UsdShade.Material | None:
    """The material bound to ``prim`` for the first of ``purposes`` ("" = all-purpose)
    that has a binding (direct or collection, ``ComputeBoundMaterial`` semantics)."""
    api = UsdShade.MaterialBindingAPI(prim)
    for purpose in purposes:
        mat, rel = api.ComputeBoundMaterial(purpose or UsdShade.Tokens.allPurpose)
        if not mat:
            continue
        # ComputeBoundMaterial falls back to the all-purpose binding by itself; only
        # accept that when "" is the purpose asked for.
        rel_purpose = _binding_purpose(rel.GetName()) if rel else ""
        if purpose == "" or rel_purpose == purpose:
            return mat
    return None


def material_key(material: UsdShade.Material | None) -> str:
    """Identity of a material for deduplication: its path, or for a material reached
    through an instance proxy the path of its prim in the prototype (all instances of a
    prototype share one row). "" for no material."""
    if not material:
        return ""
    prim = material.GetPrim()
    return str(prim.GetPrimInPrototype().GetPath() if prim.IsInstanceProxy() else prim.GetPath())


class MaterialBank:
    """Deduplicates bound materials into table rows. Row 0 = no material bound."""

    def __init__(self, time: Usd.TimeCode, purposes: tuple[str, ...] = DEFAULT_BINDING_PURPOSES):
        self.time = time
        self.purposes = tuple(purposes)
        self.rows: list[_MaterialRow] = [
            _MaterialRow(np.full(3, PREVIEW_SURFACE_DIFFUSE), diffuse_authored=False)
        ]
        self._index: dict[str, int] = {"": 0}
        self._textures: dict[tuple[str, str], np.ndarray] = {}
        #: One line per texture that could not be read (the render goes on with the
        #: input's fallback; ``--strict`` and ``phrt validate`` make each an error).
        self.texture_problems: list[str] = []

    def index(self, material: UsdShade.Material | None) -> int:
        key = material_key(material)
        if key not in self._index:
            self._index[key] = len(self.rows)
            self.rows.append(self._read(material))
        return self._index[key]

    def _value(self, shader: UsdShade.Shader, name: str):
        """(value, source shader or None) of an input, following connections."""
        inp = shader.GetInput(name)
        if not inp:
            return None, None
        attrs = inp.GetValueProducingAttributes()
        if not attrs:
            return None, None
        attr = attrs[0]
        if UsdShade.Utils.GetType(attr.GetName()) == UsdShade.AttributeType.Output:
            return attr.GetBaseName(), UsdShade.Shader(attr.GetPrim())
        return attr.Get(self.time), None

    def _read(self, material: UsdShade.Material) -> _MaterialRow:
        row = _MaterialRow(np.full(3, PREVIEW_SURFACE_DIFFUSE), diffuse_authored=False)
        shader = material.ComputeSurfaceSource()[0]
        if not shader or shader.GetIdAttr().Get() != "UsdPreviewSurface":
            return row  # not a preview surface: fall back like a bare material
        for name, attr_name in (
            ("metallic", "metallic"),
            ("roughness", "roughness"),
            ("opacity", "opacity"),
            ("ior", "ior"),
        ):
            value, src = self._value(shader, name)
            if src is None and value is not None and np.isfinite(float(value)):
                setattr(row, attr_name, float(value))
        row.metallic = float(np.clip(row.metallic, 0.0, 1.0))
        row.roughness = float(np.clip(row.roughness, 0.0, 1.0))
        row.opacity = float(np.clip(row.opacity, 0.0, 1.0))
        value, src = self._value(shader, "emissiveColor")
        if src is None and value is not None:
            row.emissive = np.nan_to_num(np.asarray(value, dtype=np.float64))
        value, src = self._value(shader, "diffuseColor")
        if src is not None:
            self._read_texture_input(row, src, value, str(material.GetPath()))
        elif value is not None:
            row.diffuse = np.clip(np.nan_to_num(np.asarray(value, dtype=np.float64)), 0, None)
            row.diffuse_authored = True
        return row

    def _read_texture_input(
        self, row: _MaterialRow, tex: UsdShade.Shader, output: str, where: str
    ) -> None:
        """Fill ``row`` from a UsdUVTexture feeding ``diffuseColor``."""
        if tex.GetIdAttr().Get() != "UsdUVTexture":
            return  # some other node (e.g. a primvar reader): keep the default colour
        file_value, _ = self._value(tex, "file")
        where = f"{tex.GetPath()}.inputs:file"
        fallback, _ = self._value(tex, "fallback")
        space, _ = self._value(tex, "sourceColorSpace")
        space = str(space or "auto")
        key = (str(getattr(file_value, "resolvedPath", "") or file_value), space)
        if key not in self._textures and file_value is not None:
            try:
                self._textures[key] = read_texture(file_value, where, space)
            except textures.TextureError as problem:
                self._textures[key] = None
                self.texture_problems.append(str(problem))
        if self._textures.get(key) is None:
            # Unreadable or no file: UsdUVTexture's fallback where authored, else the
            # input's own (UsdPreviewSurface diffuseColor 0.18).
            if fallback is not None:
                row.diffuse = np.asarray(fallback, dtype=np.float64)[:3]
                row.diffuse_authored = True
            return
        image = self._textures[key]
        scale, _ = self._value(tex, "scale")
        bias, _ = self._value(tex, "bias")
        if scale is not None or bias is not None:
            s = np.asarray(scale if scale is not None else (1, 1, 1, 1), np.float32)[:3]
            b = np.asarray(bias if bias is not None else (0, 0, 0, 0), np.float32)[:3]
            image = image * s + b
        channel = {"r": 0, "g": 1, "b": 2}.get(output)
        if channel is not None:
            image = np.repeat(image[..., channel : channel + 1], 3, axis=2)
        row.texture = np.ascontiguousarray(image, dtype=np.float32)
        row.diffuse = image.reshape(-1, 3).mean(axis=0).astype(np.float64)
        row.diffuse_authored = True
        st, reader = self._value(tex, "st")
        if reader is not None:
            varname, _ = self._value(reader, "varname")
            if varname:
                row.uv_primvar = str(varname)

    def table(self) -> MaterialTable:
        rows = self.rows
        return MaterialTable(
            diffuse=np.array([r.diffuse for r in rows], dtype=np.float32).reshape(-1, 3),
            metallic=np.array([r.metallic for r in rows], dtype=np.float32),
            roughness=np.array([r.roughness for r in rows], dtype=np.float32),
            opacity=np.array([r.opacity for r in rows], dtype=np.float32),
            ior=np.array([r.ior for r in rows], dtype=np.float32),
            emissive=np.array([r.emissive for r in rows], dtype=np.float32).reshape(-1, 3),
            textures=[r.texture for r in rows],
        )


def face_materials(prim: Usd.Prim, n_faces: int, bank: MaterialBank) -> tuple[np.ndarray, int]:
    """Material row per face (F,) int32 from the prim binding and materialBind subsets."""
    binding = UsdShade.MaterialBindingAPI(prim)
    base = bank.index(bound_material(prim, bank.purposes))
    face_mat = np.full(n_faces, base, dtype=np.int32)
    for subset in binding.GetMaterialBindSubsets():
        sub_mat = bound_material(subset.GetPrim(), bank.purposes)
        if not sub_mat:
            continue
        idx = np.asarray(subset.GetIndicesAttr().Get(bank.time) or [], dtype=np.int64)
        if len(idx) and (idx.min() < 0 or idx.max() >= n_faces):
            raise PhrtError(f"{subset.GetPath()}.indices: face index out of range")
        face_mat[idx] = bank.index(sub_mat)
    return face_mat, base
