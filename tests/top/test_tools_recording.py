"""tools/policy_replay.py recordings are plain data: exact round trip, refusal of anything else.

No rendering: the recordings are built here from FrameView / CameraFrame / TraceRecord
objects, the way ``_CapturePolicy`` keeps them.
"""

from __future__ import annotations

import gzip
import json
import math
import pickle
import struct
import sys
from dataclasses import fields, is_dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from repo_paths import TOOLS

from phrt_usd.model.frame import FrameView, TraceRecord
from phrt_usd.model.scene import CameraFrame, DistantLight, LocalLight

if str(TOOLS) not in sys.path:
    sys.path.insert(0, str(TOOLS))
import policy_replay as pr  # noqa: E402
import transition_bound as tb  # noqa: E402

#: Floats that a lossy text encoding would change (repr round-trips them all).
AWKWARD = [0.1 + 0.2, 1.0 / 3.0, 5e-324, 1.7976931348623157e308, -0.0, 2.0**-1074 * 3]


def camera(x: float, tweak: float = 0.0) -> CameraFrame:
    m = np.eye(4)
    m[:3, 3] = (x, 0.1 + 0.2, 1.0 / 3.0 + tweak)
    m[0, 1] = 1e-17  # a tiny off-diagonal term
    return CameraFrame(m, focal_length=50.0, horizontal_aperture=36.0, near=0.1, far=1e4)


def recording(n_frames: int = 8) -> dict:
    """A capture-like recording: element 0 a wall, 1..4 reflectors drifting in and out of
    view along the path, with records of every visible reflector."""
    n = 5
    reflectors = [1, 2, 3, 4]
    frames = []
    for f in range(n_frames):
        counts = np.array([5000, 400 + 90 * f, 900 - 60 * f, 0, 0], dtype=np.int64)
        if f % 3 == 1:
            counts[3] = 250 + 7 * f
        if f >= 4:
            counts[4] = 120 * f
        boxes = np.full((n, 4), np.nan)
        for e in np.flatnonzero(counts):
            boxes[e] = (10.0 * e, 5.0 + f, 10.0 * e + 30.5, 40.0 + 1.0 / 3.0)
        view = FrameView(
            time=521.0 + 2 * f + (0.1 + 0.2),
            camera=camera(0.25 * f, tweak=1e-13 * f),
            width=320,
            height=240,
            pixel_counts=counts,
            screen_boxes=None if f == 2 else boxes,
            upcoming_cameras=(camera(9.0),) if f == 5 else (),
        )
        elements = []
        for e in range(n):
            lo = np.array([2.0 * e - 0.5, -0.5 + 1e-3 * f, -6.0 - 1.0 / 3.0])
            hi = lo + np.array([1.0, 1.0 + AWKWARD[0], 1.0])
            elements.append(
                SimpleNamespace(
                    is_reflector=e in reflectors,
                    priority=(1.0 + e / 7.0) if e in reflectors else 0.0,
                    center=0.5 * (lo + hi),
                    bounds_min=lo,
                    bounds_max=hi,
                )
            )
        records = {}
        for e in reflectors:
            if counts[e] > 0:
                hits = {j: 3 * j + f for j in reflectors if j != e and (j + f) % 2}
                records[e] = TraceRecord(
                    source=e,
                    pixels=int(counts[e]),
                    rays=int(counts[e]) * (1 + e % 3) + len(hits),
                    hits=hits,
                    max_reflector_bounces=min(len(hits), 2),
                    mean_reflector_bounces=len(hits) / 3.0,
                    seconds=1e-6 * int(counts[e]) * (0.1 + 0.2),
                )
        frames.append(SimpleNamespace(view=view, elements=elements, records=records))
    return {
        "stage": "stages/synthetic.usda",
        "selection_weight": 1e-4 + 1e-20,
        "bounce_limit": 5,
        "lights": SimpleNamespace(
            distant=[
                DistantLight(
                    np.array([0.4055797876726388, 0.7071067811865476, 0.0]),
                    np.array([3.0, 2.849999964237213, 2.5500000715255737]),
                    0.5299999713897705,
                )
            ],
            local=[LocalLight(np.array([1.0, 2.0, -0.0]), np.array([AWKWARD[1]] * 3), 0.05)],
        ),
        "reflectors": reflectors,
        # Mirrors (every density's own share of pixels starting rays), one of them
        # with an awkward float: the figures read back bit for bit.
        "reflection_figures": (np.array([1.0, 1.0, 1.0, 1.0, 1.0 - 1e-16 * AWKWARD[0]]),
                               np.tile(np.arange(16, 0, -1) / 16.0, (5, 1))),
        "frames": frames,
    }


