"""Materials: bound UsdPreviewSurface materials as ``MaterialTable`` rows, textures.

``MaterialBank`` reads each bound material once (``ComputeBoundMaterial`` per gprim and
per ``materialBind`` GeomSubset, ``face_materials``) and deduplicates them into one
``phrt_usd.model.scene.MaterialTable`` (row 0 = no material). UsdPreviewSurface inputs
are read with their connections followed (material interface inputs included).
Materials are read once, at the start of the frame range (not animated).

Texturable inputs the render uses (``TEXTURED_INPUTS``): ``diffuseColor``,
``emissiveColor``, ``opacity``, ``normal`` (tangent space, ``model.surface.
NormalMaps``) and the BRDF's (``model/preview_surface.py``): ``metallic``,
``roughness``, ``specularColor``, ``useSpecularWorkflow``, ``ior``, ``clearcoat``,
``clearcoatRoughness``, ``occlusion``; each possibly fed by a ``UsdUVTexture`` output
(``rgb``, ``r``, ``g``, ``b``, ``a``), read as a ``TextureInput`` as the
UsdPreviewSurface specification defines it:

- ``file`` through the resolver (``usd/textures.py``); ``sourceColorSpace`` ``raw`` /
  ``sRGB`` / ``auto`` (``textures.read_texture``); ``fallback`` (float4) where the
  texture cannot be read or no file is authored, else the input's own fallback (for
  ``diffuseColor`` the spec's 0.18, not the gprim's displayColor);
- ``wrapS`` / ``wrapT``: repeat, mirror, clamp, black, and ``useMetadata`` (the
  fallback): the file's own wrap metadata, else ``black``;
- ``scale`` / ``bias`` (float4, per output component);
- ``st``: a ``UsdPrimvarReader_float2`` (its ``varname``, default ``st``), optionally
  through a ``UsdTransform2d`` (``in`` * ``scale``, rotated by ``rotation`` degrees
  counter-clockwise, then moved by ``translation``).

Every input is read through ``UsdShadeInput.GetValueProducingAttributes``: an input
connected to an input of its Material (or of a NodeGraph, at any depth) takes that
input's value, in instanced Materials and instance proxies too. A ``UsdPrimvarReader``
on ``diffuseColor`` makes the gprim's primvar ``varname`` (itself possibly a Material
input: Houdini's and Maya's exports) its colour per corner, in place of
``displayColor`` (``colour_primvar``); without that primvar, the reader's ``fallback``.

``opacityThreshold`` > 0 makes the material a cut-out (``model.surface.Cutouts``): the
opacity, constant or textured (``outputs:a`` of a file without alpha reads 1), is a
presence mask. Opacity < 1 without a threshold stays the constant ``opacity`` of the
row (transmissive when < 1); a *textured* opacity without a threshold is not used as
translucency (the row is opaque; docs/usd-support.md, known limits).

``displacement`` is not read (``usd/support_report.py`` lists it).

MaterialX (``usd/materialx.py``): a material whose surface is MaterialX's
``standard_surface``, ``open_pbr_surface`` or ``UsdPreviewSurface`` node, authored in USD
(a Shader of that ``info:id`` on the ``mtlx`` or universal surface output) or in a
``.mtlx`` document a prim references (``bound_material`` returns a
``materialx.DocumentMaterial`` where the binding's target lies under such an arc), is
mapped onto the UsdPreviewSurface inputs (``materialx.map_surface``), plain image nodes
read as textures; one notice per material only where the mapping leaves something out.
Other MaterialX surfaces render grey, with a notice.

- A textured ``diffuseColor`` is stored as the texture's mean colour (the row's
  ``diffuse``) plus the texture (``MaterialTable.textures``, the ``rgb`` after scale and
  bias) and its ``TextureInput`` (``MaterialTable.texture_inputs``).
- Textures are stored as read, row 0 = **top** of the image; USD ``st`` has v = 0 at the
  **bottom**, so a sampler reads row ``(1 - v) * h``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import PurePosixPath

import numpy as np
from pxr import Usd, UsdRender, UsdShade

from phrt_usd.errors import PhrtError
from phrt_usd.model.scene import ALPHA_ONE, WRAP_MODES, MaterialTable, TextureInput
from phrt_usd.usd import materialx, schema, textures

#: UsdPreviewSurface's own fallback ``diffuseColor`` (used when a material is bound but
#: its diffuseColor is unauthored and the gprim has no displayColor).
PREVIEW_SURFACE_DIFFUSE = 0.18

#: UsdPreviewSurface inputs read from textures: name -> components (the others the
#: shading does not use; see the module).
TEXTURED_INPUTS = {
    "diffuseColor": 3, "emissiveColor": 3, "opacity": 1, "normal": 3, "metallic": 1,
    "roughness": 1, "specularColor": 3, "useSpecularWorkflow": 1, "ior": 1, "clearcoat": 1,
    "clearcoatRoughness": 1, "occlusion": 1,
}  # fmt: skip

#: The BRDF's scalar inputs read as constants: input name -> ``_MaterialRow`` field (its
#: fallback there), each clamped to [0, 1] but ``ior`` (> 0).
BRDF_INPUTS = {
    "metallic": "metallic", "roughness": "roughness", "ior": "ior", "clearcoat": "clearcoat",
    "clearcoatRoughness": "clearcoat_roughness", "occlusion": "occlusion",
}  # fmt: skip

#: UsdUVTexture output -> the file's channel per component, by the file's channel count
#: (1 grey, 2 grey + alpha, 3 RGB, 4 RGBA); ``ALPHA_ONE``: no alpha, reads 1.
_OUTPUT_CHANNELS = {
    "rgb": {1: (0, 0, 0), 2: (0, 0, 0), 3: (0, 1, 2), 4: (0, 1, 2)},
    "r": {1: (0,), 2: (0,), 3: (0,), 4: (0,)},
    "g": {1: (0,), 2: (0,), 3: (1,), 4: (1,)},
    "b": {1: (0,), 2: (0,), 3: (2,), 4: (2,)},
    "a": {1: (ALPHA_ONE,), 2: (1,), 3: (ALPHA_ONE,), 4: (3,)},
}
#: The float4 components (scale, bias, fallback) of each output.
_OUTPUT_COMPONENTS = {"rgb": (0, 1, 2), "r": (0,), "g": (1,), "b": (2,), "a": (3,)}

#: OpenImageIO ``wrapmodes`` metadata words -> UsdUVTexture wrap modes.
_METADATA_WRAP = {"periodic": "repeat", "mirror": "mirror", "clamp": "clamp", "black": "black"}

@dataclass
class _MaterialRow:
    diffuse: np.ndarray  # (3,) linear RGB (texture mean when textured)
    diffuse_authored: bool
    metallic: float = 0.0
    roughness: float = 0.5
    opacity: float = 1.0
    ior: float = 1.5
    clearcoat: float = 0.0
    clearcoat_roughness: float = 0.01
    occlusion: float = 1.0
    use_specular_workflow: float = 0.0
    specular_color: np.ndarray = field(default_factory=lambda: np.zeros(3))
    emissive: np.ndarray = field(default_factory=lambda: np.zeros(3))
    texture: np.ndarray | None = None  # (h, w, 3) float32 linear diffuse rgb, row 0 = top
    uv_primvar: str = "st"
    #: The primvar a ``UsdPrimvarReader`` on ``diffuseColor`` reads (the gprim's colour
    #: per corner in place of ``displayColor``), None when no reader feeds it.
    colour_primvar: str | None = None
    opacity_threshold: float = 0.0
    #: A UsdPreviewSurface: its roughness blurs its reflections (``MaterialTable.glossy``).
    glossy: bool = False
    #: UsdPreviewSurface input name -> its ``TextureInput`` (``TEXTURED_INPUTS``).
    inputs: dict[str, TextureInput] = field(default_factory=dict)

    @property
    def needs_uv(self) -> bool:
        """Some input of the row is textured: the gprim's texture coordinates are read."""
        return bool(self.inputs)


