"""Error against run time: every heuristic × budget on the same frames, in one process.

Per stage and frame, in frame order:

1. the raster G-buffer and local shading are made once (``FrameRenderer.prepare``);
2. the ``all`` reference (every visible reflector, bounce limit, unbounded) finishes that
   frame, and so does each heuristic × budget with its own selection policy (HEU1 keeps
   its memory from frame to frame per configuration);
3. the pure ``rt`` mode renders the frame as a second reference (Embree for everything);
4. each configuration's image is compared with the references: FLIP (LDR after
   ``images.tonemap_ldr``) and PSNR, over the frame and over reflector pixels only; the
   FLIP between consecutive frames of one configuration, next to the reference's, shows
   popping.

Frame times are measured per configuration in the same run: G-buffer and shading
phases (shared) plus that configuration's own selection and trace phases.

Outputs in ``OUT``: ``sweep.csv`` (rewritten atomically after every frame, so an
interrupted sweep keeps its finished rows), ``timeline.json``, a few frames' images under
``images/``, then ``summary.md``, ``error_vs_time.png`` and ``report.html``
(``phrt_usd.evaluate.sweep_report``).
"""

from __future__ import annotations

import csv
import io
import json
import threading
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from phrt_usd.atomic import write_text_atomic
from phrt_usd.errors import BadOption
from phrt_usd.evaluate.image_metrics import flip_map, mean_over, psnr
from phrt_usd.evaluate.selection_metrics import transitions_per_frame
from phrt_usd.evaluate.sweep_files import (
    ERROR_VS_TIME_PNG,
    FLIP_MAP_SUFFIX,
    IMAGES_DIR,
    REPORT_HTML,
    SUMMARY_MD,
    SWEEP_CSV,
    TIMELINE_JSON,
)
from phrt_usd.render.renderer import FrameOutput, FrameRenderer, RenderOptions
from phrt_usd.run.frames import parse_frames
from phrt_usd.run.images import write_png_atomic, write_preview_png
from phrt_usd.run.render_job import stop_on_signals
from phrt_usd.run.run_directory import DirectoryLock
from phrt_usd.select.policies import make_policy
from phrt_usd.usd.schema import DEFAULT_BOUNCE_LIMIT, DEFAULT_RESOLUTION, DEFAULT_SELECTION_WEIGHT
from phrt_usd.usd.stage import open_stage

CSV_COLUMNS = [
    "stage", "config", "heuristic", "mode", "budget_ms", "budget_rays", "frame",
    "frame_ms", "gbuffer_ms", "shade_ms", "select_ms", "trace_ms", "predicted_trace_ms",
    "rays", "visible", "selected", "transitions", "flip", "flip_reflectors", "psnr",
    "flip_rt", "psnr_rt", "flip_temporal", "flip_temporal_reference",
]  # fmt: skip

#: How many frames per stage get their images (hybrid, reference, error map) in the report.
REPORT_FRAMES = 3


@dataclass
class SweepConfig:
    """One column of the sweep: a heuristic with one budget (None = unbounded)."""

    heuristic: str
    mode: str = "hybrid"
    budget_ms: float | None = None
    budget_rays: int | None = None

    @property
    def label(self) -> str:
        if self.mode != "hybrid" or self.heuristic in ("all", "none"):
            return {"raster": "raster", "rt": "rt"}.get(self.mode, self.heuristic)
        if self.budget_rays is not None:
            return f"{self.heuristic}@{self.budget_rays}rays"
        if self.budget_ms is None:
            return f"{self.heuristic}@inf"
        return f"{self.heuristic}@{self.budget_ms:g}ms"


@dataclass
class SweepSpec:
    stages: list[Path]
    heuristics: list[str]
    budgets_ms: list[float | None] = field(default_factory=list)
    budgets_rays: list[int | None] = field(default_factory=list)
    frames: str | None = None
    width: int = DEFAULT_RESOLUTION[0]
    height: int = DEFAULT_RESOLUTION[1]
    bounce_limit: int = DEFAULT_BOUNCE_LIMIT
    selection_weight: float = DEFAULT_SELECTION_WEIGHT
    out: Path = Path("sweep")


