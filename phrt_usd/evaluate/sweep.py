"""Error against run time: every heuristic × budget on the same frames, in one process.

A sweep's *variants* are the other knobs a user turns: every resolution × bounce limit ×
trace density (``SweepSpec.resolutions``, ``SweepSpec.bounce_limits``,
``SweepSpec.trace_densities``; one variant by default). Per stage and frame, in frame
order, per resolution:

1. the raster G-buffer and local shading are made once (``FrameRenderer.prepare``), and
   so are the ``rt`` mode's primary rays;
2. per bounce limit, the ``all`` reference (every visible reflector, that bounce limit,
   unbounded) finishes that frame, and so does each heuristic × budget with its own
   selection policy (HEU1 keeps its memory from frame to frame per configuration);
3. the pure ``rt`` mode finishes the frame at that bounce limit as a second reference;
4. each configuration's image is compared with its variant's references: FLIP (LDR
   after ``images.tonemap_ldr``) and PSNR, over the frame and over reflector pixels only,
   and the temporal error (``temporal_error``, docs/temporal-error.md): each sequence's
   previous frame warped to this one by the frame's exact motion vectors (occluded
   pixels masked) and compared with FLIP, the configuration's warped error beyond the
   reference's own, which sees the popping of a reflector switching between raster and
   traced and not the motion both sequences share.

Frame times are measured per configuration in the same run: G-buffer and shading
phases (shared) plus that configuration's own selection and trace phases.

Outputs in ``OUT`` (an empty directory, or one an earlier sweep wrote with
``overwrite``: ``sweep_output``): ``sweep.csv`` (rewritten atomically after every frame,
so an interrupted sweep keeps its finished rows), ``timeline.json``, a few frames' images
under ``images/``, then ``provenance.json`` (``provenance.collect``: version, commit,
command, machine, threads, OpenGL, FLIP's viewing conditions, seeds, the sweep's
settings), ``summary.md``, ``error_vs_time.png`` and ``report.html``
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
from phrt_usd.engine.renderer import FrameOutput, FrameRenderer, RenderOptions
from phrt_usd.errors import BadOption
from phrt_usd.evaluate import provenance
from phrt_usd.evaluate.image_metrics import flip_map, mean_over, psnr
from phrt_usd.evaluate.selection_metrics import (
    density_levels,
    density_steps,
    transitions_per_frame,
)
from phrt_usd.evaluate.sweep_files import (
    ERROR_VS_TIME_PNG,
    FLIP_MAP_SUFFIX,
    IMAGES_DIR,
    PROVENANCE_JSON,
    REPORT_HTML,
    SUMMARY_CSV,
    SUMMARY_MD,
    SWEEP_CSV,
    TEMPORAL_MAP_SUFFIX,
    TIMELINE_JSON,
)
from phrt_usd.evaluate.sweep_output import SweepDirectory, check_out
from phrt_usd.evaluate.temporal_error import FrameWarp, WarpedSequence, popping_map
from phrt_usd.model.render_options import OPTIONS
from phrt_usd.run.frames import parse_frames
from phrt_usd.run.images import write_png_atomic, write_preview_png
from phrt_usd.run.render_job import runtime_settings, stop_on_signals
from phrt_usd.select.policies import make_policy
from phrt_usd.usd.stage import open_stage

CSV_COLUMNS = [
    "stage", "config", "heuristic", "mode", "budget_ms", "budget_rays", "resolution",
    "bounce_limit", "trace_density", "frame", "frame_ms", "gbuffer_ms", "shade_ms",
    "select_ms", "trace_ms",
    "predicted_trace_ms", "rays", "visible", "selected", "transitions", "density_steps", "flip",
    "flip_reflectors", "psnr", "flip_rt", "psnr_rt", "warped_error", "warped_error_reference",
    "temporal_error", "temporal_error_reflectors",
]  # fmt: skip
#: The columns of the temporal error, blank on a sequence's first frame (no previous one).
TEMPORAL_COLUMNS = (
    "warped_error", "warped_error_reference", "temporal_error", "temporal_error_reflectors",
)

#: The render options a ``SweepSpec`` sets for all its renderers, and its lists of
#: values of one option each (a list → the option each of its values sets).
SPEC_OPTIONS = ("width", "height", "bounce_limit", "selection_weight", "threads", "gl", "exposure")
SPEC_OPTION_LISTS = {
    "budgets_ms": "budget_ms",
    "budgets_rays": "budget_rays",
    "bounce_limits": "bounce_limit",
    "trace_densities": "trace_density",
}
#: How many frames per stage get their images (hybrid, reference, error map) in the report.
REPORT_FRAMES = 3


@dataclass(frozen=True)
class Variant:
    """One setting of the knobs besides heuristic and budget: resolution, bounce limit and
    trace density (of the policies' hybrid frames; the references trace every pixel).
    ``label`` names the knobs that vary in the sweep (e.g. ``"b2 320x240 half"``; ``""``
    when the sweep has a single variant) and is appended to the configurations' labels."""

    width: int
    height: int
    bounce_limit: int
    label: str = ""
    trace_density: str = "full"

    @property
    def resolution(self) -> str:
        return f"{self.width}x{self.height}"


@dataclass
class SweepConfig:
    """One column of the sweep: a heuristic with one budget (None = unbounded), at one
    variant (None: the spec's single resolution and bounce limit, no label suffix)."""

    heuristic: str
    mode: str = "hybrid"
    budget_ms: float | None = None
    budget_rays: int | None = None
    variant: Variant | None = None

    @property
    def label(self) -> str:
        suffix = f" {self.variant.label}" if self.variant is not None and self.variant.label else ""
        if self.mode != "hybrid" or self.heuristic in ("all", "none"):
            return {"raster": "raster", "rt": "rt"}.get(self.mode, self.heuristic) + suffix
        if self.budget_rays is not None:
            return f"{self.heuristic}@{self.budget_rays}rays{suffix}"
        if self.budget_ms is None:
            return f"{self.heuristic}@inf{suffix}"
        return f"{self.heuristic}@{self.budget_ms:g}ms{suffix}"


@dataclass
class SweepSpec:
    """What a sweep renders: its stages, heuristics × budgets, frames and variants, and the
    render options every renderer of it shares. The render options take their defaults
    from their declaration (``model.render_options.OPTIONS``) and are checked by it when
    the spec is made (``BadOption``, one line), held as a render holds them."""

    stages: list[Path]
    heuristics: list[str]
    budgets_ms: list[float | None] = field(default_factory=list)
    budgets_rays: list[int | None] = field(default_factory=list)
    frames: str | None = None
    width: int = OPTIONS["width"].default
    height: int = OPTIONS["height"].default
    bounce_limit: int = OPTIONS["bounce_limit"].default
    selection_weight: float = OPTIONS["selection_weight"].default
    out: Path = Path("sweep")
    #: Knob sweeps: every bounce limit × resolution (WxH) × trace density; empty =
    #: ``bounce_limit``, (``width``, ``height``) and full density alone.
    bounce_limits: list[int] = field(default_factory=list)
    resolutions: list[tuple[int, int]] = field(default_factory=list)
    trace_densities: list[str] = field(default_factory=list)
    #: Every renderer's thread setting and OpenGL platform (``RenderOptions``).
    threads: int = OPTIONS["threads"].default
    gl: str = OPTIONS["gl"].default
    #: ``--exposure EV`` of every renderer (``RenderOptions.exposure``): images, and the
    #: FLIP / PSNR of their tone-mapped previews, are of the scaled radiance.
    exposure: float = OPTIONS["exposure"].default
    #: Replace an earlier sweep in ``out`` (its files only, ``sweep_output``); without
    #: it a non-empty ``out`` is refused.
    overwrite: bool = False

    def __post_init__(self) -> None:
        for name in SPEC_OPTIONS:
            setattr(self, name, OPTIONS[name].check(getattr(self, name)))
        for name, option in SPEC_OPTION_LISTS.items():
            setattr(self, name, [OPTIONS[option].check(v) for v in getattr(self, name)])

    def variants(self) -> list[Variant]:
        """Every resolution × bounce limit × trace density, resolutions outer, in the
        order given."""
        limits = self.bounce_limits or [self.bounce_limit]
        sizes = self.resolutions or [(self.width, self.height)]
        densities = self.trace_densities or ["full"]
        variants = []
        for w, h in sizes:
            for b in limits:
                for d in densities:
                    parts = (
                        ([f"b{b}"] if len(limits) > 1 else [])
                        + ([f"{w}x{h}"] if len(sizes) > 1 else [])
                        + ([d] if len(densities) > 1 else [])
                    )
                    variants.append(Variant(w, h, b, " ".join(parts), d))
        return variants


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


def parse_int_list(text: str | None, option: str) -> list[int]:
    """``"0,1,2,5"`` → [0, 1, 2, 5]; BadOption naming ``option`` for a non-integer."""
    if not text:
        return []
    values = []
    for item in text.split(","):
        try:
            values.append(int(item.strip()))
        except ValueError:
            raise BadOption(f"{option}: {item.strip()!r} is not an integer") from None
    return values


def parse_resolution_list(text: str | None, option: str = "--resolutions") -> list[tuple[int, int]]:
    """``"160x120,320x240"`` → [(160, 120), (320, 240)]; BadOption naming the bad item."""
    if not text:
        return []
    sizes = []
    for item in text.split(","):
        w, sep, h = item.strip().lower().partition("x")
        try:
            if not sep:
                raise ValueError
            sizes.append((int(w), int(h)))
        except ValueError:
            raise BadOption(f"{option}: {item.strip()!r} is not WxH (e.g. 320x240)") from None
    return sizes


def sweep_configs(spec: SweepSpec, variant: Variant | None = None) -> list[SweepConfig]:
    """The swept configurations of one variant (the references ``all`` and ``rt`` are
    added by ``StageSweep``); every variant's when ``variant`` is None."""
    if variant is None:
        return [c for v in spec.variants() for c in sweep_configs(spec, v)]
    configs = [SweepConfig("none", mode="raster", variant=variant)]
    for h in spec.heuristics:
        configs += [SweepConfig(h, budget_ms=b, variant=variant) for b in spec.budgets_ms]
        configs += [SweepConfig(h, budget_rays=b, variant=variant) for b in spec.budgets_rays]
    return configs


class _ConfigState:
    """Per-configuration memory across frames: policy, the previous frame of its sequence
    (``temporal_error.WarpedSequence``), and the previous frame's selection.

    ``previous``: the last rendered frame's (selected, visible), each (R,) bool over the
    stage's reflectors (``StageSweep.reflectors`` order); None before the first frame."""

    def __init__(self, config: SweepConfig, spec: SweepSpec):
        self.config = config
        variant = config.variant or spec.variants()[0]
        # rt traces everything: its renderer finishes frames with the ``all`` policy.
        policy = {"hybrid": config.heuristic, "rt": "all"}.get(config.mode, "none")
        self.policy = make_policy(
            policy, selection_weight=spec.selection_weight, bounce_limit=variant.bounce_limit
        )
        # The references (all, rt) trace every pixel: errors are against full density.
        density = variant.trace_density if policy not in ("all", "none") else "full"
        self.options = RenderOptions(
            mode=config.mode,
            heuristic=config.heuristic,
            width=variant.width,
            height=variant.height,
            budget_ms=config.budget_ms,
            budget_rays=config.budget_rays,
            bounce_limit=variant.bounce_limit,
            selection_weight=spec.selection_weight,
            threads=spec.threads,
            gl=spec.gl,
            exposure=spec.exposure,
            trace_density=density,
        )
        self.temporal = WarpedSequence()
        self.previous: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.timeline_selected: list[list[bool]] = []
        self.timeline_visible: list[list[bool]] = []
        #: This frame's (output, selection) between making the rows and remembering.
        self.pending: tuple[FrameOutput, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None


def run_sweep(spec: SweepSpec, on_frame: Callable[[str, int, int], None] | None = None) -> dict:
    """Run the sweep; returns a summary dict (rows written, output paths, ``frames``:
    per stage swept, the frames done and planned; ``interrupted`` when a signal stopped
    it, after which every file holds the finished frames)."""
    check_spec(spec)
    rows: list[dict] = []
    timeline: dict = {}
    progress: dict[str, dict] = {}
    runtime: dict = {}
    stop = threading.Event()
    # One sweep writes OUT at a time, and never over an earlier one unless asked to.
    with SweepDirectory(spec.out, spec.overwrite), stop_on_signals(stop):
        for stage_path in spec.stages:
            if stop.is_set():
                break
            _sweep_stage(stage_path, spec, rows, timeline, stop, on_frame, progress, runtime)
        summary = finish_sweep(spec, rows, timeline, interrupted=stop.is_set(), runtime=runtime)
    summary["frames"] = progress
    return summary


def check_spec(spec: SweepSpec) -> None:
    """Raise PhrtError unless ``spec`` names heuristics and budgets the sweep knows and
    its ``out`` may be written (``sweep_output.check_out``: empty, or ``overwrite``)."""
    if not spec.heuristics:
        raise BadOption("--heuristics: give at least one of heu1, heu2")
    for h in spec.heuristics:
        if h not in ("heu1", "heu2"):
            raise BadOption(f"--heuristics: {h!r} is not heu1 or heu2")
    if not spec.budgets_ms and not spec.budgets_rays:
        raise BadOption("give --budgets-ms or --budgets-rays")
    knobs = (
        ("--bounce-limits", spec.bounce_limits),
        ("--resolutions", spec.resolutions),
        ("--trace-densities", spec.trace_densities),
    )
    for option, values in knobs:
        if len(set(values)) != len(values):
            raise BadOption(f"{option}: a value is given twice")
    for variant in spec.variants():
        # RenderOptions states the valid values (bounce limit, resolution, density) once.
        RenderOptions(
            width=variant.width, height=variant.height, bounce_limit=variant.bounce_limit,
            threads=spec.threads, gl=spec.gl, exposure=spec.exposure,
            trace_density=variant.trace_density,
        )  # fmt: skip
    # Last: a bad option is named before what OUT holds.
    check_out(spec.out, spec.overwrite)


def finish_sweep(
    spec: SweepSpec,
    rows: list[dict],
    timeline: dict,
    interrupted: bool,
    runtime: dict | None = None,
) -> dict:
    """Write sweep.csv, timeline.json, provenance.json and the report into ``spec.out``;
    returns the summary dict of ``run_sweep``. ``runtime``: how this process's renderers
    ran (``gl``, ``gl_renderer``; ``_runtime_of``), None where none ran here (a cluster's
    client). Without rows (interrupted before its first frame) there is no report."""
    out = spec.out
    write_sweep_csv(out / SWEEP_CSV, rows)
    _write_json(out / TIMELINE_JSON, timeline)
    record = sweep_provenance(spec, runtime or {}, interrupted)
    _write_json(out / PROVENANCE_JSON, record)
    files = [SWEEP_CSV, TIMELINE_JSON, PROVENANCE_JSON]
    if rows:
        from phrt_usd.evaluate.sweep_report import write_sweep_report

        write_sweep_report(out)
        files += [SUMMARY_MD, SUMMARY_CSV, ERROR_VS_TIME_PNG, REPORT_HTML]
    return {
        "out": str(out),
        "rows": len(rows),
        "stages": [Path(s).stem for s in spec.stages],
        "configs": [
            label
            for v in spec.variants()
            for label in [c.label for c in sweep_configs(spec, v)]
            + [SweepConfig("all", variant=v).label, SweepConfig("all", mode="rt", variant=v).label]
        ],
        "interrupted": interrupted,
        "threads": spec.threads,
        "exposure": spec.exposure,
        "provenance": record,
        "files": files,
    }


def interruption_note(summary: dict) -> str:
    """What an interrupted sweep (``run_sweep``'s summary) did and left, in one line:
    ``stopped after 3 of 40 frames of farm (not started: sewer); OUT holds sweep.csv (21
    rows) and the report of the finished frames; a new sweep into OUT needs --overwrite``."""
    progress = summary.get("frames") or {}
    done = [f"{c['done']} of {c['total']} frames of {name}" for name, c in progress.items()]
    waiting = [name for name in summary.get("stages", []) if name not in progress]
    where = "; ".join(done) or "no frame"
    if waiting:
        where += f" (not started: {', '.join(waiting)})"
    out = summary["out"]
    if not summary["rows"]:
        held = f"{out} holds no results ({SWEEP_CSV} has no rows, no report)"
    else:
        held = (
            f"{out} holds {SWEEP_CSV} ({summary['rows']} rows) and the report of the finished "
            f"frames ({SUMMARY_MD}, {REPORT_HTML})"
        )
    return f"stopped after {where}; {held}; a new sweep into {out} needs --overwrite"


def sweep_provenance(spec: SweepSpec, runtime: dict, interrupted: bool = False) -> dict:
    """provenance.json of a sweep: ``provenance.collect`` with the sweep's threads and
    OpenGL (``runtime``: what its renderers used, when they ran in this process) and its
    settings."""
    settings = {
        "stages": [str(s) for s in spec.stages],
        "heuristics": list(spec.heuristics),
        "budgets_ms": list(spec.budgets_ms),
        "budgets_rays": list(spec.budgets_rays),
        "frames": spec.frames,
        "variants": [
            {"resolution": v.resolution, "bounce_limit": v.bounce_limit,
             "trace_density": v.trace_density}
            for v in spec.variants()
        ],  # fmt: skip
        "selection_weight": spec.selection_weight,
        "exposure": spec.exposure,
        "interrupted": interrupted,
    }
    record = provenance.collect(
        threads=spec.threads, gl=spec.gl, gl_renderer=runtime.get("gl_renderer"), extra=settings
    )
    if runtime.get("gl"):
        record["gl"]["platform"] = runtime["gl"]
    if runtime.get("llvmpipe_threads") is not None:
        record["threads"]["llvmpipe"] = runtime["llvmpipe_threads"]
    return record


def _runtime_of(renderer: FrameRenderer) -> dict:
    """How a sweep's hybrid renderer runs (``render_job.runtime_settings``: OpenGL
    platform, llvmpipe's threads, ...) and its ``GL_RENDERER``."""
    rasterizer = getattr(renderer, "_rasterizer", None)
    gl_renderer = getattr(rasterizer, "gl_renderer", None)
    return runtime_settings(renderer) | {"gl_renderer": gl_renderer}


def _sweep_stage(stage_path, spec, rows, timeline, stop, on_frame, progress, runtime) -> None:
    """Sweep one stage into ``rows`` and ``timeline``; ``progress[stage]`` counts its
    frames (done, total); ``runtime`` gets its renderer's settings (``_runtime_of``)."""
    sweep = StageSweep(stage_path, spec)
    count = progress[sweep.name] = {"done": 0, "total": len(sweep.times)}
    try:
        sweep.warm_up()
        if not runtime and sweep.resolutions:  # llvmpipe's threads run once it has drawn
            runtime.update(_runtime_of(sweep.resolutions[0].hybrid))
        for n, t in enumerate(sweep.times):
            rows.extend(sweep.frame(t, record=True))
            write_sweep_csv(spec.out / SWEEP_CSV, rows)
            count["done"] = n + 1
            if on_frame is not None:
                on_frame(sweep.name, n + 1, len(sweep.times))
            if stop.is_set():
                break
    finally:
        sweep.close()
    timeline[sweep.name] = sweep.timeline()


class _VariantStates:
    """One variant's configurations and its two references (``all`` hybrid, ``rt``)."""

    def __init__(self, variant: Variant, spec: SweepSpec):
        self.variant = variant
        self.states = [_ConfigState(c, spec) for c in sweep_configs(spec, variant)]
        self.reference = _ConfigState(SweepConfig("all", variant=variant), spec)
        self.rt_state = _ConfigState(SweepConfig("all", mode="rt", variant=variant), spec)

    def all_states(self) -> list[_ConfigState]:
        return [*self.states, self.reference, self.rt_state]


class _Resolution:
    """The renderers of one resolution (hybrid and rt, shared by its bounce limits) and
    the previous frame's G-buffer (its element ids and depth, which the next frame's warp
    reads; None before the first frame)."""

    def __init__(self, stage, times, spec: SweepSpec, variants: list[_VariantStates]):
        first = variants[0].variant
        base = RenderOptions(
            mode="hybrid", heuristic="all", width=first.width, height=first.height,
            budget_ms=None, budget_rays=None, bounce_limit=first.bounce_limit,
            selection_weight=spec.selection_weight, threads=spec.threads, gl=spec.gl,
            exposure=spec.exposure,
        )  # fmt: skip
        self.hybrid = FrameRenderer(stage, base)
        self.hybrid.plan(times)
        self.rt = FrameRenderer(stage, replace(base, mode="rt"))
        self.rt.plan(times)
        self.variants = variants
        self.previous_gbuffer = None

    def warp(self, prep) -> FrameWarp | None:
        """How frame ``prep`` (a ``PreparedFrame``) reads the previous one, shared by every
        sequence of this resolution (they have one geometry): its motion vectors, element
        ids and the depth its points had then against the previous G-buffer; None for
        the first frame."""
        previous, motion = self.previous_gbuffer, prep.motion
        if previous is None or motion is None or not motion.has_previous:
            return None
        gb = prep.gbuffer
        return FrameWarp.between(
            motion.vectors, gb.element_id, previous.element_id, previous.depth,
            motion.previous_depth,
        )  # fmt: skip


class StageSweep:
    """One stage's sweep, frame by frame: the shared renderers (one hybrid and one rt per
    resolution) and every configuration's memory (policy, previous image and selection)
    of every variant. ``frame(t, record=False)`` renders a warm-up frame: every memory
    advances but no row, timeline entry or image is kept, so a chunk of frames can start
    mid-path (``phrt_usd.cluster``)."""

    def __init__(self, stage_path: Path | str, spec: SweepSpec):
        self.stage = open_stage(stage_path)
        self.spec = spec
        self.name = Path(stage_path).stem
        #: Every time code of this stage's sweep (the chunk's frames are a slice of it).
        self.times = parse_frames(spec.frames, self.stage.frame_range)
        by_size: dict[tuple[int, int], list[_VariantStates]] = {}
        for variant in spec.variants():
            key = (variant.width, variant.height)
            by_size.setdefault(key, []).append(_VariantStates(variant, spec))
        self.resolutions = [
            _Resolution(self.stage, self.times, spec, vs) for vs in by_size.values()
        ]
        self.reflectors = [
            self.stage.scene.elements[i].path for i in self.stage.scene.reflector_ids
        ]
        times = self.times
        self.report_frames = set(times[:: max(1, len(times) // REPORT_FRAMES)][:REPORT_FRAMES])
        self.recorded: list[float] = []

    def close(self) -> None:
        for res in self.resolutions:
            res.hybrid.close()
            res.rt.close()

    def warm_up(self) -> None:
        """Render the first frame once per resolution, untimed, with a throwaway ``all``
        policy: the first frame of a process compiles GL programs and builds the Embree
        scene (~0.8 s on the farm), which would otherwise land in every configuration's
        first frame time. No configuration's memory is touched."""
        if not self.times:
            return
        t = self.times[0]
        for res in self.resolutions:
            reference = res.variants[0].reference
            policy = make_policy(
                "all",
                selection_weight=self.spec.selection_weight,
                bounce_limit=reference.options.bounce_limit,
            )
            res.hybrid.finish(res.hybrid.prepare(t), policy, reference.options)
            res.rt.render(t)

    def frame(self, t: float, record: bool = True) -> list[dict]:
        """Render frame ``t`` for every configuration and both references of every
        variant; returns its CSV rows (none for a warm-up frame, ``record=False``)."""
        rows = []
        for res in self.resolutions:
            prep = res.hybrid.prepare(t)
            rt_prep = res.rt.prepare(t)
            reflector_px = prep.reflectivity > 0
            # Every sequence of this resolution is warped alike (one geometry), outside
            # the frames' timed phases; a warm-up frame's too, so the next one has it.
            warp = res.warp(prep)
            for group in res.variants:
                reference, rt_state = group.reference, group.rt_state
                ref_out = res.hybrid.finish(prep, reference.policy, reference.options)
                rt_out = res.rt.finish(rt_prep, rt_state.policy, rt_state.options)
                outputs = [(s, res.hybrid.finish(prep, s.policy, s.options)) for s in group.states]
                outputs += [(reference, ref_out), (rt_state, rt_out)]
                # Every sequence advances by this frame, warm-up frames included.
                warped = {id(s): s.temporal.push(out.beauty, warp) for s, out in outputs}
                references = _References(
                    ref_out, warped[id(reference)], rt_out, reflector_px,
                    None if warp is None else warp.valid,
                )  # fmt: skip
                for state, output in outputs:
                    selection = _selection_row(output, self.reflectors)
                    if record:
                        error = flip_map(ref_out.beauty, output.beauty)
                        own = warped[id(state)]
                        temporal = None if own is None else popping_map(own, references.ref_warped)
                        rows.append(
                            _row(self.name, state, output, error, own, temporal, references,
                                 selection)
                        )  # fmt: skip
                        if t in self.report_frames:
                            label = state.config.label
                            _write_report_images(
                                self.spec.out, self.name, t, label, output, error, temporal
                            )
                    state.pending = (output, selection)
                # Every row of this frame is made before any selection memory advances:
                # a row's transitions are from the previous frame's selection.
                for state in group.all_states():
                    _remember(state, *state.pending, record)
                    state.pending = None
            res.previous_gbuffer = prep.gbuffer
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
            for res in self.resolutions
            for group in res.variants
            for s in group.all_states()
        }


@dataclass
class _References:
    """What one variant's rows are measured against in a frame: the ``all`` reference's
    output and its sequence's warped error map at this frame (None on the first frame),
    the ``rt`` output, the reflector pixels of this frame and the pixels the warp kept
    ((H, W) bool; None on the first frame)."""

    ref: FrameOutput
    ref_warped: np.ndarray | None
    rt: FrameOutput
    reflector_px: np.ndarray
    warped_px: np.ndarray | None


def _row(
    stage: str,
    state: _ConfigState,
    output: FrameOutput,
    flip_ref: np.ndarray,
    warped_map: np.ndarray | None,
    temporal_map: np.ndarray | None,
    refs: _References,
    selection: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> dict:
    """One CSV row. flip_ref: (H, W) FLIP of this output against the ``all`` reference
    ``refs.ref``; warped_map: (H, W) this output's sequence's warped error map
    (``temporal_error.WarpedSequence``), temporal_map: its ``popping_map`` against the
    reference's, both None on the first frame (the temporal columns are then blank);
    selection: this frame's (selected, visible, levels), see ``_selection_row``.
    ``transitions`` and ``density_steps``: from the configuration's previous frame into
    this one (``selection_metrics``; 0 on its first frame)."""
    st = output.stats
    cfg = state.config
    transitions = steps = 0
    if state.previous is not None:
        pairs = zip(state.previous, selection, strict=True)
        selected, visible, levels = (np.stack(pair) for pair in pairs)
        transitions = int(transitions_per_frame(selected, visible)[-1])
        steps = density_steps(selected, visible, levels)
    heuristic = {"rt": "all", "raster": "none"}.get(cfg.mode, cfg.heuristic)
    temporal = dict.fromkeys(TEMPORAL_COLUMNS, "")
    if temporal_map is not None:
        kept = refs.warped_px
        temporal = {
            "warped_error": round(mean_over(warped_map, kept), 6),
            "warped_error_reference": round(mean_over(refs.ref_warped, kept), 6),
            "temporal_error": round(mean_over(temporal_map, kept), 6),
            "temporal_error_reflectors": round(
                mean_over(temporal_map, kept & refs.reflector_px), 6
            ),
        }
    return {
        "stage": stage,
        "config": cfg.label,
        "heuristic": heuristic,
        "mode": cfg.mode,
        "budget_ms": _blank(cfg.budget_ms),
        "budget_rays": _blank(cfg.budget_rays),
        "resolution": f"{state.options.width}x{state.options.height}",
        "bounce_limit": state.options.bounce_limit,
        # The variant's density: its references (all, rt) trace every pixel whatever it is.
        "trace_density": (cfg.variant.trace_density if cfg.variant else "full"),
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
        "density_steps": steps,
        "flip": round(mean_over(flip_ref), 6),
        "flip_reflectors": round(mean_over(flip_ref, refs.reflector_px), 6),
        "psnr": round(psnr(refs.ref.beauty, output.beauty), 4),
        "flip_rt": round(mean_over(flip_map(refs.rt.beauty, output.beauty)), 6),
        "psnr_rt": round(psnr(refs.rt.beauty, output.beauty), 4),
        **temporal,
    }


def _blank(value):
    """CSV cell: empty for None (an unbounded budget)."""
    return "" if value is None else value


def _remember(
    state: _ConfigState,
    output: FrameOutput,
    selection: tuple[np.ndarray, np.ndarray, np.ndarray],
    record: bool = True,
) -> None:
    """Keep this frame's (selected, visible, levels) for the next frame's row."""
    selected, visible, _levels = selection
    state.previous = selection
    if record:
        state.timeline_selected.append(selected.tolist())
        state.timeline_visible.append(visible.tolist())


def _selection_row(
    output: FrameOutput, reflectors: list[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(selected, visible) of one rendered frame, each (R,) bool over ``reflectors``, and
    (R,) int64 levels (``selection_metrics.density_levels``)."""
    selected, visible = set(output.stats.selected), set(output.stats.visible)
    return (
        np.array([p in selected for p in reflectors], dtype=bool),
        np.array([p in visible for p in reflectors], dtype=bool),
        density_levels(output.stats.densities, reflectors),
    )


def _write_report_images(
    out: Path,
    stage: str,
    t: float,
    label: str,
    output: FrameOutput,
    error: np.ndarray,
    temporal: np.ndarray | None,
) -> None:
    """Preview PNG, FLIP error map and temporal error map (``popping_map``; none on the
    first frame), both (H, W) in [0, 1], of one configuration's frame, in magma."""
    import matplotlib

    folder = out / IMAGES_DIR / stage / f"{t:g}"
    folder.mkdir(parents=True, exist_ok=True)
    write_preview_png(folder / f"{label}.png", output.beauty)
    maps = [(FLIP_MAP_SUFFIX, error)]
    if temporal is not None:
        maps.append((TEMPORAL_MAP_SUFFIX, temporal))
    for suffix, values in maps:
        magma = matplotlib.colormaps["magma"](np.clip(values, 0.0, 1.0))[..., :3]
        # The error map is already display-referred: written without the tone map.
        _write_display_png(folder / f"{label}{suffix}.png", magma.astype(np.float32))


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