def assert_same(a, b, where: str = "recording") -> None:
    """Equal, with equal types, dtypes, shapes and float bits (NaN and -0.0 included)."""
    assert type(a) is type(b), f"{where}: {type(a).__name__} vs {type(b).__name__}"
    if isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, f"{where}: {a.dtype}{a.shape}"
        assert a.tobytes() == b.tobytes(), where
    elif isinstance(a, float):
        assert struct.pack("<d", a) == struct.pack("<d", b), f"{where}: {a!r} vs {b!r}"
    elif is_dataclass(a):
        for f in fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, SimpleNamespace):
        assert list(vars(a)) == list(vars(b)), where
        for k in vars(a):
            assert_same(getattr(a, k), getattr(b, k), f"{where}.{k}")
    elif isinstance(a, dict):
        assert list(a) == list(b), where
        for k in a:
            assert_same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    else:
        assert a == b, f"{where}: {a!r} vs {b!r}"


def through_json(data: dict) -> dict:
    return pr.decode_recording(json.loads(json.dumps(pr.encode_recording(data))))


def test_schema_covers_the_dataclasses() -> None:
    for cls, schema in pr._SCHEMAS.items():
        assert set(schema) == {f.name for f in fields(cls)}, cls.__name__


@pytest.mark.parametrize("name", ["rec.json", "rec.json.gz"])
def test_round_trip_is_exact(tmp_path: Path, name: str) -> None:
    data = recording()
    assert_same(data, through_json(data))
    path = tmp_path / name
    pr.save_recording(path, data)
    assert (path.read_bytes()[:2] == b"\x1f\x8b") == name.endswith(".gz")
    loaded = pr.load_recording(path)
    assert_same(data, loaded)
    # Spot checks of what assert_same compares bit for bit.
    cam = loaded["frames"][3].view.camera
    assert cam.world_from_camera.dtype == np.float64 and cam.world_from_camera.shape == (4, 4)
    assert cam.world_from_camera[1, 3] == 0.1 + 0.2
    assert loaded["frames"][0].view.pixel_counts.dtype == np.int64
    assert loaded["frames"][2].view.screen_boxes is None
    assert np.isnan(loaded["frames"][0].view.screen_boxes[3]).all()
    assert math.copysign(1.0, loaded["lights"].local[0].position[2]) == -1.0
    assert loaded["frames"][5].view.upcoming_cameras[0].world_from_camera[0, 3] == 9.0


def test_awkward_floats_round_trip_bit_for_bit() -> None:
    data = recording(2)
    values = np.array([*AWKWARD, math.nan, math.inf, -math.inf, 0.1, 1e-300, 123456.789e10])
    data["frames"][0].view.camera.world_from_camera[:] = np.resize(values, (4, 4))
    data["frames"][1].records[1].seconds = AWKWARD[3]
    data["frames"][1].records[1].mean_reflector_bounces = AWKWARD[2]
    data["selection_weight"] = AWKWARD[0]
    back = through_json(data)
    got = back["frames"][0].view.camera.world_from_camera
    assert got.tobytes() == data["frames"][0].view.camera.world_from_camera.tobytes()
    assert back["frames"][1].records[1].seconds == AWKWARD[3]
    assert back["frames"][1].records[1].mean_reflector_bounces == AWKWARD[2] != 0.0
    assert back["selection_weight"] == 0.1 + 0.2


@pytest.mark.parametrize("heuristic", ["heu1", "heu2", "all"])
@pytest.mark.parametrize("budget", [300, 1200, 100000])
def test_replay_of_the_file_equals_replay_in_memory(heuristic: str, budget: int) -> None:
    data = recording()
    back = through_json(data)
    for lookahead in (True, False):
        sel, vis = pr.replay(data, heuristic, budget, lookahead=lookahead)
        sel2, vis2 = pr.replay(back, heuristic, budget, lookahead=lookahead)
        assert np.array_equal(sel, sel2) and np.array_equal(vis, vis2)
        assert pr.transition_counts(sel, vis) == pr.transition_counts(sel2, vis2)
        assert pr.mean_rays(data, sel) == pr.mean_rays(back, sel2)
    # A budget that bites: a selection, not everything (HEU1 takes large reflectors at a
    # reduced density, so every visible one fits its 1200 rays; 300 do not).
    if budget == {"heu1": 300, "heu2": 1200}.get(heuristic):
        assert 0 < sel.sum() < vis.sum()