def parse_budget_list(text: str | None, kind: type) -> list:
    """``"0,2,4,inf"`` → [0, 2, 4, None] (``inf``/``none`` = unbounded)."""
    if not text:
        return []
    values: list = []
    for item in text.split(","):
        item = item.strip().lower()
        if item in ("inf", "none", "unbounded"):
            values.append(None)
            continue
        try:
            v = kind(item)
        except ValueError:
            raise BadOption(f"budget {item!r} is not a number (or inf)") from None
        if v < 0 or not np.isfinite(v):
            raise BadOption(f"budget {item!r} must be finite and >= 0 (or inf)")
        values.append(v)
    return values


def sweep_configs(spec: SweepSpec) -> list[SweepConfig]:
    configs = [SweepConfig("none", mode="raster")]
    for h in spec.heuristics:
        configs += [SweepConfig(h, budget_ms=b) for b in spec.budgets_ms]
        configs += [SweepConfig(h, budget_rays=b) for b in spec.budgets_rays]
    return configs


class _ConfigState:
    """Per-configuration memory across frames: policy, previous image and selection.

    ``previous``: the last rendered frame's (selected, visible), each (R,) bool over the
    stage's reflectors (``StageSweep.reflectors`` order); None before the first frame."""

    def __init__(self, config: SweepConfig, spec: SweepSpec):
        self.config = config
        self.policy = make_policy(
            config.heuristic if config.mode == "hybrid" else "none",
            selection_weight=spec.selection_weight,
            bounce_limit=spec.bounce_limit,
        )
        self.options = RenderOptions(
            mode=config.mode,
            heuristic=config.heuristic,
            width=spec.width,
            height=spec.height,
            budget_ms=config.budget_ms,
            budget_rays=config.budget_rays,
            bounce_limit=spec.bounce_limit,
            selection_weight=spec.selection_weight,
        )
        self.previous_image: np.ndarray | None = None
        self.previous: tuple[np.ndarray, np.ndarray] | None = None
        self.timeline_selected: list[list[bool]] = []
        self.timeline_visible: list[list[bool]] = []


