"""UsdPreviewSurface as the shading reads it: a point's inputs turned into the columns of
its *surface* (the specification's workflow rule), and the table of the GGX lobe's
directional albedo that the BRDF's energy terms read.

The BRDF (``engine/shade_kernels.brdf_cos``, and in GLSL ``engine/raster/shaders/
cube_lookup.frag``'s ``brdf_cos``: keep the two in step, ``tests/engine/
test_preview_surface.py`` ties them together) is, per light direction l and direction to
the eye v about the shading normal n, with h the half vector and s = (1 - v·h)^5::

    f = coat + t(v) t(l) (f_diffuse + f_specular)
    f_specular = F D V,           F = F0 + (F90 - F0) s                  (Schlick)
    D = a² / (π ((n·h)² (a² - 1) + 1)²)                                 (GGX, a = roughness²)
    V = 1 / (2 (n·l sqrt((n·v)² (1 - a²) + a²) + n·v sqrt((n·l)² (1 - a²) + a²)))
                                                    (Smith, height-correlated: G / (4 n·l n·v))
    f_diffuse = diffuse / π (1 - E(v)) (1 - E(l)) / (1 - E_avg)        (per channel)
    coat = clearcoat Fc D_c V_c,  Fc = Fc0 + (1 - Fc0) s, white; t(x) = 1 - clearcoat Ec(x)

E(μ) = F0 A(μ, r) + F90 B(μ, r) is the specular lobe's directional albedo (split sum:
``specular_albedo_table``), E_avg its cosine-weighted mean over the hemisphere, Ec the
clear coat's. The diffuse lobe takes exactly the energy the specular lobe leaves
(Kelemen and Szirmay-Kalos 2001; Kulla and Conty 2017), so the BRDF is reciprocal (every
factor is symmetric in l and v) and its albedo ``E(v) + diffuse (1 - E(v))`` is at most 1
for inputs in [0, 1]; the clear coat's layer takes its own albedo out of the base on the
way in and out (t(v) t(l)). Storm's ``previewSurface.glslfx`` weights its diffuse by
1 - F(v·h) and adds the clear coat on top, which gains energy at grazing angles.

The workflow rule (the specification's words): metallic workflow F0 = lerp(R², albedo,
metallic), F90 = lerp(1, albedo, metallic), R = (1 - ior) / (1 + ior), and the diffuse
colour is albedo (1 - metallic); specular workflow F0 = specularColor, F90 = 1, the
diffuse colour is diffuseColor. The clear coat's Fc0 is R² of the same ior.

Light (the renderer's convention, ``engine/shading``): a light of radiance E leaves
``π f (n·l) E`` towards the eye, so a white Lambert surface facing a unit DistantLight
shows 1. The environment's mean radiance (the ambient) leaves ``occlusion × (E(v)_total +
diffuse (1 - E(v)) ...)`` (``ambient_weight``), the specular part only where the
mirror reflection does not stand in for it (reflectors: ``reflection_weight``).

Plain numpy; no USD, OpenGL or numba here.
"""

from __future__ import annotations

import functools

import numpy as np

from phrt_usd.model.scene import MaterialTable

#: The columns of a point's surface row (``surface_columns``), float32 (n, SURFACE_COLUMNS):
#: diffuse colour (3, after the workflow), F0 (3), F90 (3), roughness, clear coat amount,
#: clear coat roughness, clear coat F0, occlusion, specular ambient (1: the ambient's
#: specular part is shaded; 0: a reflection stands in for it), and one spare column (0),
#: so that a row is four RGBA texels on the GPU.
DIFFUSE, F0, F90 = 0, 3, 6
ROUGHNESS, CLEARCOAT, CLEARCOAT_ROUGHNESS, CLEARCOAT_F0, OCCLUSION, SPECULAR_AMBIENT = (
    9, 10, 11, 12, 13, 14,
)  # fmt: skip
SURFACE_COLUMNS = 16

#: Smallest roughness the lobes are evaluated at. At roughness 0 GGX is a delta that a
#: point light would show as one infinitely bright texel; 0.045 (a = 0.002) is Filament's
#: floor, the smallest lobe whose D stays finite in float32 half-vector arithmetic. The
#: albedo table's roughness 0 is evaluated there too.
MIN_ROUGHNESS = 0.045

