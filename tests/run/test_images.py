"""Frame EXR / preview PNG writing: exact round trips, strictness, atomic replacement."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from phrt_usd.errors import PhrtError
from phrt_usd.run.images import (
    DEPTH_BACKGROUND,
    HALF_MAX,
    ID_BACKGROUND,
    MAX_EXACT_ID,
    read_frame_exr,
    read_preview_png,
    srgb_oetf,
    tonemap_ldr,
    write_frame_exr,
    write_preview_png,
)
from phrt_usd.run.run_files import frame_image_paths, frame_name

H, W = 24, 32


def _frame(seed: int = 0, height: int = H, width: int = W) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    element_id = rng.integers(-1, 5000, (height, width)).astype(np.int32)
    element_id[0, :3] = [-1, MAX_EXACT_ID, MAX_EXACT_ID - 1]  # extremes must survive
    depth = rng.uniform(0.01, 1e4, (height, width)).astype(np.float32)
    depth[element_id == -1] = np.inf
    return {
        "beauty": rng.uniform(0.0, 20.0, (height, width, 3)).astype(np.float32),
        "alpha": (element_id >= 0).astype(np.float32),
        "depth": depth,
        "element_id": element_id,
        "traced_mask": rng.random((height, width)) < 0.3,
    }


def _write(path: Path, frame: dict[str, np.ndarray]) -> None:
    write_frame_exr(
        path,
        frame["beauty"],
        frame["alpha"],
        frame["depth"],
        frame["element_id"],
        frame["traced_mask"],
    )


def test_exr_round_trip_is_exact_for_ids_depth_and_mask(tmp_path: Path) -> None:
    frame = _frame()
    path = tmp_path / "frames" / "0001.exr"
    _write(path, frame)
    back = read_frame_exr(path)
    np.testing.assert_array_equal(back["element_id"], frame["element_id"])
    assert back["element_id"].dtype == np.int32
    np.testing.assert_array_equal(back["traced_mask"], frame["traced_mask"])
    np.testing.assert_array_equal(back["depth"], frame["depth"])  # float32 Z, inf restored
    assert np.isinf(back["depth"][frame["element_id"] == -1]).all()
    np.testing.assert_array_equal(back["alpha"], frame["alpha"])
    # RGB is half: 11 significant bits → relative error ≤ 2**-11.
    np.testing.assert_allclose(back["beauty"], frame["beauty"], rtol=2.0**-11, atol=1e-6)


def test_exr_stores_finite_depth_for_background(tmp_path: Path) -> None:
    import OpenImageIO as oiio

    frame = _frame()
    path = tmp_path / "f.exr"
    _write(path, frame)
    image = oiio.ImageInput.open(str(path))
    names = list(image.spec().channelnames)
    raw = image.read_image(oiio.FLOAT)
    image.close()
    z = raw[..., names.index("Z")]
    assert np.isfinite(raw).all(), "no NaN/Inf may be stored in the file"
    assert (z[frame["element_id"] == -1] == np.float32(DEPTH_BACKGROUND)).all()


def test_exr_clamps_radiance_beyond_half_range(tmp_path: Path) -> None:
    frame = _frame()
    frame["beauty"][0, 0] = [1e9, HALF_MAX * 2, 3.0]
    path = tmp_path / "f.exr"
    _write(path, frame)
    back = read_frame_exr(path)["beauty"]
    assert np.isfinite(back).all()
    np.testing.assert_array_equal(back[0, 0, :2], [HALF_MAX, HALF_MAX])


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_beauty_raises_and_writes_nothing(tmp_path: Path, bad: float) -> None:
    frame = _frame()
    frame["beauty"][3, 4, 1] = bad
    with pytest.raises(PhrtError, match="row 3, column 4"):
        _write(tmp_path / "f.exr", frame)
    with pytest.raises(PhrtError):
        write_preview_png(tmp_path / "f.png", frame["beauty"])
    assert os.listdir(tmp_path) == []


def test_nan_depth_and_huge_ids_raise(tmp_path: Path) -> None:
    frame = _frame()
    frame["depth"][1, 1] = np.nan
    with pytest.raises(PhrtError, match="depth"):
        _write(tmp_path / "f.exr", frame)
    frame = _frame()
    frame["element_id"][2, 2] = MAX_EXACT_ID + 1
    with pytest.raises(PhrtError, match="element id"):
        _write(tmp_path / "f.exr", frame)


def test_exr_rejects_mismatched_shapes(tmp_path: Path) -> None:
    frame = _frame()
    frame["depth"] = frame["depth"][:-1]
    with pytest.raises(PhrtError, match="depth"):
        _write(tmp_path / "f.exr", frame)


def test_existing_files_are_replaced_whole_and_no_temp_files_remain(tmp_path: Path) -> None:
    exr, png = tmp_path / "0007.exr", tmp_path / "0007.png"
    big = _frame(seed=1, height=64, width=80)
    _write(exr, big)
    write_preview_png(png, big["beauty"])
    small = _frame(seed=2, height=8, width=6)
    _write(exr, small)
    write_preview_png(png, small["beauty"])
    assert sorted(os.listdir(tmp_path)) == ["0007.exr", "0007.png"]
    np.testing.assert_array_equal(read_frame_exr(exr)["element_id"], small["element_id"])
    assert read_preview_png(png).shape == (8, 6, 3)
    # A failed write leaves the previous file intact.
    broken = _frame(seed=3, height=8, width=6)
    broken["beauty"][0, 0, 0] = np.nan
    with pytest.raises(PhrtError):
        _write(exr, broken)
    np.testing.assert_array_equal(read_frame_exr(exr)["element_id"], small["element_id"])
    assert sorted(os.listdir(tmp_path)) == ["0007.exr", "0007.png"]


def test_preview_png_is_the_tonemapped_beauty(tmp_path: Path) -> None:
    # linear 0, 0.5, 1, 7 (clamped), and a dark value on the linear toe of the sRGB curve
    values = np.array([0.0, 0.5, 1.0, 7.0, 0.002], dtype=np.float32)
    beauty = np.repeat(values[None, :, None], 3, axis=2)
    path = tmp_path / "p.png"
    write_preview_png(path, beauty)
    pixels = read_preview_png(path)[0, :, 0].astype(int)
    # sRGB(0.5) = 1.055 * 0.5**(1/2.4) - 0.055 = 0.7354 → 188; 0.002 * 12.92 * 255 = 6.6 → 7
    np.testing.assert_array_equal(pixels, [0, 188, 255, 255, 7])


def test_tonemap_ldr_range_and_monotonic_for_extreme_inputs() -> None:
    rgb = np.array([[[-1e30, 0.0, 1e-30], [0.25, 1.0, 1e30]]], dtype=np.float32)
    out = tonemap_ldr(rgb)
    assert out.dtype == np.float32 and out.shape == rgb.shape
    assert np.isfinite(out).all() and out.min() >= 0.0 and out.max() <= 1.0
    ramp = np.linspace(0.0, 2.0, 200, dtype=np.float32).reshape(1, -1, 1).repeat(3, axis=2)
    assert (np.diff(tonemap_ldr(ramp)[0, :, 0]) >= 0).all()
    # exposure +1 doubles the linear value before encoding
    np.testing.assert_allclose(tonemap_ldr(rgb[..., :1] * 0 + 0.25, exposure=1.0), srgb_oetf(0.5))


def test_srgb_oetf_is_continuous_at_the_knee() -> None:
    knee = np.float32(0.0031308)
    below, above = srgb_oetf(np.array([knee])), srgb_oetf(np.array([np.nextafter(knee, 1)]))
    assert abs(float(above[0] - below[0])) < 1e-5


def test_frame_names_and_paths() -> None:
    assert frame_name(12.0) == "0012"
    assert frame_name(12.0000000001) == "0012"
    assert frame_name(-3.0) == "-003"
    assert frame_name(12.5) == "0012.500"
    assert frame_name(1234567.0) == "1234567"
    exr, png = frame_image_paths(Path("/out"), 7.25)
    assert exr == Path("/out/frames/0007.250.exr") and png == Path("/out/frames/0007.250.png")
    with pytest.raises(PhrtError):
        frame_name(float("nan"))


def test_fractional_frame_exr_round_trip(tmp_path: Path) -> None:
    exr, _ = frame_image_paths(tmp_path, 3.5)
    frame = _frame(seed=4)
    _write(exr, frame)
    assert sorted(os.listdir(exr.parent)) == ["0003.500.exr"]
    np.testing.assert_array_equal(read_frame_exr(exr)["element_id"], frame["element_id"])


def test_write_exr_stores_uint_ids_and_header_attributes_exactly(tmp_path: Path) -> None:
    from fractions import Fraction

    from phrt_usd.run.images import read_exr, read_manifest, write_exr

    ids = np.array([[0, 1, 2**24], [2**32 - 2, ID_BACKGROUND, 7]], dtype=np.uint32)
    matrix = np.arange(16, dtype=np.float32).reshape(4, 4)
    header = {
        "worldToCamera": matrix.T,  # not C-contiguous: written as the matrix it shows
        "framesPerSecond": Fraction(24000, 1001),
        "phrt/timeCode": np.array([1.0 / 3.0]),
        "phrt/stage": "/a/b.usda",
    }
    path = tmp_path / "ids.exr"
    write_exr(path, {"": {"id": ids}}, header, {0: "/A", 7: "/B"})
    back, channels = read_exr(path)
    assert channels["id"].dtype == np.uint32
    np.testing.assert_array_equal(channels["id"], ids)
    np.testing.assert_array_equal(back["worldToCamera"], matrix.T)
    assert back["framesPerSecond"] == Fraction(24000, 1001)
    assert back["phrt/timeCode"][0] == 1.0 / 3.0  # a double, not a float
    assert back["phrt/stage"] == "/a/b.usda"
    assert read_manifest(back) == {0: "/A", 7: "/B"}
    assert "capDate" not in back


def test_write_exr_parts_and_same_bytes_twice(tmp_path: Path) -> None:
    import OpenEXR

    from phrt_usd.run.images import read_exr, write_exr

    rgb = np.full((4, 5), 0.5, dtype=np.float16)
    z = np.full((4, 5), 2.0, dtype=np.float32)
    write_exr(tmp_path / "a.exr", {"rgba": {"R": rgb}, "depth": {"Z": z}})
    write_exr(tmp_path / "b.exr", {"rgba": {"R": rgb}, "depth": {"Z": z}})
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()
    parts = OpenEXR.File(str(tmp_path / "a.exr"), header_only=True).parts
    assert [p.name() for p in parts] == ["rgba", "depth"]
    assert set(read_exr(tmp_path / "a.exr")[1]) == {"R", "Z"}
    with pytest.raises(PhrtError, match="one \\(H, W\\) size"):
        write_exr(tmp_path / "c.exr", {"": {"R": rgb, "Z": z[:-1]}})


def test_frame_ids_are_uint_and_older_float_ids_still_read(tmp_path: Path) -> None:
    from phrt_usd.run.images import read_exr, write_exr

    frame = _frame(seed=5)
    _write(tmp_path / "new.exr", frame)
    _, channels = read_exr(tmp_path / "new.exr")
    assert channels["id"].dtype == np.uint32
    assert (channels["id"][frame["element_id"] == -1] == ID_BACKGROUND).all()
    # A frame of an earlier phrt: id as float, -1 for background.
    old = {name: channels[name] for name in ("R", "G", "B", "A", "Z", "traced")}
    old["id"] = frame["element_id"].astype(np.float32)
    write_exr(tmp_path / "old.exr", {"": old})
    np.testing.assert_array_equal(
        read_frame_exr(tmp_path / "old.exr")["element_id"], frame["element_id"]
    )
