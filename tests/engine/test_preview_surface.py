"""UsdPreviewSurface's BRDF as the shading evaluates it (``shade_kernels.brdf_cos``,
``model/preview_surface.py``): energy (white furnace), reciprocity, the albedo table, and
the GLSL copy of the light pass against the compiled one at analytic inputs."""

from __future__ import annotations

import numpy as np
import pytest

from phrt_usd import kernels
from phrt_usd.engine import shading
from phrt_usd.model import preview_surface as ps

_SHADE = kernels.load("phrt_usd.engine.shade_kernels")
_N = np.array([0.0, 0.0, 1.0])


def _surface(albedo=1.0, metallic=0.0, roughness=0.5, clearcoat=0.0, coat_rough=0.01,
             specular=None, ior=1.5) -> np.ndarray:  # fmt: skip
    """One surface row of UsdPreviewSurface inputs (specular: the specular workflow's
    specularColor, else the metallic workflow)."""
    return ps.surface_columns(
        np.full((1, 3), albedo), metallic, specular is not None,
        np.full(3, 0.0 if specular is None else specular), roughness, clearcoat, coat_rough,
        ior, 1.0, 1.0,
    )  # fmt: skip


def _brdf_cos(surface: np.ndarray, to_eye: np.ndarray, to_light: np.ndarray) -> np.ndarray:
    """π f n·l (m, 3) of one surface row at m (eye, light) direction pairs, normal +z."""
    m = len(to_light)
    out = np.empty((m, 3))
    _SHADE.brdf_kernel(
        np.ascontiguousarray(np.repeat(surface, m, axis=0), np.float32),
        np.tile(_N, (m, 1)), np.ascontiguousarray(to_eye, np.float64),
        np.ascontiguousarray(to_light, np.float64), ps.specular_albedo_table(),
        ps.MIN_ROUGHNESS, out,
    )  # fmt: skip
    return out


def _ggx_pdf_sample(alpha: float, v: np.ndarray, u1, u2):
    """Directions l (k, 3) reflected about GGX-sampled half vectors (pdf D n·h) and their
    pdf over l, D n·h / (4 v·h)."""
    a2 = alpha * alpha
    cos_h = np.sqrt((1.0 - u1) / (1.0 + (a2 - 1.0) * u1))
    sin_h = np.sqrt(1.0 - cos_h**2)
    h = np.stack([sin_h * np.cos(2 * np.pi * u2), sin_h * np.sin(2 * np.pi * u2), cos_h], 1)
    vh = h @ v
    return 2.0 * vh[:, None] * h - v, h


def _pdf_ggx(alpha: float, v: np.ndarray, to_light: np.ndarray) -> np.ndarray:
    a2 = alpha * alpha
    h = to_light + v
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    nh, vh = h[:, 2], np.maximum(h @ v, 1e-12)
    d = a2 / (np.pi * (nh * nh * (a2 - 1.0) + 1.0) ** 2)
    return d * nh / (4.0 * vh)


def directional_albedo(surface: np.ndarray, cos_view: float, samples: int = 1 << 15):
    """(3,) ∫ f n·l dω of one surface row seen at n·v = ``cos_view``, by multiple
    importance sampling (balance heuristic) of the cosine and of both GGX lobes (base
    and clear coat roughness), stratified (a Hammersley set per strategy)."""
    v = np.array([np.sqrt(1.0 - cos_view**2), 0.0, cos_view])
    u1, u2 = ps._hammersley(samples)
    alphas = [max(float(surface[0, ps.ROUGHNESS]), ps.MIN_ROUGHNESS) ** 2,
              max(float(surface[0, ps.CLEARCOAT_ROUGHNESS]), ps.MIN_ROUGHNESS) ** 2]
    cosine = np.stack([np.sqrt(u1) * np.cos(2 * np.pi * u2), np.sqrt(u1) * np.sin(2 * np.pi * u2),
                       np.sqrt(1.0 - u1)], 1)  # fmt: skip
    directions = [cosine] + [_ggx_pdf_sample(a, v, u1, u2)[0] for a in alphas]
    lt = np.concatenate(directions)
    lt = lt[lt[:, 2] > 1e-9]
    pdf = (lt[:, 2] / np.pi + sum(_pdf_ggx(a, v, lt) for a in alphas)) / 3.0
    f_cos = _brdf_cos(surface, np.tile(v, (len(lt), 1)), lt) / np.pi
    return (f_cos / pdf[:, None]).sum(axis=0) / (3 * samples)