def read_texture(value, where: str, color_space: str = "auto") -> np.ndarray:
    """A texture file (through ``usd/textures.py``, USD's resolver) as (h, w, 3)
    float32 linear RGB, row 0 = top; grey images are replicated to RGB."""
    pixels, _ = textures.read_texture(value, where, color_space)
    if pixels.shape[2] < 3:
        return np.ascontiguousarray(np.repeat(pixels[..., :1], 3, axis=2))
    return np.ascontiguousarray(pixels[..., :3])


def transform_2d(rotation: float, scale, translation) -> np.ndarray | None:
    """(2, 3) float64 affine st -> st' of a UsdTransform2d: ``st * scale``, rotated by
    ``rotation`` degrees counter-clockwise, then ``+ translation``; None for identity."""
    s = np.asarray(scale, np.float64).reshape(2)
    t = np.asarray(translation, np.float64).reshape(2)
    a = np.radians(float(rotation))
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    m = np.concatenate([rot * s[None, :], t[:, None]], axis=1)
    if np.array_equal(m, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]):
        return None
    return m


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


def bound_material(
    prim: Usd.Prim, purposes: tuple[str, ...]
) -> UsdShade.Material | materialx.DocumentMaterial | None:
    """The material bound to ``prim`` for the first of ``purposes`` ("" = all-purpose)
    that has a binding (direct or collection, ``ComputeBoundMaterial`` semantics); a
    binding whose target USD could not compose because it lies under a ``.mtlx``
    document's arc gives that document's material (``materialx.referenced_material``)."""
    api = UsdShade.MaterialBindingAPI(prim)
    for purpose in purposes:
        mat, rel = api.ComputeBoundMaterial(purpose or UsdShade.Tokens.allPurpose)
        # ComputeBoundMaterial falls back to the all-purpose binding by itself; only
        # accept that when "" is the purpose asked for.
        rel_purpose = _binding_purpose(rel.GetName()) if rel else ""
        if not (purpose == "" or rel_purpose == purpose):
            continue
        if mat:
            return mat
        document = _document_material(prim.GetStage(), rel) if rel else None
        if document is not None:
            return document
    return None


