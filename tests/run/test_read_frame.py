"""RenderResult.read_frame on every product layout: the default frames/NNNN.exr, RenderProducts
of colour only, of AOVs in a multi-part file (a renamed channel included), of two files, a
PNG only and a product without vars; each plane read by what it holds, the same frame
whatever the layout."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdRender
from scenes import mirror_floor_stage, render_var

import phrt_usd
from phrt_usd.errors import PhrtError
from phrt_usd.run.images import srgb_oetf

#: A small frame: the layouts differ in files, not in pixels.
WIDTH, HEIGHT = 32, 24
#: Every plane the default layout holds (phrt_usd.run.products.DEFAULT_SOURCES).
DEFAULT_KEYS = {"beauty", "alpha", "depth", "element_id", "traced_mask"}
#: Every plane a var can hold.
ALL_KEYS = DEFAULT_KEYS | {"normal", "position", "albedo", "reflectivity"}
#: Half-float storage of a var against the float render it came from: relative rounding
#: of half's 11-bit significand (2**-11), doubled for the float -> half -> float trip.
HALF_RTOL = 2**-10

#: name → (sourceName, dataType, aov name or None)
VARS = {
    "color": ("color", "color3h", None),
    "colorf": ("color", "color3f", None),
    "depth": ("depth", "float", None),
    "id": ("primId", "int", None),
    "traced": ("phrt:traced", "int", None),
    "N": ("normal", "normal3h", "Nworld"),
    "P": ("position", "point3f", None),
    "albedo": ("albedo", "color3h", None),
    "F": ("phrt:reflectivity", "half", None),
}
#: layout → its products: (productName, var names, multipart)
LAYOUTS = {
    "colour-only": [("beauty.$F4.exr", ["color"], False)],
    "multipart-aovs": [
        ("aovs.$F4.exr", ["colorf", "depth", "id", "traced", "N", "P", "albedo", "F"], True)
    ],
    "two-files": [("beauty.$F4.exr", ["color"], False), ("data.$F4.exr", ["depth", "id"], False)],
    "png-only": [("preview.$F4.png", ["color"], False)],
    "no-vars": [("plain.####.exr", [], False)],
}
#: The planes each layout's files hold.
EXPECTED_KEYS = {
    "colour-only": {"beauty", "alpha"},
    "multipart-aovs": ALL_KEYS,
    "two-files": {"beauty", "alpha", "depth", "element_id"},
    "png-only": {"beauty"},
    "no-vars": DEFAULT_KEYS,
}


def _with_products(path, layout: str):
    """mirror_floor_stage at WIDTH x HEIGHT whose settings write ``layout``'s products."""
    mirror_floor_stage(path, WIDTH, HEIGHT)
    stage = Usd.Stage.Open(str(path))
    products = []
    for index, (name, var_names, multipart) in enumerate(LAYOUTS[layout]):
        product = UsdRender.Product.Define(stage, f"/Render/Products/P{index}")
        product.CreateProductNameAttr(name)
        targets = []
        for var_name in var_names:
            targets.append(render_var(stage, var_name, *VARS[var_name]))
        if targets:
            product.CreateOrderedVarsRel().SetTargets(targets)
        if multipart:
            product.GetPrim().CreateAttribute(
                "driver:parameters:OpenEXR:multipart", Sdf.ValueTypeNames.Bool
            ).Set(True)
        products.append(product.GetPath())
    settings = UsdRender.Settings.Get(stage, "/Render/Settings")
    settings.CreateProductsRel().SetTargets(products)
    stage.GetRootLayer().Save()
    return path


@pytest.fixture(scope="module")
def default_frame(tmp_path_factory):
    """The frame in the default layout, all reflectors traced (no time budget)."""
    path = mirror_floor_stage(tmp_path_factory.mktemp("default") / "shot.usda", WIDTH, HEIGHT)
    with phrt_usd.render(path, budget_ms=math.inf) as result:
        frame = result.read_frame()
    return frame


@pytest.mark.slow
@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_read_frame_reads_every_product_layout(layout, default_frame, tmp_path):
    stage = _with_products(tmp_path / "shot.usda", layout)
    with phrt_usd.render(stage, budget_ms=math.inf) as result:
        assert result.summary["mean_selected"] == 1  # the mirror traced, as by default
        frame = result.read_frame(1)
    assert set(frame) == EXPECTED_KEYS[layout]
    beauty = frame["beauty"]
    assert beauty.shape == (HEIGHT, WIDTH, 3) and beauty.dtype == np.float32
    if layout == "png-only":
        # The 8-bit preview decoded: the frame within half a step of 255, compared encoded,
        # against the default layout's half-float beauty: plus its rounding (2**-11
        # relative) through the encoding's slope (x d oetf / dx <= 1.055 / 2.4 x^(1/2.4)
        # <= 0.44): 2.2e-4.
        gap = np.abs(srgb_oetf(beauty) - srgb_oetf(default_frame["beauty"])).max()
        assert gap <= 0.5 / 255 + 0.44 * 2**-11
    else:
        np.testing.assert_allclose(beauty, default_frame["beauty"], rtol=HALF_RTOL, atol=1e-6)
    for key in EXPECTED_KEYS[layout] & DEFAULT_KEYS - {"beauty"}:
        np.testing.assert_allclose(frame[key], default_frame[key], rtol=HALF_RTOL, err_msg=key)
        assert frame[key].dtype == default_frame[key].dtype, key
    if layout == "multipart-aovs":
        covered = frame["element_id"] >= 0
        lengths = np.linalg.norm(frame["normal"][covered], axis=-1)
        np.testing.assert_allclose(lengths, 1.0, atol=2e-3)  # unit normals, half-rounded
        floor = frame["reflectivity"] == 1.0  # the mirror floor, F = 1
        assert floor.any() and frame["traced_mask"][floor].all()
        # World positions (metres) of the floor lie in its plane y = 0.
        np.testing.assert_allclose(frame["position"][floor][:, 1], 0.0, atol=1e-4)
        assert frame["albedo"].shape == (HEIGHT, WIDTH, 3)


@pytest.mark.slow
def test_read_frame_names_a_missing_file(tmp_path):
    stage = _with_products(tmp_path / "shot.usda", "colour-only")
    with phrt_usd.render(stage, budget_ms=math.inf) as result:
        (result.out / "beauty.0001.exr").unlink()
        with pytest.raises(PhrtError, match=r"frame 1: .*beauty\.0001\.exr: no such image file"):
            result.read_frame()
