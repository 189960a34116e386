"""MaterialX surfaces read as UsdPreviewSurface: ``standard_surface`` and
``open_pbr_surface`` (and MaterialX's own ``UsdPreviewSurface`` node) mapped onto the
inputs of the one BRDF the render shades (``model/preview_surface.py``).

A stage carries them in two ways:

- **A ``.mtlx`` document referenced (or payloaded) by a prim**, as DCCs and the
  StandardShaderBall do (``@plastic.mtlx@</MaterialX/Materials>``). usd-core has no
  usdMtlx file-format plugin, so USD cannot compose the arc: the prim stays empty and a
  binding to a material under it targets a prim that does not exist.
  ``referenced_material`` finds such a binding's document: the nearest ancestor of the
  target whose prim specs reference or payload ``.mtlx`` files (each asset path anchored
  to the layer that authors it and resolved through ``pxr.Ar``), and the target's path
  below it read as usdMtlx lays a document out (``/MaterialX/Materials/<material>``).
  The document is read with the ``materialx`` package (never written), once per
  resolved path; ``readable_document`` tells the composition report which missing
  ``.mtlx`` arcs the render reads anyway.
- **MaterialX nodes authored in USD**: a UsdShade Shader whose ``info:id`` is one of
  ``SURFACE_KINDS`` on the Material's ``mtlx`` (or universal) surface output, its inputs
  authored in USD; ``usd/materials.py`` collects them.

Either way an input's value is a constant, an ``Image`` (a plain ``image`` /
``tiledimage`` node feeding it, directly or through a node graph's output) or an
``Unread`` node; ``map_surface`` turns the inputs (unauthored ones at the node
definition's default, from MaterialX's standard library) into UsdPreviewSurface inputs.
The mapping follows MaterialX's own translation graph ``standard_surface_to_
UsdPreviewSurface`` (open_pbr_surface's inputs renamed as its ``open_pbr_to_standard_
surface`` graph does), with ``specular`` / ``specular_color`` and ``transmission`` added:

UsdPreviewSurface input <- standard_surface (open_pbr_surface's name where it differs):

- diffuseColor <- ((base * base_color * (1 - subsurface) + subsurface * subsurface_color)
  * (1 - transmission) + transmission * transmission_color) * lerp(1, coat_color, coat)
  (base_weight, subsurface_weight, transmission_weight, coat_weight): the coat's colour
  tints what is under it; a transmissive surface's colour is its transmission colour
  (what shows where the render draws glass opaque: surfaces it does not trace; where it
  refracts, opacity 0 gives the diffuse no weight);
- metallic <- metalness (base_metalness); roughness <- specular_roughness;
  ior <- specular_IOR (specular_ior);
- useSpecularWorkflow = 1 and specularColor <- specular * specular_color * R²(ior)
  (specular_weight) where the surface is not metallic and the specular weight or colour
  is not 1: the weight and colour scale F0; else the metallic workflow (F0 = R²(ior));
- clearcoat <- coat (coat_weight); clearcoatRoughness <- coat_roughness;
- opacity <- mean(opacity) * (1 - transmission) (geometry_opacity, transmission_weight):
  transmission is the render's glass (opacity < 1 refracts by the ior);
- emissiveColor <- emission * emission_color * the coat's tint (open_pbr's
  emission_luminance read as the weight, as MaterialX's translation graph reads it).

Approximations, each named in the one notice of a material (``MappedSurface.dropped``)
where the surface authors it: a metal's ``specular_color`` (its edge tint: F90 is the
base colour, as UsdPreviewSurface's metallic workflow has it) and ``specular`` weight
on a metal; ``coat_IOR`` (the coat's Fresnel uses ``specular_IOR``);
``transmission_color`` (refracted light is untinted: the colour is only the diffuse
one); ``subsurface`` (its colour is diffuse, no scattering); and every other input
authored away from its default (``diffuse_roughness``, sheen / fuzz, thin film,
anisotropy, normals, ...). An image on an input the table does not texture, or a node
other than a plain image, gives the input's default and a notice.

``MaterialX`` is imported on first use only (a stage without MaterialX pays nothing).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import PurePosixPath

import numpy as np
from pxr import Ar, Sdf, Usd

#: The file extension of a MaterialX document.
DOCUMENT_EXTENSION = ".mtlx"

#: MaterialX surface shader node definitions the render maps -> the mapping used.
SURFACE_KINDS = {
    "ND_standard_surface_surfaceshader": "standard_surface",
    "ND_standard_surface_surfaceshader_100": "standard_surface",
    "ND_open_pbr_surface_surfaceshader": "open_pbr_surface",
    "ND_UsdPreviewSurface_surfaceshader": "UsdPreviewSurface",
}
#: MaterialX node categories read as a texture file (``file``, address modes, tiling).
IMAGE_CATEGORIES = ("image", "tiledimage")

#: open_pbr_surface's names of standard_surface's inputs (``open_pbr_to_standard_surface``).
OPEN_PBR_NAMES = {
    "base": "base_weight", "base_color": "base_color", "metalness": "base_metalness",
    "specular": "specular_weight", "specular_color": "specular_color",
    "specular_roughness": "specular_roughness", "specular_IOR": "specular_ior",
    "coat": "coat_weight", "coat_color": "coat_color", "coat_roughness": "coat_roughness",
    "coat_IOR": "coat_ior", "transmission": "transmission_weight",
    "transmission_color": "transmission_color", "subsurface": "subsurface_weight",
    "subsurface_color": "subsurface_color", "emission": "emission_luminance",
    "emission_color": "emission_color", "opacity": "geometry_opacity",
}  # fmt: skip
#: The inputs ``map_surface`` reads (standard_surface's names).
MAPPED_INPUTS = tuple(OPEN_PBR_NAMES)
#: Mapped inputs an image may feed -> the UsdPreviewSurface input it textures.
TEXTURED = {
    "base_color": "diffuseColor", "metalness": "metallic", "specular_roughness": "roughness",
    "coat": "clearcoat", "coat_roughness": "clearcoatRoughness",
    "emission_color": "emissiveColor",
}  # fmt: skip
#: UsdPreviewSurface inputs MaterialX's ``UsdPreviewSurface`` node passes on as they are
#: (its images on the texturable ones but ``normal``).
PREVIEW_INPUTS = (
    "diffuseColor", "emissiveColor", "useSpecularWorkflow", "specularColor", "metallic",
    "roughness", "clearcoat", "clearcoatRoughness", "opacity", "opacityThreshold", "ior",
    "occlusion",
)  # fmt: skip
#: MaterialX address modes -> UsdUVTexture wrap modes (MaterialX's default: periodic).
WRAP_MODES = {"periodic": "repeat", "clamp": "clamp", "mirror": "mirror", "constant": "black"}
#: MaterialX colour spaces of an image's ``file`` -> ``textures.read_texture``'s.
COLOUR_SPACES = {"srgb_texture": "sRGB", "lin_rec709": "raw", "lin_srgb": "raw", "raw": "raw"}
#: Two values closer than this count as equal (a default authored again, 1 vs 1.0001).
SAME = 1e-4


@dataclass(frozen=True)
class Image:
    """A plain MaterialX image node feeding an input.

    file        : the file (an ``Sdf.AssetPath`` of a USD input, or a document's file
                  resolved against the document)
    where       : the node, for messages
    colour_space: ``textures.read_texture``'s (``sRGB``, ``raw``, ``auto``)
    wrap        : (u, v) UsdUVTexture wrap modes
    transform   : (2, 3) affine st -> st' (``tiledimage``'s ``uvtiling`` / ``uvoffset``)
                  or None
    scalar      : a float image (its first channel)
    """

    file: object
    where: str
    colour_space: str
    wrap: tuple[str, str]
    transform: np.ndarray | None = None
    scalar: bool = False


@dataclass(frozen=True)
class Unread:
    """A node feeding an input that the render does not run (its category or id)."""

    node: str


@dataclass
class MappedSurface:
    """UsdPreviewSurface inputs of a MaterialX surface (``map_surface``).

    constants : input name -> value (float64 array; every mapped input)
    images    : input name -> (``Image``, scale (k,), bias (k,)): the input textured,
                ``value = texel * scale + bias``
    dropped   : what the mapping leaves out (input names with why), for the notice
    """

    constants: dict[str, np.ndarray] = field(default_factory=dict)
    images: dict[str, tuple[Image, np.ndarray, np.ndarray]] = field(default_factory=dict)
    dropped: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class DocumentMaterial:
    """A material of a ``.mtlx`` document a binding targets through an arc USD could not
    compose: ``path`` the binding's target (the USD path usdMtlx would have made),
    ``document`` the resolved file ("" when no document the prim references defines
    it), ``name`` the material's name in it."""

    path: str
    document: str
    name: str


