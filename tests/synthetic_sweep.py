"""A synthetic sweep output directory (``write_synthetic_sweep``: sweep.csv, timeline.json,
preview and FLIP images) for the report tests: two stages, heuristics at two time budgets,
a ray budget and unbounded, the ``raster`` / ``all`` / ``rt`` baselines, random but
consistent per-frame figures. No rendering."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

COLUMNS = [
    "stage", "config", "heuristic", "mode", "budget_ms", "budget_rays", "frame", "frame_ms",
    "gbuffer_ms", "shade_ms", "select_ms", "trace_ms", "predicted_trace_ms", "rays",
    "visible", "selected", "transitions", "density_steps", "flip", "flip_reflectors", "psnr",
    "flip_rt",
    "psnr_rt", "temporal_error", "temporal_error_reflectors",
]  # fmt: skip

#: (config, heuristic, mode, budget_ms, budget_rays), deliberately not in display order.
CONFIGS = [
    ("all", "all", "hybrid", "", ""),
    ("heu1@8ms", "heu1", "hybrid", "8", ""),
    ("rt", "all", "rt", "", ""),
    ("heu2@4ms", "heu2", "hybrid", "4", ""),
    ("heu1@inf", "heu1", "hybrid", "", ""),
    ("raster", "none", "raster", "", ""),
    ("heu1@20000rays", "heu1", "hybrid", "", "20000"),
    ("heu1@4ms", "heu1", "hybrid", "4", ""),
    ("heu2@8ms", "heu2", "hybrid", "8", ""),
]
STAGES = {"farm": 5, "sewer": 7}  # stage → reflector count
FRAMES = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
IMAGE_FRAME = "0003"
IMAGE_SIZE = (12, 8)  # width, height of the synthetic preview PNGs


def _write_png(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    height, width = rgb.shape[:2]
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(width, height, 3, oiio.UINT8))
    assert out.write_image(np.ascontiguousarray(rgb, dtype=np.uint8))
    out.close()


def write_synthetic_sweep(out: Path, seed: int = 7, configs=CONFIGS) -> Path:
    """A small sweep output directory (csv, timeline.json, images) in ``out``."""
    rng = np.random.default_rng(seed)
    out.mkdir(parents=True, exist_ok=True)
    rows, timeline = [], {}
    for stage, n_reflectors in STAGES.items():
        timeline[stage] = {}
        visible = rng.random((len(FRAMES), n_reflectors)) < 0.7
        for config, heuristic, mode, budget_ms, budget_rays in configs:
            if heuristic == "all" and mode == "hybrid":
                selected = visible.copy()
            elif heuristic == "none" or mode == "raster":
                selected = np.zeros_like(visible)
            else:
                selected = visible & (rng.random(visible.shape) < 0.5)
            timeline[stage][config] = {
                "reflectors": [f"/World/{stage}/mirror_{i}" for i in range(n_reflectors)],
                "frames": FRAMES,
                "selected": selected.tolist(),
                "visible": visible.tolist(),
            }
            for f, frame in enumerate(FRAMES):
                both = visible[f] & visible[f - 1] if f else np.zeros(n_reflectors, bool)
                switched = both & (selected[f] != selected[f - 1])
                is_ref = config == "all"
                flip = 0.0 if is_ref else float(rng.uniform(0.001, 0.2))
                rows.append(
                    {
                        "stage": stage,
                        "config": config,
                        "heuristic": heuristic,
                        "mode": mode,
                        "budget_ms": budget_ms,
                        "budget_rays": budget_rays,
                        "frame": frame,
                        "frame_ms": float(rng.uniform(3.0, 60.0)),
                        "gbuffer_ms": float(rng.uniform(1, 3)),
                        "shade_ms": float(rng.uniform(1, 3)),
                        "select_ms": float(rng.uniform(0, 1)),
                        "trace_ms": float(rng.uniform(0.0, 20.0)),
                        "predicted_trace_ms": float(rng.uniform(0.0, 20.0)),
                        "rays": int(rng.integers(0, 50000)),
                        "visible": int(visible[f].sum()),
                        "selected": int(selected[f].sum()),
                        "transitions": int(switched.sum()),
                        "density_steps": int(rng.integers(0, 3)),
                        "flip": flip,
                        "flip_reflectors": 0.0 if is_ref else float(rng.uniform(0.0, 0.5)),
                        "psnr": 100.0 if is_ref else float(rng.uniform(20, 45)),
                        "flip_rt": float(rng.uniform(0, 0.1)),
                        "psnr_rt": float(rng.uniform(20, 45)),
                        "temporal_error": ""
                        if f == 0
                        else (0.0 if is_ref else float(rng.uniform(0, 0.05))),
                        "temporal_error_reflectors": ""
                        if f == 0
                        else (0.0 if is_ref else float(rng.uniform(0, 0.3))),
                    }
                )
            if config in ("raster", "heu1@4ms", "all", "rt"):
                image_dir = out / "images" / stage / IMAGE_FRAME
                shape = (IMAGE_SIZE[1], IMAGE_SIZE[0], 3)
                _write_png(image_dir / f"{config}.png", rng.integers(0, 256, shape))
                if config != "all":
                    _write_png(image_dir / f"{config}_flip.png", rng.integers(0, 256, shape))
    with (out / "sweep.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    (out / "timeline.json").write_text(json.dumps(timeline))
    return out