#: Smallest n·v the BRDF takes (grazing view directions, the silhouette's pixels).
MIN_COSINE = 1e-4

#: UsdPreviewSurface's fallbacks of the inputs the BRDF reads.
FALLBACK_METALLIC = 0.0
FALLBACK_ROUGHNESS = 0.5
FALLBACK_IOR = 1.5
FALLBACK_CLEARCOAT = 0.0
FALLBACK_CLEARCOAT_ROUGHNESS = 0.01
FALLBACK_OCCLUSION = 1.0
FALLBACK_SPECULAR_COLOR = (0.0, 0.0, 0.0)

#: The albedo table's size: TABLE_ROUGHNESS rows (roughness i / (rows - 1)) of
#: TABLE_COSINES columns (n·v = j / (columns - 1), at least MIN_COSINE), plus a column of
#: the rows' cosine-weighted means; each cell TABLE_SAMPLES importance samples of the
#: lobe (a Hammersley set). 32 x 32 cells interpolated bilinearly stay within 0.5 % of
#: the integral (``tests/engine/test_preview_surface.py`` checks it at cell centres).
TABLE_ROUGHNESS = 32
TABLE_COSINES = 32
TABLE_SAMPLES = 256


def _hammersley(count: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points of the 2D Hammersley set in [0, 1)²."""
    i = np.arange(count, dtype=np.uint32)
    bits = i.copy()
    bits = ((bits << 16) | (bits >> 16)) & 0xFFFFFFFF
    bits = ((bits & 0x55555555) << 1) | ((bits & 0xAAAAAAAA) >> 1)
    bits = ((bits & 0x33333333) << 2) | ((bits & 0xCCCCCCCC) >> 2)
    bits = ((bits & 0x0F0F0F0F) << 4) | ((bits & 0xF0F0F0F0) >> 4)
    bits = ((bits & 0x00FF00FF) << 8) | ((bits & 0xFF00FF00) >> 8)
    return (i + 0.5) / count, bits.astype(np.float64) / 2.0**32


def visible_normal_draws(alpha: float, mu: np.ndarray, samples: int):
    """(v·h, n·l) (c, samples) float64: the GGX lobe of ``alpha``'s visible normals h
    drawn on a Hammersley set of ``samples`` (Heitz 2018) for views v at n·v = ``mu``
    (c, 1) in the x-z plane, v·h clamped to [0, 1], l = v reflected about h."""
    u1, u2 = _hammersley(samples)
    # The view direction in the x-z plane, stretched to the unit-roughness frame.
    vx, vz = np.sqrt(np.maximum(1.0 - mu * mu, 0.0)), mu
    sx, sz = alpha * vx, vz
    length = np.sqrt(sx * sx + sz * sz)
    sx, sz = sx / length, sz / length
    # T1 = (0, 1, 0) (v has no y), T2 = Vh x T1 = (-sz, 0, sx).
    rad, phi = np.sqrt(u1), 2.0 * np.pi * u2
    t1, t2 = rad * np.cos(phi), rad * np.sin(phi)
    blend = 0.5 * (1.0 + sz)
    t2 = (1.0 - blend) * np.sqrt(np.maximum(1.0 - t1 * t1, 0.0)) + blend * t2
    up = np.sqrt(np.maximum(1.0 - t1 * t1 - t2 * t2, 0.0))
    nx, ny, nz = -t2 * sz + up * sx, t1 + 0.0 * sx, t2 * sx + up * sz
    hx, hy, hz = alpha * nx, alpha * ny, np.maximum(nz, 0.0)
    norm = np.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hz = hx / norm, hz / norm
    vh = np.clip(vx * hx + vz * hz, 0.0, 1.0)
    return vh, 2.0 * vh * hz - vz


def smith_lambda(c: np.ndarray, a2: float) -> np.ndarray:
    """Smith's Λ of GGX (alpha² ``a2``) at cosine ``c`` (floored at 1e-12)."""
    c = np.maximum(c, 1e-12)
    return 0.5 * (np.sqrt(1.0 + a2 * (1.0 - c * c) / (c * c)) - 1.0)


def lobe_albedo(roughness: float, cosine: np.ndarray, samples: int = TABLE_SAMPLES):
    """(A, B) (c,) float64 at one ``roughness`` and ``cosine`` (c,) values of n·v: the
    GGX lobe's directional albedo is ``F0 A + F90 B`` (Schlick's F split, the BRDF of
    the module). Integrated over the lobe's visible normals (Heitz 2018: each sample
    weighs G2 / G1(v), at most 1), on a Hammersley set."""
    alpha = max(float(roughness), MIN_ROUGHNESS) ** 2
    a2 = alpha * alpha
    mu = np.maximum(np.asarray(cosine, np.float64), MIN_COSINE)[:, None]
    vh, nl = visible_normal_draws(alpha, mu, samples)
    lam_v = smith_lambda(mu, a2)
    weight = np.where(nl > 0.0, (1.0 + lam_v) / (1.0 + lam_v + smith_lambda(nl, a2)), 0.0)
    s5 = (1.0 - vh) ** 5
    return (weight * (1.0 - s5)).mean(-1), (weight * s5).mean(-1)


@functools.cache
def specular_albedo_table() -> np.ndarray:
    """(TABLE_ROUGHNESS, TABLE_COSINES + 1, 2) float32: (A, B) of ``lobe_albedo`` at
    roughness i / (rows - 1) (row i) and n·v j / (columns - 1) (column j < TABLE_COSINES);
    the last column holds each row's cosine-weighted means 2 ∫ (A, B)(μ) μ dμ (over
    midpoints of 4 TABLE_COSINES cosines). Computed once a process."""
    mu = np.linspace(0.0, 1.0, TABLE_COSINES)
    fine = (np.arange(4 * TABLE_COSINES) + 0.5) / (4 * TABLE_COSINES)
    table = np.empty((TABLE_ROUGHNESS, TABLE_COSINES + 1, 2))
    for i, rough in enumerate(np.linspace(0.0, 1.0, TABLE_ROUGHNESS)):
        a, b = lobe_albedo(rough, mu)
        table[i, :TABLE_COSINES, 0], table[i, :TABLE_COSINES, 1] = a, b
        fa, fb = lobe_albedo(rough, fine)
        table[i, TABLE_COSINES] = 2.0 * (fa * fine).mean(), 2.0 * (fb * fine).mean()
    return np.ascontiguousarray(table, np.float32)


def ior_reflectance(ior) -> np.ndarray:
    """R² = ((1 - ior) / (1 + ior))², the specification's F0 of a dielectric of ``ior``
    (a non-positive or non-finite ior reads the fallback 1.5)."""
    ior = np.asarray(ior, np.float64)
    ior = np.where(np.isfinite(ior) & (ior > 0.0), ior, FALLBACK_IOR)
    return ((1.0 - ior) / (1.0 + ior)) ** 2


def surface_columns(
    albedo,
    metallic,
    use_specular,
    specular_color,
    roughness,
    clearcoat,
    clearcoat_roughness,
    ior,
    occlusion,
    specular_ambient,
) -> np.ndarray:
    """(n, SURFACE_COLUMNS) float32 rows of n points from their UsdPreviewSurface inputs:
    albedo (n, 3) (diffuseColor), metallic, use_specular (useSpecularWorkflow != 0),
    specular_color (n, 3), roughness, clearcoat, clearcoat_roughness, ior, occlusion and
    specular_ambient (n,) each (or scalars): the workflow rule of the module, every input
    clamped to its range ([0, 1]; colours >= 0 and F0, F90 <= 1)."""
    albedo = np.clip(np.nan_to_num(np.asarray(albedo, np.float64)).reshape(-1, 3), 0.0, None)
    n = len(albedo)

    def col(x) -> np.ndarray:
        return np.broadcast_to(np.nan_to_num(np.asarray(x, np.float64)), (n,))[:, None]

    m = np.clip(col(metallic), 0.0, 1.0)
    spec = col(use_specular) != 0.0
    r2 = ior_reflectance(np.broadcast_to(np.asarray(ior, np.float64), (n,)))[:, None]
    colour = np.clip(albedo, 0.0, 1.0)
    specular = np.clip(np.broadcast_to(np.asarray(specular_color, np.float64), (n, 3)), 0, 1)
    out = np.zeros((n, SURFACE_COLUMNS), np.float32)
    out[:, DIFFUSE : DIFFUSE + 3] = np.where(spec, albedo, albedo * (1.0 - m))
    out[:, F0 : F0 + 3] = np.where(spec, specular, r2 + (colour - r2) * m)
    out[:, F90 : F90 + 3] = np.where(spec, 1.0, 1.0 + (colour - 1.0) * m)
    out[:, ROUGHNESS] = np.clip(col(roughness), 0.0, 1.0)[:, 0]
    out[:, CLEARCOAT] = np.clip(col(clearcoat), 0.0, 1.0)[:, 0]
    out[:, CLEARCOAT_ROUGHNESS] = np.clip(col(clearcoat_roughness), 0.0, 1.0)[:, 0]
    out[:, CLEARCOAT_F0] = r2[:, 0]
    out[:, OCCLUSION] = np.clip(col(occlusion), 0.0, 1.0)[:, 0]
    out[:, SPECULAR_AMBIENT] = np.clip(col(specular_ambient), 0.0, 1.0)[:, 0]
    return out


def fallback_surface(albedo, specular_ambient=1.0) -> np.ndarray:
    """``surface_columns`` of points whose only input is ``albedo`` (n, 3): every other
    input at UsdPreviewSurface's fallback."""
    return surface_columns(
        albedo, FALLBACK_METALLIC, 0, FALLBACK_SPECULAR_COLOR, FALLBACK_ROUGHNESS,
        FALLBACK_CLEARCOAT, FALLBACK_CLEARCOAT_ROUGHNESS, FALLBACK_IOR, FALLBACK_OCCLUSION,
        specular_ambient,
    )  # fmt: skip


#: The inputs a point reads besides its albedo: name -> (MaterialTable field, fallback,
#: components). Every one may be textured (``MaterialTable.texture_inputs``).
INPUTS = {
    "metallic": ("metallic", FALLBACK_METALLIC, 1),
    "useSpecularWorkflow": ("use_specular_workflow", 0.0, 1),
    "specularColor": ("specular_color", FALLBACK_SPECULAR_COLOR, 3),
    "roughness": ("roughness", FALLBACK_ROUGHNESS, 1),
    "clearcoat": ("clearcoat", FALLBACK_CLEARCOAT, 1),
    "clearcoatRoughness": ("clearcoat_roughness", FALLBACK_CLEARCOAT_ROUGHNESS, 1),
    "ior": ("ior", FALLBACK_IOR, 1),
    "occlusion": ("occlusion", FALLBACK_OCCLUSION, 1),
}


def material_inputs(materials: MaterialTable, name: str) -> np.ndarray:
    """(M, k) float32 constants of input ``name`` (``INPUTS``) per row of ``materials``
    (M = its rows; a table without the field, or shorter, reads the fallback)."""
    field, fallback, k = INPUTS[name]
    rows = len(materials.opacity)
    out = np.empty((rows, k), np.float32)
    out[:] = np.asarray(fallback, np.float32).reshape(1, -1)
    value = np.asarray(getattr(materials, field, np.zeros(0)), np.float32).reshape(-1, k)
    m = min(len(value), rows)
    out[:m] = value[:m]
    return out


def textured_inputs(materials: MaterialTable) -> bool:
    """Some row of ``materials`` has one of ``INPUTS`` textured."""
    return any(name in inputs for inputs in materials.texture_inputs for name in INPUTS)


#: The columns of a material's inputs as ``shade_kernels.surface_rows`` takes them
#: (``input_rows``): metallic, useSpecularWorkflow, specularColor (3), roughness,
#: clearcoat, clearcoatRoughness, R² of its ior, occlusion, two spare (0).
INPUT_COLUMNS = 12


def input_rows(materials: MaterialTable) -> np.ndarray:
    """(M, INPUT_COLUMNS) float32: each row's constant inputs (``INPUT_COLUMNS``)."""
    rows = len(materials.opacity)
    out = np.zeros((rows, INPUT_COLUMNS), np.float32)
    out[:, 0:1] = np.clip(material_inputs(materials, "metallic"), 0.0, 1.0)
    out[:, 1:2] = material_inputs(materials, "useSpecularWorkflow") != 0.0
    out[:, 2:5] = np.clip(material_inputs(materials, "specularColor"), 0.0, 1.0)
    out[:, 5:6] = np.clip(material_inputs(materials, "roughness"), 0.0, 1.0)
    out[:, 6:7] = np.clip(material_inputs(materials, "clearcoat"), 0.0, 1.0)
    out[:, 7:8] = np.clip(material_inputs(materials, "clearcoatRoughness"), 0.0, 1.0)
    out[:, 8:9] = ior_reflectance(material_inputs(materials, "ior"))
    out[:, 9:10] = np.clip(material_inputs(materials, "occlusion"), 0.0, 1.0)
    return np.nan_to_num(out)


def textured_input_rows(materials, constant, tri, weights, tri_material, corner_uv):
    """(m, INPUT_COLUMNS) float32 inputs of points on triangles ``tri`` (m,) with
    barycentric ``weights`` (m, 3): ``constant`` (``input_rows``) of their materials,
    the textured inputs sampled (``model.surface.input_values``)."""
    from phrt_usd.model.surface import input_values

    mats = np.clip(np.take(tri_material, tri), 0, len(constant) - 1)
    out = np.take(constant, mats, axis=0)
    columns = {"metallic": (0, 1), "useSpecularWorkflow": (1, 1), "specularColor": (2, 3),
               "roughness": (5, 1), "clearcoat": (6, 1), "clearcoatRoughness": (7, 1),
               "ior": (8, 1), "occlusion": (9, 1)}  # fmt: skip
    for name, (at, k) in columns.items():
        if not any(name in inputs for inputs in materials.texture_inputs):
            continue
        value = input_values(
            materials, name, material_inputs(materials, name), tri, weights, tri_material,
            corner_uv,
        )  # fmt: skip
        if name == "ior":
            value = ior_reflectance(value)
        elif name == "useSpecularWorkflow":
            value = value != 0.0
        else:
            value = np.clip(value, 0.0, 1.0)
        out[:, at : at + k] = value[:, :k]
    return np.ascontiguousarray(np.nan_to_num(out), np.float32)


def mean_reflection(surface: np.ndarray) -> np.ndarray:
    """(n, 3) float64: the mirror reflection's weight (``shade_kernels.
    reflection_weight``) of surface rows (n, SURFACE_COLUMNS) averaged over the
    hemisphere of view directions (cosine-weighted): the clear coat's mean albedo plus
    the base's under it, from the albedo table's means. What a view-independent weight
    of the reflection can be (the tracer's deeper bounces)."""
    s = np.asarray(surface, np.float64)
    table = specular_albedo_table().astype(np.float64)

    def mean(rough: np.ndarray) -> np.ndarray:
        y = np.clip(np.maximum(rough, MIN_ROUGHNESS), 0.0, 1.0) * (TABLE_ROUGHNESS - 1)
        y0 = np.minimum(y.astype(np.int64), TABLE_ROUGHNESS - 2)
        fy = (y - y0)[:, None]
        return table[y0, TABLE_COSINES] * (1.0 - fy) + table[y0 + 1, TABLE_COSINES] * fy

    base, coat = mean(s[:, ROUGHNESS]), mean(s[:, CLEARCOAT_ROUGHNESS])
    c, fc0 = s[:, CLEARCOAT, None], s[:, CLEARCOAT_F0, None]
    coat_albedo = c * np.minimum(fc0 * coat[:, :1] + coat[:, 1:], 1.0)
    lobe = np.minimum(s[:, F0 : F0 + 3] * base[:, :1] + s[:, F90 : F90 + 3] * base[:, 1:], 1.0)
    return coat_albedo + (1.0 - coat_albedo) ** 2 * lobe