# --- the mapping -------------------------------------------------------------------------


def _same(a, b) -> bool:
    """Two input values are equal (numbers within ``SAME``; others as they compare)."""
    try:
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    except (TypeError, ValueError):
        return bool(a == b)
    return a.shape == b.shape and bool(np.all(np.abs(a - b) <= SAME))


def _reflectance(ior: float) -> float:
    """R² = ((1 - ior) / (1 + ior))², the F0 of a dielectric of ``ior``."""
    return ((1.0 - ior) / (1.0 + ior)) ** 2 if ior > 0.0 else 0.04


def map_surface(kind: str, inputs: dict, defaults: dict) -> MappedSurface:
    """UsdPreviewSurface inputs of a MaterialX surface of ``kind`` (``SURFACE_KINDS``'s
    values) from its authored ``inputs`` (name -> value, ``Image`` or ``Unread``) and
    its node definition's ``defaults`` (name -> value): the table of the module."""
    if kind == "UsdPreviewSurface":
        return _map_preview(inputs, defaults)
    names = OPEN_PBR_NAMES if kind == "open_pbr_surface" else {n: n for n in OPEN_PBR_NAMES}
    out = MappedSurface()
    value: dict[str, np.ndarray] = {}
    images: dict[str, Image] = {}
    for name in MAPPED_INPUTS:
        src = names[name]
        given = inputs.get(src)
        default = np.asarray(defaults.get(src, 0.0), np.float64)
        if isinstance(given, Image) and name in TEXTURED:
            images[name] = given
        elif isinstance(given, (Image, Unread)):
            node = given.node if isinstance(given, Unread) else "image"
            out.dropped.append(f"{src} (fed by {node}: its default used)")
        elif given is not None:
            default = np.nan_to_num(np.asarray(given, np.float64))
        value[name] = default
    for src, given in inputs.items():  # authored inputs the table does not read
        if src in names.values():
            continue
        if isinstance(given, (Image, Unread)) or not _same(given, defaults.get(src, given)):
            out.dropped.append(src)

    def scalar(name: str, lo: float = 0.0, hi: float = 1.0) -> float:
        return float(np.clip(value[name].reshape(-1)[0], lo, hi))

    def colour(name: str) -> np.ndarray:
        return np.clip(np.resize(value[name].reshape(-1), 3), 0.0, None)

    base, subsurface, coat = scalar("base"), scalar("subsurface"), scalar("coat")
    transmission = scalar("transmission")
    tint = 1.0 + (np.clip(colour("coat_color"), 0.0, 1.0) - 1.0) * coat  # the coat's colour
    # What is not the base's own colour: subsurface's, then transmission's (see the module).
    under = (subsurface * colour("subsurface_color") * (1.0 - transmission)
             + transmission * colour("transmission_color")) * tint  # fmt: skip
    base_scale = base * (1.0 - subsurface) * (1.0 - transmission) * tint
    metallic = scalar("metalness")
    ior = scalar("specular_IOR", 0.0, np.inf) or 1.5
    emission = max(float(value["emission"].reshape(-1)[0]), 0.0)
    c = out.constants
    c["diffuseColor"] = base_scale * colour("base_color") + under
    c["metallic"] = np.float64(metallic)
    c["roughness"] = np.float64(scalar("specular_roughness"))
    c["ior"] = np.float64(ior)
    c["clearcoat"] = np.float64(coat)
    c["clearcoatRoughness"] = np.float64(scalar("coat_roughness"))
    c["emissiveColor"] = emission * colour("emission_color") * tint
    c["opacity"] = np.float64(float(np.mean(np.clip(value["opacity"], 0.0, 1.0)))
                              * (1.0 - transmission))  # fmt: skip
    weight, tone = scalar("specular", 0.0, np.inf), np.clip(colour("specular_color"), 0, 1)
    plain = _same(weight, 1.0) and _same(tone, np.ones(3))
    metal = metallic > 0.0 or "metalness" in images
    if not plain and not metal:  # the weight and colour scale F0: the specular workflow
        c["useSpecularWorkflow"] = np.float64(1.0)
        c["specularColor"] = np.clip(weight * tone * _reflectance(ior), 0.0, 1.0)
    elif not plain:
        out.dropped.append(f"{names['specular_color']} / {names['specular']} on a metal "
                           "(its edge tint: F90 is the base colour)")  # fmt: skip
    if coat > 0.0 and not _same(value["coat_IOR"], ior):
        out.dropped.append(f"{names['coat_IOR']} (the coat's Fresnel uses the base's ior)")
    if transmission > 0.0 and not _same(colour("transmission_color"), np.ones(3)):
        out.dropped.append(f"{names['transmission_color']} (refracted light is untinted; "
                           "the colour is the diffuse one)")  # fmt: skip
    if subsurface > 0.0:
        out.dropped.append(f"{names['subsurface']} (its colour as diffuse, no scattering)")
    for name, image in images.items():
        target = TEXTURED[name]
        if name == "base_color":
            scale, bias = base_scale, under
        elif name == "emission_color":
            scale, bias = emission * tint, np.zeros(3)
        else:
            scale, bias = np.ones(1), np.zeros(1)
        out.images[target] = (image, np.asarray(scale, np.float64), np.asarray(bias, np.float64))
    return out