#: Materials of the furnace: (name, surface row).
FURNACE = [
    ("white dielectric, rough", _surface(1.0, 0.0, 1.0)),
    ("white dielectric, fallback roughness", _surface(1.0, 0.0, 0.5)),
    ("white dielectric, smooth", _surface(1.0, 0.0, 0.0)),
    ("white metal, rough", _surface(1.0, 1.0, 1.0)),
    ("half metal", _surface(0.8, 0.5, 0.3)),
    ("specular workflow, white specular over white", _surface(1.0, 0.0, 0.4, specular=1.0)),
    ("clear coat over white", _surface(1.0, 0.0, 0.6, clearcoat=1.0, coat_rough=0.1)),
    ("clear coat over white metal", _surface(1.0, 1.0, 0.3, clearcoat=1.0, coat_rough=0.0)),
    ("high ior", _surface(1.0, 0.0, 0.2, ior=3.0)),
]

#: The furnace's allowance over 1: the albedo table's error (``preview_surface``: its
#: bilinear cells within 0.5 % of the integral, which the diffuse lobe's normalisation
#: 1 / (1 - E_avg) reads) plus this estimator's noise (2^15 stratified samples a
#: strategy, below 0.1 %).
FURNACE_SLACK = 0.01


@pytest.mark.parametrize("name,surface", FURNACE, ids=[f[0] for f in FURNACE])
@pytest.mark.parametrize("cos_view", [0.05, 0.3, 0.7, 1.0])
def test_white_furnace_energy_at_most_one(name, surface, cos_view):
    """No input in [0, 1] returns more than it receives: ∫ f n·l dω <= 1 (a furnace of
    uniform unit radiance), for every material of FURNACE at grazing to normal view."""
    albedo = directional_albedo(surface, cos_view)
    assert np.all(albedo <= 1.0 + FURNACE_SLACK), (name, cos_view, albedo)


@pytest.mark.parametrize("cos_view", [0.2, 0.5, 1.0])
def test_white_furnace_white_metal_at_roughness_zero_returns_everything(cos_view):
    """A white metal at roughness 0 is a perfect mirror: the model claims it returns all
    of a uniform environment (``ambient_weight`` = 1), and the BRDF integrates to 1."""
    surface = _surface(1.0, 1.0, 0.0)
    albedo = directional_albedo(surface, cos_view)
    # GGX at the MIN_ROUGHNESS floor loses < 0.1 % to masking; FURNACE_SLACK as above.
    assert np.all(np.abs(albedo - 1.0) <= FURNACE_SLACK), albedo
    v = np.array([[np.sqrt(1.0 - cos_view**2), 0.0, cos_view]], np.float32)
    ambient, reflection = shading.surface_weights(surface, np.array([_N], np.float32), v)
    assert np.all(np.abs(ambient - 1.0) <= FURNACE_SLACK), ambient
    assert np.all(np.abs(reflection - 1.0) <= FURNACE_SLACK), reflection


@pytest.mark.parametrize("name,surface", FURNACE[:6], ids=[f[0] for f in FURNACE[:6]])
@pytest.mark.parametrize("cos_view", [0.1, 0.5, 1.0])
def test_ambient_weight_is_the_directional_albedo(name, surface, cos_view):
    """Without a clear coat the ambient term is exact for a uniform environment: its
    weight (``shade_kernels.ambient_weight``) is the BRDF's directional albedo, within
    the table's error and the estimator's noise (FURNACE_SLACK)."""
    v = np.array([[np.sqrt(1.0 - cos_view**2), 0.0, cos_view]], np.float32)
    ambient, _ = shading.surface_weights(surface, np.array([_N], np.float32), v)
    albedo = directional_albedo(surface, cos_view)
    assert np.allclose(ambient[0], albedo, atol=FURNACE_SLACK), (ambient, albedo)