class _Planted:
    """Unpickling this creates ``marker`` (what a hostile recording would do instead)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (open, (str(self.marker), "w"))


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert err.endswith("\n") and err.count("\n") == 1, err
    assert "Traceback" not in err
    return err


@pytest.mark.parametrize("name", ["planted.json", "planted.json.gz", "planted.pkl"])
@pytest.mark.parametrize("compress", [False, True])
def test_a_pickle_is_refused_without_running_it(
    tmp_path: Path, capsys, name: str, compress: bool
) -> None:
    marker = tmp_path / "code-ran"
    payload = pickle.dumps({"format": pr.RECORDING_FORMAT, "version": 1, "x": _Planted(marker)})
    path = tmp_path / name
    path.write_bytes(gzip.compress(payload) if compress else payload)
    with pytest.raises(pr.RecordingError, match="not a replay recording") as info:
        pr.load_recording(path)
    assert "\n" not in str(info.value)
    assert pr.main(["replay", str(path), "--budgets", "1000"]) == 1
    assert str(path) in _one_line_error(capsys)
    assert tb.main([str(path), "--budgets", "1000"]) == 1
    _one_line_error(capsys)
    assert not marker.exists()
    # The payload is live: unpickling it (here, on purpose) does create the marker.
    pickle.loads(payload)["x"].close()
    assert marker.exists()


def _set(obj: dict, keys: list, value) -> dict:
    for k in keys[:-1]:
        obj = obj[k]
    obj[keys[-1]] = value
    return obj


def _drop(obj: dict, keys: list) -> None:
    for k in keys[:-1]:
        obj = obj[k]
    del obj[keys[-1]]


CAM = ["frames", 0, "view", "camera"]
REC = ["frames", 1, "records", 0]
MUTATIONS = {
    "wrong format": (lambda d: _set(d, ["format"], "phrt-checkpoint"), "format"),
    "no format": (lambda d: _drop(d, ["format"]), "no format"),
    "wrong version": (lambda d: _set(d, ["version"], 1), "version 1"),
    "version as text": (lambda d: _set(d, ["version"], "2"), "version"),
    "missing frames": (lambda d: _drop(d, ["frames"]), "frames"),
    "unknown field": (lambda d: _set(d, ["code"], "__import__('os')"), "code"),
    "missing camera field": (lambda d: _drop(d, [*CAM, "near"]), "near"),
    "camera as text": (lambda d: _set(d, CAM, "CameraFrame()"), "camera"),
    "float as text": (lambda d: _set(d, [*CAM, "far"], "1e4"), "far"),
    "bool for int": (lambda d: _set(d, [*REC, "rays"], True), "rays"),
    "float for int": (lambda d: _set(d, [*REC, "pixels"], 4.5), "pixels"),
    "hits not pairs": (lambda d: _set(d, [*REC, "hits"], {"2": 3}), "hits"),
    "object dtype": (lambda d: _set(d, [*CAM, "world_from_camera", "dtype"], "object"), "dtype"),
    "float32 dtype": (lambda d: _set(d, [*CAM, "world_from_camera", "dtype"], "float32"), "dtype"),
    "bad shape": (lambda d: _set(d, [*CAM, "world_from_camera", "shape"], [2, 8]), "shape"),
    "short data": (lambda d: _set(d, [*CAM, "world_from_camera", "data"], [1.0]), "data"),
    "text in data": (
        lambda d: d["frames"][0]["view"]["pixel_counts"]["data"].__setitem__(0, "9"),
        "pixel_counts",
    ),
    "float in int array": (
        lambda d: d["frames"][0]["view"]["pixel_counts"]["data"].__setitem__(0, 1.5),
        "pixel_counts",
    ),
    "int64 overflow": (
        lambda d: d["frames"][0]["view"]["pixel_counts"]["data"].__setitem__(0, 2**70),
        "pixel_counts",
    ),
    "lost record": (lambda d: d["frames"][1]["records"].pop(0), "no record of reflector"),
    "duplicate record": (
        lambda d: d["frames"][1]["records"].append(d["frames"][1]["records"][0]),
        "second record",
    ),
    "elements short": (
        lambda d: _set(d, ["frames", 0, "elements", "priority", "shape"], [4]),
        "priority",
    ),
    "reflectors differ": (lambda d: _set(d, ["reflectors"], [1, 2, 3]), "reflectors"),
    "class tag": (lambda d: _set(d, ["lights"], {"__class__": "os.system"}), "lights"),
}


@pytest.mark.parametrize("mutation", sorted(MUTATIONS))
def test_a_malformed_recording_is_refused_with_one_line(
    tmp_path: Path, capsys, mutation: str
) -> None:
    change, mentions = MUTATIONS[mutation]
    obj = pr.encode_recording(recording(3))
    change(obj)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(obj))
    with pytest.raises(pr.RecordingError, match=mentions) as info:
        pr.load_recording(path)
    assert "\n" not in str(info.value) and str(info.value).startswith(str(path))
    assert pr.main(["replay", str(path), "--budgets", "1000"]) == 1
    _one_line_error(capsys)


@pytest.mark.parametrize(
    "content",
    [b"", b"{", b'{"format": "phrt-replay-recording", "version": 1,', b"[1, 2]", b"\xff\xfe\x00",
     b"null", b"[" * 100000 + b"]" * 100000, b"\x1f\x8b\x08\x00garbage"],
    ids=["empty", "brace", "truncated", "list", "binary", "null", "deep", "bad-gzip"],
)  # fmt: skip
def test_corrupt_files_are_refused_with_one_line(tmp_path: Path, capsys, content: bytes) -> None:
    path = tmp_path / "rec.json.gz"
    path.write_bytes(content)
    with pytest.raises(pr.RecordingError) as info:
        pr.load_recording(path)
    assert "\n" not in str(info.value)
    assert pr.main(["replay", str(path), "--budgets", "1000"]) == 1
    _one_line_error(capsys)


def test_truncated_gzip_recording_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "rec.json.gz"
    pr.save_recording(path, recording(2))
    path.write_bytes(path.read_bytes()[:-40])
    with pytest.raises(pr.RecordingError, match="not a replay recording"):
        pr.load_recording(path)


def test_missing_file_is_one_line(tmp_path: Path, capsys) -> None:
    assert pr.main(["replay", str(tmp_path / "none.json.gz"), "--budgets", "10"]) == 1
    assert "cannot read" in _one_line_error(capsys)


def test_save_refuses_what_the_format_does_not_know(tmp_path: Path) -> None:
    data = recording(2)
    data["frames"][1].view.camera.world_from_camera = np.eye(4, dtype=np.float32)
    with pytest.raises(pr.RecordingError, match="world_from_camera"):
        pr.save_recording(tmp_path / "rec.json", data)
    assert not (tmp_path / "rec.json").exists()


def _images(n: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {
        "times": np.arange(n, dtype=float),
        "ids": rng.integers(-1, 5, (n, 4, 6)).astype(np.int32),
        "raster": rng.random((n, 4, 6, 3), dtype=np.float32),
        "all": rng.random((n, 4, 6, 3), dtype=np.float32),
        "traced": rng.random((n, 4, 6)) < 0.5,
    }


def test_images_npz_is_loaded_without_pickles(tmp_path: Path) -> None:
    good = tmp_path / "good.npz"
    np.savez(good, **_images(3))
    images = pr.load_images(good, 3)
    assert images["raster"].dtype == np.float32 and images["traced"].dtype == bool
    with pytest.raises(pr.RecordingError, match="frames of images"):
        pr.load_images(good, 4)
    marker = tmp_path / "code-ran"
    objects = tmp_path / "objects.npz"
    arrays = _images(3)
    arrays["ids"] = np.array([_Planted(marker)], dtype=object)
    np.savez(objects, **arrays)  # an object array: pickled inside the npz
    planted = tmp_path / "planted.npz"
    planted.write_bytes(pickle.dumps(_Planted(marker)))
    for path in (objects, planted):
        with pytest.raises(pr.RecordingError, match="not a capture's images"):
            pr.load_images(path, 3)
    assert not marker.exists()