def _map_preview(inputs: dict, defaults: dict) -> MappedSurface:
    """MaterialX's ``UsdPreviewSurface`` node: its inputs are UsdPreviewSurface's."""
    out = MappedSurface()
    for name in PREVIEW_INPUTS:
        given = inputs.get(name)
        default = np.nan_to_num(np.asarray(defaults.get(name, 0.0), np.float64))
        if isinstance(given, Image) and name not in ("useSpecularWorkflow", "opacityThreshold"):
            k = 3 if name in ("diffuseColor", "emissiveColor", "specularColor") else 1
            out.images[name] = (given, np.ones(k), np.zeros(k))
        elif isinstance(given, (Image, Unread)):
            node = given.node if isinstance(given, Unread) else "image"
            out.dropped.append(f"{name} (fed by {node}: its default used)")
        elif given is not None:
            default = np.nan_to_num(np.asarray(given, np.float64))
        out.constants[name] = default
    for name, given in inputs.items():
        if name not in PREVIEW_INPUTS and (
            isinstance(given, (Image, Unread)) or not _same(given, defaults.get(name, given))
        ):
            out.dropped.append(name)
    return out


# --- MaterialX documents -----------------------------------------------------------------


@functools.cache
def _library():
    """MaterialX's standard data library (node definitions and their defaults), loaded
    once a process."""
    import MaterialX as mx

    lib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), lib)
    return lib