def _directions(rng, k: int) -> np.ndarray:
    d = rng.normal(size=(k, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.05  # above the surface, not grazing below MIN_COSINE
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("name,surface", FURNACE, ids=[f[0] for f in FURNACE])
def test_brdf_is_reciprocal(name, surface):
    """f(l, v) = f(v, l) for 500 random direction pairs above the surface: every factor
    of the model is symmetric (``preview_surface``). The kernel returns π f n·l; divided
    by n·l both ways the two agree to float32 rounding of the surface row (1e-5 relative)."""
    rng = np.random.default_rng(7)
    v, lt = _directions(rng, 500), _directions(rng, 500)
    forward = _brdf_cos(surface, v, lt) / lt[:, 2:3]
    backward = _brdf_cos(surface, lt, v) / v[:, 2:3]
    assert np.allclose(forward, backward, rtol=1e-5, atol=1e-9)


def test_albedo_table_matches_the_integral():
    """The table's nodes within 0.5 % of a 16384-sample integral of the lobe (its
    stated accuracy: 256 visible-normal samples a node)."""
    table = ps.specular_albedo_table()
    for i in (0, 7, 16, 31):
        rough = i / (ps.TABLE_ROUGHNESS - 1)
        a, b = ps.lobe_albedo(rough, np.linspace(0.0, 1.0, ps.TABLE_COSINES), 16384)
        assert np.abs(table[i, : ps.TABLE_COSINES, 0] - a).max() < 0.005
        assert np.abs(table[i, : ps.TABLE_COSINES, 1] - b).max() < 0.005


def test_workflows_as_the_specification_says():
    """Metallic 1: F0 = F90 = albedo, no diffuse; metallic 0: F0 = ((1 - ior) / (1 +
    ior))², F90 = 1, the albedo diffuse; the specular workflow: F0 = specularColor,
    F90 = 1, diffuseColor diffuse."""
    albedo = np.array([[0.8, 0.5, 0.2]])
    metal = ps.surface_columns(albedo, 1.0, 0, np.zeros(3), 0.5, 0, 0.01, 1.5, 1, 1)[0]
    assert np.allclose(metal[ps.F0 : ps.F0 + 3], albedo[0])
    assert np.allclose(metal[ps.F90 : ps.F90 + 3], albedo[0])
    assert np.allclose(metal[ps.DIFFUSE : ps.DIFFUSE + 3], 0.0)
    plastic = ps.surface_columns(albedo, 0.0, 0, np.zeros(3), 0.5, 0, 0.01, 2.0, 1, 1)[0]
    assert np.allclose(plastic[ps.F0 : ps.F0 + 3], (1.0 / 3.0) ** 2)
    assert np.allclose(plastic[ps.F90 : ps.F90 + 3], 1.0)
    assert np.allclose(plastic[ps.DIFFUSE : ps.DIFFUSE + 3], albedo[0])
    spec = ps.surface_columns(albedo, 1.0, 1, np.array([0.1, 0.2, 0.3]), 0.5, 0, 0.01, 1.5,
                              1, 1)[0]  # fmt: skip
    assert np.allclose(spec[ps.F0 : ps.F0 + 3], [0.1, 0.2, 0.3])
    assert np.allclose(spec[ps.F90 : ps.F90 + 3], 1.0)
    assert np.allclose(spec[ps.DIFFUSE : ps.DIFFUSE + 3], albedo[0])
    # The compiled rule (shade_kernels.surface_rows) gives the same rows.
    table = np.zeros((1, ps.INPUT_COLUMNS), np.float32)
    table[0, 0], table[0, 5], table[0, 7], table[0, 8], table[0, 9] = 0.3, 0.5, 0.01, 0.04, 1
    out = np.empty((1, ps.SURFACE_COLUMNS), np.float32)
    _SHADE.surface_rows(albedo.astype(np.float32), np.zeros(1, np.int64), table, False,
                        np.zeros(0, np.float32), out)  # fmt: skip
    expected = ps.surface_columns(albedo, 0.3, 0, np.zeros(3), 0.5, 0, 0.01, 1.5, 1, 1)
    assert np.allclose(out, expected, atol=1e-6)