def run_sweep(spec: SweepSpec, on_frame: Callable[[str, int, int], None] | None = None) -> dict:
    """Run the sweep; returns a summary dict (rows written, output paths)."""
    check_spec(spec)
    out = spec.out
    if out.exists() and not out.is_dir():
        raise BadOption(f"--out {out}: exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    timeline: dict = {}
    stop = threading.Event()
    with DirectoryLock(out), stop_on_signals(stop):  # one sweep writes OUT at a time
        for stage_path in spec.stages:
            if stop.is_set():
                break
            _sweep_stage(stage_path, spec, rows, timeline, stop, on_frame)
        return finish_sweep(spec, rows, timeline, interrupted=stop.is_set())


def check_spec(spec: SweepSpec) -> None:
    """Raise PhrtError unless ``spec`` names heuristics and budgets the sweep knows."""
    if not spec.heuristics:
        raise BadOption("--heuristics: give at least one of heu1, heu2")
    for h in spec.heuristics:
        if h not in ("heu1", "heu2"):
            raise BadOption(f"--heuristics: {h!r} is not heu1 or heu2")
    if not spec.budgets_ms and not spec.budgets_rays:
        raise BadOption("give --budgets-ms or --budgets-rays")


def finish_sweep(spec: SweepSpec, rows: list[dict], timeline: dict, interrupted: bool) -> dict:
    """Write sweep.csv, timeline.json and the report into ``spec.out``; returns the
    summary dict of ``run_sweep``."""
    out = spec.out
    write_sweep_csv(out / SWEEP_CSV, rows)
    _write_json(out / TIMELINE_JSON, timeline)
    from phrt_usd.evaluate.sweep_report import write_sweep_report

    write_sweep_report(out)
    return {
        "out": str(out),
        "rows": len(rows),
        "stages": [Path(s).stem for s in spec.stages],
        "configs": [c.label for c in sweep_configs(spec)] + ["all", "rt"],
        "interrupted": interrupted,
        "files": [SWEEP_CSV, TIMELINE_JSON, SUMMARY_MD, ERROR_VS_TIME_PNG, REPORT_HTML],
    }


def _sweep_stage(stage_path, spec, rows, timeline, stop, on_frame) -> None:
    sweep = StageSweep(stage_path, spec)
    try:
        sweep.warm_up()
        for n, t in enumerate(sweep.times):
            rows.extend(sweep.frame(t, record=True))
            write_sweep_csv(spec.out / SWEEP_CSV, rows)
            if on_frame is not None:
                on_frame(sweep.name, n + 1, len(sweep.times))
            if stop.is_set():
                break
    finally:
        sweep.close()
    timeline[sweep.name] = sweep.timeline()


class StageSweep:
    """One stage's sweep, frame by frame: the shared renderers and every configuration's
    memory (policy, previous image and selection). ``frame(t, record=False)`` renders a
    warm-up frame: every memory advances but no row, timeline entry or image is kept, so a
    chunk of frames can start mid-path (``phrt_usd.cluster``)."""

    def __init__(self, stage_path: Path | str, spec: SweepSpec):
        self.stage = open_stage(stage_path)
        self.spec = spec
        self.name = Path(stage_path).stem
        #: Every time code of this stage's sweep (the chunk's frames are a slice of it).
        self.times = parse_frames(spec.frames, self.stage.frame_range)
        base = RenderOptions(
            mode="hybrid", heuristic="all", width=spec.width, height=spec.height,
            budget_ms=None, budget_rays=None, bounce_limit=spec.bounce_limit,
            selection_weight=spec.selection_weight,
        )  # fmt: skip
        self.hybrid = FrameRenderer(self.stage, base)
        self.hybrid.plan(self.times)
        self.rt = FrameRenderer(self.stage, replace(base, mode="rt"))
        self.states = [_ConfigState(c, spec) for c in sweep_configs(spec)]
        self.reference = _ConfigState(SweepConfig("all"), spec)
        self.rt_state = _ConfigState(SweepConfig("all", mode="rt"), spec)
        self.reflectors = [
            self.stage.scene.elements[i].path for i in self.stage.scene.reflector_ids
        ]
        times = self.times
        self.report_frames = set(times[:: max(1, len(times) // REPORT_FRAMES)][:REPORT_FRAMES])
        self.recorded: list[float] = []

    def close(self) -> None:
        self.hybrid.close()
        self.rt.close()

    def warm_up(self) -> None:
        """Render the first frame once, untimed, with a throwaway ``all`` policy: the
        first frame of a process compiles GL programs and builds the Embree scene (~0.8 s
        on the farm), which would otherwise land in every configuration's first frame
        time. No configuration's memory is touched."""
        if not self.times:
            return
        t = self.times[0]
        reference = self.reference
        policy = make_policy(
            "all", selection_weight=self.spec.selection_weight, bounce_limit=self.spec.bounce_limit
        )
        self.hybrid.finish(self.hybrid.prepare(t), policy, reference.options)
        self.rt.render(t)

    def frame(self, t: float, record: bool = True) -> list[dict]:
        """Render frame ``t`` for every configuration and both references; returns its CSV
        rows (none for a warm-up frame, ``record=False``)."""
        reference, rt_state = self.reference, self.rt_state
        prep = self.hybrid.prepare(t)
        ref_out = self.hybrid.finish(prep, reference.policy, reference.options)
        rt_out = self.rt.render(t)
        reflector_px = prep.reflectivity > 0
        temporal_ref = (
            None
            if reference.previous_image is None
            else mean_over(flip_map(reference.previous_image, ref_out.beauty))
        )
        outputs = [(s, self.hybrid.finish(prep, s.policy, s.options)) for s in self.states]
        outputs += [(reference, ref_out), (rt_state, rt_out)]
        rows = []
        for state, output in outputs:
            selection = _selection_row(output, self.reflectors)
            if record:
                error = flip_map(ref_out.beauty, output.beauty)
                rows.append(
                    _row(
                        self.name,
                        state,
                        output,
                        ref_out,
                        error,
                        rt_out,
                        reflector_px,
                        temporal_ref,
                        selection,
                    )
                )
                if t in self.report_frames:
                    label = state.config.label
                    _write_report_images(self.spec.out, self.name, t, label, output, error)
            _remember(state, output, selection, record)
        if record:
            self.recorded.append(t)
        return rows

    def timeline(self) -> dict:
        """timeline.json's entry of this stage: per configuration label, the recorded
        frames and which reflectors each selected / saw."""
        return {
            s.config.label: {
                "reflectors": self.reflectors,
                "frames": list(self.recorded),
                "selected": s.timeline_selected,
                "visible": s.timeline_visible,
            }
            for s in [*self.states, self.reference, self.rt_state]
        }


def _row(
    stage: str,
    state: _ConfigState,
    output: FrameOutput,
    ref: FrameOutput,
    flip_ref: np.ndarray,
    rt: FrameOutput,
    reflector_px: np.ndarray,
    temporal_ref: float | None,
    selection: tuple[np.ndarray, np.ndarray],
) -> dict:
    """One CSV row. flip_ref: (H, W) FLIP of this output against the ``all`` reference
    ``ref``; reflector_px: (H, W) bool pixels of reflectors; temporal_ref: the
    reference's FLIP between this frame and the previous one (None on the first);
    selection: this frame's (selected, visible), see ``_selection_row``. ``transitions``:
    from the configuration's previous frame into this one (``selection_metrics``; 0 on
    its first frame)."""
    st = output.stats
    cfg = state.config
    transitions = 0
    if state.previous is not None:
        (selected_before, visible_before), (selected, visible) = state.previous, selection
        transitions = int(
            transitions_per_frame(
                np.stack([selected_before, selected]), np.stack([visible_before, visible])
            )[-1]
        )
    temporal = None
    if state.previous_image is not None:
        temporal = mean_over(flip_map(state.previous_image, output.beauty))
    heuristic = {"rt": "all", "raster": "none"}.get(cfg.mode, cfg.heuristic)
    return {
        "stage": stage,
        "config": cfg.label,
        "heuristic": heuristic,
        "mode": cfg.mode,
        "budget_ms": _blank(cfg.budget_ms),
        "budget_rays": _blank(cfg.budget_rays),
        "frame": st.time,
        "frame_ms": round(st.frame_ms, 3),
        "gbuffer_ms": round(st.phase_ms.get("gbuffer", 0.0), 3),
        "shade_ms": round(st.phase_ms.get("shade", 0.0), 3),
        "select_ms": round(st.phase_ms.get("select", 0.0), 3),
        "trace_ms": round(st.trace_ms, 3),
        "predicted_trace_ms": round(st.predicted_trace_ms, 3),
        "rays": st.rays,
        "visible": len(set(st.visible)),
        "selected": len(set(st.selected)),
        "transitions": transitions,
        "flip": round(mean_over(flip_ref), 6),
        "flip_reflectors": round(mean_over(flip_ref, reflector_px), 6),
        "psnr": round(psnr(ref.beauty, output.beauty), 4),
        "flip_rt": round(mean_over(flip_map(rt.beauty, output.beauty)), 6),
        "psnr_rt": round(psnr(rt.beauty, output.beauty), 4),
        "flip_temporal": _blank(None if temporal is None else round(temporal, 6)),
        "flip_temporal_reference": _blank(None if temporal_ref is None else round(temporal_ref, 6)),
    }


def _blank(value):
    """CSV cell: empty for None (unbounded budget, no previous frame)."""
    return "" if value is None else value


def _remember(
    state: _ConfigState,
    output: FrameOutput,
    selection: tuple[np.ndarray, np.ndarray],
    record: bool = True,
) -> None:
    """Keep this frame's image and (selected, visible) for the next frame's row."""
    selected, visible = selection
    state.previous = selection
    state.previous_image = output.beauty
    if record:
        state.timeline_selected.append(selected.tolist())
        state.timeline_visible.append(visible.tolist())


def _selection_row(output: FrameOutput, reflectors: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(selected, visible) of one rendered frame, each (R,) bool over ``reflectors``."""
    selected, visible = set(output.stats.selected), set(output.stats.visible)
    return (
        np.array([p in selected for p in reflectors], dtype=bool),
        np.array([p in visible for p in reflectors], dtype=bool),
    )


def _write_report_images(
    out: Path, stage: str, t: float, label: str, output: FrameOutput, error: np.ndarray
) -> None:
    """Preview PNG and FLIP error map (magma) of one configuration's frame."""
    import matplotlib

    folder = out / IMAGES_DIR / stage / f"{t:g}"
    folder.mkdir(parents=True, exist_ok=True)
    write_preview_png(folder / f"{label}.png", output.beauty)
    magma = matplotlib.colormaps["magma"](np.clip(error, 0.0, 1.0))[..., :3]
    # The error map is already display-referred: written without the tone map.
    _write_display_png(folder / f"{label}{FLIP_MAP_SUFFIX}.png", magma.astype(np.float32))


def _write_display_png(path: Path, rgb: np.ndarray) -> None:
    """Write an (H, W, 3) display-referred [0, 1] image as an 8-bit PNG, atomically."""
    data = np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8)
    write_png_atomic(path, data)


def write_sweep_csv(path: Path, rows: list[dict]) -> None:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=CSV_COLUMNS)
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomic(path, buf.getvalue())


def _write_json(path: Path, data: dict) -> None:
    write_text_atomic(path, json.dumps(data, indent=1))