def _document_material(stage: Usd.Stage, rel: Usd.Relationship):
    """The ``materialx.DocumentMaterial`` a binding relationship whose target is no
    Material names, or None."""
    collection = ":collection:" in rel.GetName()
    binding = (UsdShade.MaterialBindingAPI.CollectionBinding(rel) if collection
               else UsdShade.MaterialBindingAPI.DirectBinding(rel))  # fmt: skip
    path = binding.GetMaterialPath()
    return None if path.isEmpty else materialx.referenced_material(stage, path)


def material_key(material: UsdShade.Material | None) -> str:
    """Identity of a material for deduplication: its path, or for a material reached
    through an instance proxy the path of its prim in the prototype (all instances of a
    prototype share one row). "" for no material."""
    if not material:
        return ""
    if isinstance(material, materialx.DocumentMaterial):
        return material.path
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
        #: (resolved path, colour space) -> (pixels (h, w, c), wrap metadata) or None.
        self._files: dict[tuple[str, str], tuple[np.ndarray, str] | None] = {}
        #: One line per texture that could not be read (the render goes on with the
        #: input's fallback; ``--strict`` and ``phrt validate`` make each an error).
        self.texture_problems: list[str] = []
        #: One line per material rendered approximately (MaterialX surfaces).
        self.notices: list[str] = []
        #: Some row's colour comes from a primvar reader (``colour_primvar`` then looks).
        self.reads_colour_primvars = False
        #: Materials of MaterialX surfaces by treatment ("mapped" / "grey").
        self.materialx_paths: dict[str, list[str]] = {"mapped": [], "grey": []}

    def index(self, material: UsdShade.Material | None) -> int:
        key = material_key(material)
        if key not in self._index:
            self._index[key] = len(self.rows)
            self.rows.append(self._read(material))
        return self._index[key]

    def _value(self, shader: UsdShade.Shader, name: str):
        """(value, source shader or None) of an input, following connections: for a
        connected shader output (its name, the shader), else the value (None when
        unauthored and without fallback)."""
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

    def _constant(self, shader: UsdShade.Shader, name: str, default):
        """A finite constant input as float64 (``default`` when unauthored, connected
        or not finite)."""
        value, src = self._value(shader, name)
        if src is not None or value is None:
            return np.asarray(default, np.float64)
        value = np.asarray(value, np.float64)
        return value if np.all(np.isfinite(value)) else np.asarray(default, np.float64)

    def _read(self, material) -> _MaterialRow:
        row = _MaterialRow(np.full(3, PREVIEW_SURFACE_DIFFUSE), diffuse_authored=False)
        if isinstance(material, materialx.DocumentMaterial):
            self._read_document(row, material)
            return row
        shader = material.ComputeSurfaceSource()[0]
        if not shader or shader.GetIdAttr().Get() != "UsdPreviewSurface":
            self._read_materialx(row, material)
            return row
        row.glossy = True
        for name, attr in (*BRDF_INPUTS.items(), ("opacity", "opacity")):
            value = float(self._constant(shader, name, getattr(row, attr)))
            setattr(row, attr, value if name == "ior" else float(np.clip(value, 0.0, 1.0)))
        if not row.ior > 0.0:
            row.ior = 1.5
        row.use_specular_workflow = float(self._constant(shader, "useSpecularWorkflow", 0) != 0)
        row.specular_color = np.clip(self._constant(shader, "specularColor", np.zeros(3)), 0, 1)
        threshold = float(self._constant(shader, "opacityThreshold", 0.0))
        row.opacity_threshold = float(np.clip(threshold, 0.0, 1.0))
        row.emissive = np.clip(self._constant(shader, "emissiveColor", np.zeros(3)), 0, None)
        value, src = self._value(shader, "diffuseColor")
        if src is None and value is not None:
            row.diffuse = np.clip(np.nan_to_num(np.asarray(value, dtype=np.float64)), 0, None)
            row.diffuse_authored = True
        if src is not None and _is_primvar_reader(src):
            self._primvar_colour(row, src)
        unread = []
        for name in TEXTURED_INPUTS:
            output, src = self._value(shader, name)
            if src is None:
                continue
            node = str(src.GetIdAttr().Get() or "")
            if node == "UsdUVTexture":
                self._texture_input(row, name, src, str(output))
            elif not (name == "diffuseColor" and _is_primvar_reader(src)):
                unread.append(f"{name} ({node or src.GetPath()})")
        if unread:  # the support report's unread_shader_node
            self.notices.append(
                f"{material.GetPath()}: {', '.join(unread)} fed by nodes the render does not "
                "run; rendered with the inputs' fallbacks"
            )
        return row

    def _primvar_colour(self, row: _MaterialRow, reader: UsdShade.Shader) -> None:
        """``diffuseColor`` fed by a ``UsdPrimvarReader``: the gprim's primvar
        ``varname`` (followed through its connections, e.g. to an input of the Material)
        is its colour per corner; a gprim without that primvar takes the reader's
        ``fallback`` (the spec's 0)."""
        name, _ = self._value(reader, "varname")
        row.colour_primvar = str(name) if name else None
        if row.colour_primvar is None:
            return
        self.reads_colour_primvars = True
        fallback = np.nan_to_num(np.asarray(self._constant(reader, "fallback", 0.0), np.float64))
        row.diffuse = np.clip(np.resize(fallback.reshape(-1), 3), 0.0, None)
        row.diffuse_authored = False  # the primvar, where the gprim has it

    def _texture_input(self, row: _MaterialRow, name: str, tex: UsdShade.Shader, output: str):
        """Fill input ``name`` of ``row`` from output ``output`` of the UsdUVTexture
        ``tex`` (see the module): its ``TextureInput``, or the fallback when the file
        cannot be read."""
        if tex.GetIdAttr().Get() != "UsdUVTexture" or output not in _OUTPUT_CHANNELS:
            return  # some other node: the input keeps its constant
        comps = _OUTPUT_COMPONENTS[output]
        where = f"{tex.GetPath()}.inputs:file"
        file_value, _ = self._value(tex, "file")
        space = str(self._value(tex, "sourceColorSpace")[0] or "auto")
        read = self._file(file_value, where, space)
        if read is None:  # no file authored, or one that cannot be read
            fallback, _ = self._value(tex, "fallback")
            if fallback is not None:
                self._set_constant(row, name, np.asarray(fallback, np.float64)[list(comps)])
            elif name == "diffuseColor":
                # The input's own fallback (the row's other inputs keep theirs), not the
                # gprim's displayColor.
                row.diffuse = np.full(3, PREVIEW_SURFACE_DIFFUSE)
                row.diffuse_authored = True
            return
        pixels, metadata = read
        channels = _OUTPUT_CHANNELS[output][min(max(pixels.shape[2], 1), 4)]
        scale = self._constant(tex, "scale", (1.0, 1.0, 1.0, 1.0)).reshape(4)[list(comps)]
        bias = self._constant(tex, "bias", (0.0, 0.0, 0.0, 0.0)).reshape(4)[list(comps)]
        wrap = tuple(self._wrap(tex, axis, metadata) for axis in ("wrapS", "wrapT"))
        transform, varname = self._st(tex)
        spec = TextureInput(
            image=pixels,
            channels=tuple(int(c) for c in channels),
            scale=scale.astype(np.float32),
            bias=bias.astype(np.float32),
            wrap=wrap,
            transform=transform,
        )
        self._use(row, name, spec, varname)

    def _use(self, row: _MaterialRow, name: str, spec: TextureInput, varname: str) -> None:
        """Record ``spec`` as input ``name`` of ``row`` (reading texture coordinates
        ``varname``), with the informative constants (texture means)."""
        row.inputs[name] = spec
        row.uv_primvar = varname
        h, w = spec.image.shape[:2]
        img = spec.image.reshape(h * w, -1)
        # The texels' mean, channel by channel: scale and bias are affine, so the mean of
        # the file's channel scaled is the scaled mean (no texel-sized temporaries: a
        # 2048² map is 50 MB a channel set).
        channel_means = [1.0 if c == ALPHA_ONE else float(img[:, c].mean(dtype=np.float64))
                         for c in spec.channels]  # fmt: skip
        mean = np.asarray(channel_means) * spec.scale + spec.bias
        if name == "diffuseColor":
            # RGB from the first three outputs, or the first one as grey; the file's own
            # array where it is that already (an RGB file read as it is: no copy).
            outputs = (0, 1, 2) if len(spec.channels) >= 3 else (0, 0, 0)
            plain = (
                tuple(spec.channels) == (0, 1, 2) and spec.image.shape[2] == 3
                and spec.image.dtype == np.float32 and spec.image.flags.c_contiguous
                and np.all(spec.scale == 1.0) and np.all(spec.bias == 0.0)
            )  # fmt: skip
            if plain:
                row.texture = spec.image
            else:
                row.texture = self._diffuse_texels(spec, img, outputs).reshape(h, w, 3)
            row.diffuse = np.broadcast_to(mean, (3,)).copy() if mean.size == 1 else mean[:3]
            row.diffuse_authored = True
        elif name == "emissiveColor":
            row.emissive = np.broadcast_to(mean, (3,)).copy() if mean.size == 1 else mean[:3]
        elif name == "opacity":
            # A textured opacity is a presence mask of a cut-out; without a threshold
            # it is not used as translucency (module docstring): the row is opaque.
            row.opacity = 1.0

    @staticmethod
    def _diffuse_texels(spec: TextureInput, img: np.ndarray, outputs) -> np.ndarray:
        """(h w, 3) float32 diffuse colour texels of ``spec`` (``img`` its file's (h w, c)
        texels): its ``outputs`` (indices into its channels) scaled and biased."""
        texels = np.empty((len(img), 3), np.float32)
        for k, j in enumerate(outputs):
            c = spec.channels[j]
            src = np.float32(1.0) if c == ALPHA_ONE else img[:, c]
            texels[:, k] = src * spec.scale[j] + spec.bias[j]
        return texels

    def _set_constant(self, row: _MaterialRow, name: str, value: np.ndarray) -> None:
        """An unreadable texture's ``fallback`` components as the input's constant."""
        value = np.nan_to_num(value)
        if name == "diffuseColor":
            row.diffuse = np.clip(np.broadcast_to(value, (3,)), 0, None).astype(np.float64)
            row.diffuse_authored = True
        elif name == "emissiveColor":
            row.emissive = np.clip(np.broadcast_to(value, (3,)), 0, None).astype(np.float64)
        elif name == "opacity":
            row.opacity = float(np.clip(value.reshape(-1)[0], 0.0, 1.0))
        elif name == "specularColor":
            row.specular_color = np.clip(np.broadcast_to(value, (3,)), 0, 1).astype(np.float64)
        elif name == "useSpecularWorkflow":
            row.use_specular_workflow = float(value.reshape(-1)[0] != 0)
        elif name in BRDF_INPUTS:
            setattr(row, BRDF_INPUTS[name], float(value.reshape(-1)[0]))

    def _file(self, file_value, where: str, space: str):
        """(pixels (h, w, c) float32, wrap metadata) of a texture file, read once per
        (resolved path, colour space); None (and one problem line) when unreadable or
        no file is authored."""
        if file_value is None or not str(getattr(file_value, "path", file_value) or ""):
            return None
        key = (str(getattr(file_value, "resolvedPath", "") or file_value), space)
        if key not in self._files:
            try:
                self._files[key] = textures.read_texture(file_value, where, space)
            except textures.TextureError as problem:
                self._files[key] = None
                self.texture_problems.append(str(problem))
        return self._files[key]

    def _wrap(self, tex: UsdShade.Shader, axis: str, metadata: str) -> str:
        """``wrapS`` / ``wrapT`` of ``tex`` as one of ``WRAP_MODES``; ``useMetadata``
        (the fallback) reads the file's wrap metadata ("s,t"), else ``black``."""
        value = str(self._value(tex, axis)[0] or "useMetadata")
        if value in WRAP_MODES:
            return value
        words = [w.strip() for w in metadata.split(",")] if metadata else []
        k = 0 if axis == "wrapS" else 1
        word = words[k] if len(words) > k else (words[0] if words else "")
        return _METADATA_WRAP.get(word, "black")

    def _st(self, tex: UsdShade.Shader) -> tuple[np.ndarray | None, str]:
        """(UsdTransform2d affine or None, primvar name) of a texture's ``st`` input."""
        transform = None
        st, src = self._value(tex, "st")
        if src is not None and src.GetIdAttr().Get() == "UsdTransform2d":
            transform = transform_2d(
                float(self._constant(src, "rotation", 0.0)),
                self._constant(src, "scale", (1.0, 1.0)),
                self._constant(src, "translation", (0.0, 0.0)),
            )
            st, src = self._value(src, "in")
        varname = "st"
        if src is not None and _is_primvar_reader(src):
            name, _ = self._value(src, "varname")
            varname = str(name) if name else "st"
        return transform, varname

    # ------------------------------------------------------------------ MaterialX

    def _read_materialx(self, row: _MaterialRow, material: UsdShade.Material) -> None:
        """A material without a UsdPreviewSurface: its MaterialX surface mapped
        (``usd/materialx.py``; a notice only where the mapping leaves something out),
        else grey with a notice. Materials of other render contexts keep the default
        grey silently (the support report lists them)."""
        path = str(material.GetPath())
        kind, mapped = self.materialx_mapping(material)
        if mapped is None and not kind:  # no surface: a Material referencing a document's?
            prim = material.GetPrim()
            document = materialx.referenced_material(prim.GetStage(), prim.GetPath())
            if document is not None:
                self._read_document(row, document)
                return
        if mapped is None:
            out = material.GetSurfaceOutput("mtlx")
            if out and out.HasConnectedSource():
                self.materialx_paths["grey"].append(path)
                self.notices.append(
                    f"{path}: MaterialX surface {kind or '(unknown)'} is not read; rendered grey"
                )
            return
        self._apply_mapped(row, mapped, path, kind)

    def materialx_mapping(self, material: UsdShade.Material):
        """(kind, ``materialx.MappedSurface``) of a Material whose surface (its ``mtlx``
        output, else the universal one) is a MaterialX node the render maps; (the
        surface's id or "", None) otherwise."""
        shader = material.ComputeSurfaceSource("mtlx")[0]  # else the universal output
        ident = str(shader.GetIdAttr().Get() or "") if shader else ""
        kind = materialx.SURFACE_KINDS.get(ident)
        if kind is None:
            return ident, None
        inputs = self.materialx_inputs(shader)
        return kind, materialx.map_surface(kind, inputs, materialx.node_defaults(ident))

    def _read_document(self, row: _MaterialRow, material: materialx.DocumentMaterial):
        """A material of a ``.mtlx`` document (``materialx.DocumentMaterial``): its
        surface mapped, or grey with a notice when it is no surface the render maps."""
        kind, ident, inputs, defaults = materialx.document_surface(material)
        where = f"{material.path} ({PurePosixPath(material.document).name})"
        if not kind:
            self.materialx_paths["grey"].append(material.path)
            self.notices.append(
                f"{where}: MaterialX surface {ident or '(none)'} is not read; rendered grey"
                if material.document else f"{material.path}: no MaterialX material "
                f"{material.name} in the .mtlx documents referenced there; rendered grey"
            )  # fmt: skip
            return
        self._apply_mapped(row, materialx.map_surface(kind, inputs, defaults), where, kind)

    def materialx_inputs(self, shader: UsdShade.Shader) -> dict:
        """A MaterialX surface Shader's authored inputs as ``materialx.map_surface``
        takes them: values (connections to Material inputs followed), ``Image`` for a
        plain image node feeding one, else ``Unread``."""
        inputs = {}
        for inp in shader.GetInputs():
            name = inp.GetBaseName()
            value, src = self._value(shader, name)
            if src is not None:
                inputs[name] = self._materialx_image(src)
            elif value is not None:
                inputs[name] = value if isinstance(value, (str, bool)) else np.asarray(value)
        return inputs

    def _materialx_image(self, node: UsdShade.Shader):
        """A MaterialX node authored in USD as ``materialx.Image`` (``ND_image_*`` /
        ``ND_tiledimage_*``) or ``materialx.Unread``."""
        ident = str(node.GetIdAttr().Get() or "")
        parts = ident.split("_")
        if len(parts) < 3 or parts[1] not in materialx.IMAGE_CATEGORIES:
            return materialx.Unread(ident or str(node.GetPath()))
        file_value, _ = self._value(node, "file")
        inp = node.GetInput("file")
        scalar = parts[2] == "float"
        space = str(inp.GetAttr().GetColorSpace() or "") if inp else ""
        space = "raw" if scalar else materialx.COLOUR_SPACES.get(space, "auto")
        wrap = tuple(
            materialx.WRAP_MODES.get(str(self._value(node, a)[0] or "periodic"), "repeat")
            for a in ("uaddressmode", "vaddressmode")
        )
        transform = None
        if parts[1] == "tiledimage":
            transform = materialx.tiling_transform(
                self._constant(node, "uvtiling", (1.0, 1.0)),
                self._constant(node, "uvoffset", (0.0, 0.0)),
            )
        where = f"{node.GetPath()}.inputs:file"
        return materialx.Image(file_value, where, space, wrap, transform, scalar)

    def _apply_mapped(self, row: _MaterialRow, mapped, where: str, kind: str) -> None:
        """Fill ``row`` from a ``materialx.MappedSurface``: its constants (clamped as a
        UsdPreviewSurface's are), its images as textures; one notice naming what the
        mapping left out, if anything."""
        for name, value in mapped.constants.items():
            value = np.nan_to_num(np.asarray(value, np.float64)).reshape(-1)
            if name == "opacityThreshold":
                row.opacity_threshold = float(np.clip(value[0], 0.0, 1.0))
            elif name == "ior":
                row.ior = float(value[0]) if value[0] > 0.0 else 1.5
            elif name in BRDF_INPUTS:
                setattr(row, BRDF_INPUTS[name], float(np.clip(value[0], 0.0, 1.0)))
            else:
                self._set_constant(row, name, np.resize(value, 3 if value.size > 1 else 1))
        row.diffuse_authored = True
        row.glossy = True  # its roughness blurs its reflections, as a UsdPreviewSurface's
        for name, (image, scale, bias) in mapped.images.items():
            read = self._file(image.file, image.where, image.colour_space)
            if read is None:  # not found or not decoded: a problem line, the constant
                continue
            pixels, _ = read
            output = "r" if image.scalar or len(scale) == 1 else "rgb"
            channels = _OUTPUT_CHANNELS[output][min(max(pixels.shape[2], 1), 4)]
            if len(scale) == 3 and output == "r":
                channels = channels * 3
            spec = TextureInput(
                image=pixels,
                channels=tuple(int(c) for c in channels),
                scale=np.resize(scale, len(channels)).astype(np.float32),
                bias=np.resize(bias, len(channels)).astype(np.float32),
                wrap=image.wrap,
                transform=image.transform,
            )
            self._use(row, name, spec, "st")
        self.materialx_paths["mapped"].append(where)
        if mapped.dropped:
            self.notices.append(
                f"{where}: MaterialX {kind} mapped onto UsdPreviewSurface without "
                + "; ".join(mapped.dropped)
            )

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
            texture_inputs=[dict(r.inputs) for r in rows],
            opacity_threshold=np.array([r.opacity_threshold for r in rows], dtype=np.float32),
            specular_color=np.array([r.specular_color for r in rows], np.float32).reshape(-1, 3),
            use_specular_workflow=np.array([r.use_specular_workflow for r in rows], np.float32),
            clearcoat=np.array([r.clearcoat for r in rows], dtype=np.float32),
            clearcoat_roughness=np.array([r.clearcoat_roughness for r in rows], np.float32),
            occlusion=np.array([r.occlusion for r in rows], dtype=np.float32),
            glossy=np.array([r.glossy for r in rows], dtype=bool),
        )


def _is_primvar_reader(shader: UsdShade.Shader) -> bool:
    """A ``UsdPrimvarReader_*`` node (float, float2, float3, float4, int, ...)."""
    return str(shader.GetIdAttr().Get() or "").startswith("UsdPrimvarReader")


def colour_primvar(bank: MaterialBank, rows) -> str:
    """The primvar holding the colour of a gprim drawn with material ``rows``: the
    first row's ``UsdPrimvarReader`` ``varname`` (``_MaterialRow.colour_primvar``), else
    ``displayColor``."""
    if not bank.reads_colour_primvars:  # the common case: no per-mesh look-up
        return "displayColor"
    for row in np.unique(np.asarray(rows, np.int64)):
        name = bank.rows[int(row)].colour_primvar
        if name:
            return name
    return "displayColor"


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