def defines_node(node_def: str) -> bool:
    """MaterialX's standard library defines node definition ``node_def`` (an
    ``info:id`` such as ``ND_image_color3``)."""
    return _library().getNodeDef(node_def) is not None


def node_defaults(node_def: str) -> dict:
    """Input name -> default value (float or tuple) of MaterialX node definition
    ``node_def`` (empty when the library has no such definition)."""
    nd = _library().getNodeDef(node_def)
    return {} if nd is None else {i.getName(): _plain(i.getValue()) for i in nd.getActiveInputs()}


def _plain(value):
    """A MaterialX value as a float, tuple or str (None stays None)."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return tuple(value.asTuple()) if hasattr(value, "asTuple") else value


@functools.lru_cache(maxsize=64)
def read_document(path: str):
    """(document, "") of the ``.mtlx`` file at resolved ``path``, read with MaterialX
    and given the standard library; (None, why) when it cannot be read."""
    import MaterialX as mx

    doc = mx.createDocument()
    try:
        mx.readFromXmlFile(doc, path)
    except Exception as exc:  # MaterialX raises its own exception types
        return None, " ".join(str(exc).split()) or type(exc).__name__
    doc.setDataLibrary(_library())
    return doc, ""


def resolve_asset(layer: Sdf.Layer, asset: str) -> str:
    """The resolved path of ``asset`` as ``layer`` authors it (anchored to the layer),
    "" when nothing resolves."""
    anchored = layer.ComputeAbsolutePath(asset) if layer else asset
    return str(Ar.GetResolver().Resolve(anchored) or "")


def readable_document(asset: str) -> bool:
    """``asset`` (a path as USD's composition errors name it) is a ``.mtlx`` document
    that exists and MaterialX reads: the render reads its materials itself."""
    path = asset.split(":SDF_FORMAT_ARGS:")[0]
    if not path.lower().endswith(DOCUMENT_EXTENSION):
        return False
    resolved = str(Ar.GetResolver().Resolve(path) or "")
    return bool(resolved) and read_document(resolved)[0] is not None


def _document_arcs(prim: Usd.Prim) -> list[tuple[str, Sdf.Path]]:
    """(resolved document or "", the arc's prim path) of each ``.mtlx`` reference and
    payload the prim's specs author (variants included)."""
    arcs = []
    for spec in prim.GetPrimStack():
        for items in (spec.referenceList, spec.payloadList):
            for arc in items.GetAddedOrExplicitItems():
                if str(arc.assetPath).lower().endswith(DOCUMENT_EXTENSION):
                    arcs.append((resolve_asset(spec.layer, arc.assetPath), arc.primPath))
    return arcs


def _material_name(arc_path: Sdf.Path, below: Sdf.Path) -> str:
    """The material a path ``below`` an arc to ``arc_path`` of a document names, as
    usdMtlx lays a document out (``/MaterialX/Materials/<name>``), "" if none."""
    root = arc_path if not arc_path.isEmpty else Sdf.Path("/MaterialX")
    path = root if below == Sdf.Path(".") else root.AppendPath(below)
    parts = path.pathString.strip("/").split("/")
    return parts[2] if len(parts) == 3 and parts[:2] == ["MaterialX", "Materials"] else ""


def referenced_material(stage: Usd.Stage, target: Sdf.Path) -> DocumentMaterial | None:
    """The document material a binding to ``target`` means when ``target`` lies under a
    prim whose ``.mtlx`` arc USD could not compose (module doc); None otherwise."""
    path = Sdf.Path(target)
    while path != Sdf.Path.absoluteRootPath and not path.isEmpty:
        prim = stage.GetPrimAtPath(path)
        arcs = _document_arcs(prim) if prim else []
        missing = ""
        for document, arc_path in arcs:
            name = _material_name(arc_path, Sdf.Path(target).MakeRelativePath(path))
            doc = read_document(document)[0] if document and name else None
            if doc is not None and _material_node(doc, name) is not None:
                return DocumentMaterial(str(target), document, name)
            missing = missing or (name if doc is not None else "")
        if arcs:  # a material the readable documents do not define: "" as its document
            return DocumentMaterial(str(target), "", missing) if missing else None
        path = path.GetParentPath()
    return None


def _material_node(doc, name: str):
    """The ``surfacematerial`` node ``name`` of a document (None when there is none)."""
    node = doc.getNode(name)
    return node if node is not None and node.getType() == "material" else None


def document_surface(material: DocumentMaterial):
    """(kind or "", the surface's node definition name, inputs, defaults) of a document
    material's surface shader: inputs as ``map_surface`` takes them."""
    import MaterialX as mx

    doc = read_document(material.document)[0] if material.document else None
    node = _material_node(doc, material.name) if doc is not None else None
    shaders = mx.getShaderNodes(node) if node is not None else []
    if not shaders:
        return "", "", {}, {}
    shader = shaders[0]
    nd = shader.getNodeDef()
    nd_name = nd.getName() if nd is not None else shader.getCategory()
    kind = SURFACE_KINDS.get(nd_name, "")
    inputs = {}
    for inp in shader.getInputs():
        upstream = inp.getConnectedNode()
        if upstream is not None:
            inputs[inp.getName()] = _document_image(upstream, material.document)
        elif inp.getValue() is not None:
            inputs[inp.getName()] = _plain(inp.getValue())
    return kind, nd_name, inputs, node_defaults(nd_name)


def _document_image(node, document: str) -> Image | Unread:
    """An upstream node of a document as ``Image`` (a plain image node, its file
    resolved against the document) or ``Unread``."""
    if node.getCategory() not in IMAGE_CATEGORIES or node.getInput("file") is None:
        return Unread(node.getCategory())
    file_input = node.getInput("file")
    name = file_input.getResolvedValueString()
    if not name:
        return Unread(f"{node.getCategory()} without a file")
    anchored = Ar.GetResolver().CreateIdentifier(name, Ar.ResolvedPath(document))
    resolved = str(Ar.GetResolver().Resolve(anchored) or "") or anchored
    scalar = node.getType() == "float"
    space = "raw" if scalar else COLOUR_SPACES.get(file_input.getActiveColorSpace(), "auto")
    wrap = tuple(
        WRAP_MODES.get(str(node.getInputValue(a) or "periodic"), "repeat")
        for a in ("uaddressmode", "vaddressmode")
    )
    transform = None
    if node.getCategory() == "tiledimage":
        tiling = _plain(node.getInputValue("uvtiling")) or (1.0, 1.0)
        offset = _plain(node.getInputValue("uvoffset")) or (0.0, 0.0)
        transform = tiling_transform(tiling, offset)
    where = f"{PurePosixPath(document).name}: {node.getNamePath()}.file"
    return Image(resolved, where, space, wrap, transform, scalar)


def tiling_transform(tiling, offset) -> np.ndarray | None:
    """(2, 3) affine st -> st * tiling - offset of a ``tiledimage``; None for identity."""
    t = np.asarray(tiling, np.float64).reshape(2)
    o = np.asarray(offset, np.float64).reshape(2)
    if np.array_equal(t, [1.0, 1.0]) and not o.any():
        return None
    return np.array([[t[0], 0.0, -o[0]], [0.0, t[1], -o[1]]])
