"""Colour of a blackbody radiator: UsdLux ``inputs:colorTemperature`` as linear Rec.709.

UsdLux (``LightAPI.inputs:colorTemperature``): the colour is "calculated as an RGB
color using a D65 white point ... normalized such that the default value of 6500 will
always result in white"; the renderer multiplies it into ``inputs:color``. Computed
here from physics, vectorised over temperatures:

1. Planck's law, spectral radiance ``B(λ, T) = 2hc² / λ⁵ / (exp(hc / (λ k T)) - 1)``,
   sampled every ``WAVELENGTH_STEP_NM`` over ``WAVELENGTHS_NM``.
2. CIE 1931 2° colour matching functions by the multi-lobe Gaussian fit of Wyman,
   Sloan and Shirley, "Simple Analytic Approximations to the CIE XYZ Color Matching
   Functions", JCGT 2(2), 2013 (their eq. 2, coefficients in ``_CMF_LOBES``; within
   the CIE tables' own rounding for rendering purposes) → XYZ.
3. XYZ → linear Rec.709 / sRGB primaries, D65 white (IEC 61966-2-1, ``XYZ_TO_REC709``).
4. Divided per channel by the 6500 K colour (so 6500 K is exactly white, as UsdLux
   says), then by its Rec.709 luminance (``REC709_LUMINANCE``), so that changing the
   temperature changes the hue, not the brightness.

USD's own ``UsdLuxBlackbodyTemperatureAsRgb`` interpolates a table and normalises the
luminance only: its 6500 K is (1.04, 0.98, 1.03); ours is (1, 1, 1), the schema's text.
"""

from __future__ import annotations

import numpy as np

#: Temperatures UsdLux calls valid ("from 1000 to 10000"); others are clamped to it.
TEMPERATURE_RANGE_K = (1000.0, 10000.0)
#: The temperature that is white (UsdLux: "the default value of 6500 will always result
#: in white").
WHITE_TEMPERATURE_K = 6500.0
#: Visible range of the CIE 1931 tables (nm) and the integration step (1 nm: the tables'
#: own spacing; the integrands are smooth, so the sum is converged far below 1e-4).
WAVELENGTHS_NM = (360.0, 830.0)
WAVELENGTH_STEP_NM = 1.0

#: Planck's constant (J s), the speed of light (m/s), Boltzmann's constant (J/K): CODATA.
_H, _C, _K = 6.62607015e-34, 2.99792458e8, 1.380649e-23

#: Wyman, Sloan, Shirley 2013 multi-lobe fit: per XYZ component, lobes of
#: (weight, mean nm, sigma below the mean, sigma above the mean).
_CMF_LOBES = (
    ((1.056, 599.8, 37.9, 31.0), (0.362, 442.0, 16.0, 26.7), (-0.065, 501.1, 20.4, 26.2)),
    ((0.821, 568.8, 46.9, 40.5), (0.286, 530.9, 16.3, 31.1)),
    ((1.217, 437.0, 11.8, 36.0), (0.681, 459.0, 26.0, 13.8)),
)

#: XYZ → linear Rec.709 (sRGB primaries, D65 white), IEC 61966-2-1.
XYZ_TO_REC709 = np.array(
    [
        [3.2404542, -1.5371385, -0.4985314],
        [-0.9692660, 1.8760108, 0.0415560],
        [0.0556434, -0.2040259, 1.0572252],
    ]
)
#: Rec.709 luminance weights (ITU-R BT.709).
REC709_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def _cmf(wavelengths_nm: np.ndarray) -> np.ndarray:
    """(3, n) CIE 1931 x̄, ȳ, z̄ at ``wavelengths_nm`` (n,) (the fit of ``_CMF_LOBES``)."""
    rows = []
    for lobes in _CMF_LOBES:
        total = np.zeros_like(wavelengths_nm)
        for weight, mean, below, above in lobes:
            sigma = np.where(wavelengths_nm < mean, below, above)
            total += weight * np.exp(-0.5 * ((wavelengths_nm - mean) / sigma) ** 2)
        rows.append(total)
    return np.stack(rows)


def blackbody_xyz(temperature_k: np.ndarray) -> np.ndarray:
    """(n, 3) CIE XYZ of blackbodies at ``temperature_k`` (n,) kelvin (> 0), scaled so
    that Y = 1 (only the chromaticity is meaningful)."""
    t = np.asarray(temperature_k, dtype=np.float64).reshape(-1)
    lam_nm = np.arange(WAVELENGTHS_NM[0], WAVELENGTHS_NM[1] + 0.5, WAVELENGTH_STEP_NM)
    lam = lam_nm * 1e-9
    # exp overflows only far below 1000 K in the visible range; expm1 keeps it exact.
    exponent = np.minimum(_H * _C / (lam[None, :] * _K * t[:, None]), 700.0)
    radiance = 1.0 / (lam[None, :] ** 5 * np.expm1(exponent))  # 2hc² cancels
    xyz = radiance @ _cmf(lam_nm).T  # (n, 3)
    return xyz / xyz[:, 1:2]


def _raw_rec709(temperature_k: np.ndarray) -> np.ndarray:
    return blackbody_xyz(temperature_k) @ XYZ_TO_REC709.T


_WHITE = _raw_rec709(np.array([WHITE_TEMPERATURE_K]))[0]


def blackbody_rec709(temperature_k: np.ndarray | float) -> np.ndarray:
    """(n, 3) float64 linear Rec.709 colour of ``temperature_k`` (n,) or a scalar (then
    (3,)): 6500 K is (1, 1, 1), every colour has Rec.709 luminance 1, channels >= 0.
    Temperatures are clamped to ``TEMPERATURE_RANGE_K`` (non-finite ones read 6500 K)."""
    scalar = np.ndim(temperature_k) == 0
    t = np.asarray(temperature_k, dtype=np.float64).reshape(-1)
    t = np.clip(np.where(np.isfinite(t), t, WHITE_TEMPERATURE_K), *TEMPERATURE_RANGE_K)
    # Low temperatures lie outside the Rec.709 gamut (blue < 0): clipped to the gamut.
    rgb = np.maximum(_raw_rec709(t) / _WHITE, 0.0)
    rgb /= (rgb @ REC709_LUMINANCE)[:, None]
    return rgb[0] if scalar else rgb
