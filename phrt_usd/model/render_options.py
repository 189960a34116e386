"""The render options, declared once, and the options a render runs with.

``OPTIONS`` is the one table of render options (as hdEmbree's ``config.cpp`` declares its
render settings): each option's name, type, default, range or choices, help, and the
``PhrtRenderSettingsAPI`` attribute a stage sets it with. Everything that states an option
reads it here: the checks (``RenderOption.check``, through ``phrt_usd.checks``), the API's
names and the stage's settings under its overrides (``phrt_usd.api``, ``usd.schema``'s
defaults), the CLI's ``render`` and ``sweep`` options (help and defaults), ``SweepSpec``,
and docs/api.md's option table (tests/model/test_render_options.py checks it against this).

The options a render runs with come in two parts (as pbrt-v4 splits ``BasicPBRTOptions``
from ``PBRTOptions``): ``SetupOptions``, what a render is set up with once (mode, frame
size, threads, OpenGL platform, the G-buffer's source), and ``FrameOptions``, what each
frame's selection, tracing and images read (heuristic, budgets, target frame rate, bounce
limit, selection weight, trace density, screen space, exposure). ``RenderOptions`` is
both, built with every option by name as before (``RenderOptions(mode="rt",
budget_rays=500)``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

from phrt_usd.checks import (
    check_choice,
    check_finite,
    check_integer,
    check_number,
    check_range,
    check_token,
)
from phrt_usd.errors import BadOption
from phrt_usd.model.trace_density import TRACE_DENSITIES
from phrt_usd.threads import DEFAULT_THREADS, MAX_THREADS

#: The two parts of the options: set up once, or read by every frame.
SETUP, FRAME = "setup", "frame"

#: Rendering modes: hybrid (raster G-buffer, traced reflections of the selected
#: reflectors), rt (everything traced: the reference), raster (nothing traced).
MODES = ("hybrid", "rt", "raster")
#: Selection policies (``select.policies.make_policy``).
HEURISTICS = ("heu1", "heu2", "all", "none", "heu3")
#: OpenGL platforms of the raster phase (``engine.raster.gl_platform``).
GL_PLATFORMS = ("auto", "egl", "osmesa")
#: Sources of the G-buffer (``engine.primary_source``).
PRIMARY_SOURCES = ("auto", "raster", "rays")
#: Screen-space reflections before Embree (``engine.trace.screen_space``): off or on.
SCREEN_SPACE = ("off", "on")
#: Recursion depth beyond which extra bounces change nothing visible.
MAX_BOUNCE_LIMIT = 16
#: Largest frame side in pixels (OpenGL's usual maximum framebuffer size).
MAX_RESOLUTION_SIDE = 16384
#: Largest frame in pixels: the G-buffer, shading planes and images take ~100 bytes a
#: pixel, so 2**26 pixels (e.g. 8192x8192) already need several GB.
MAX_RESOLUTION_PIXELS = 2**26
#: Largest --budget-rays: far above any frame's need (a 2**26-pixel frame at 16 bounces
#: casts ~1e9 rays) and small enough for every int64 figure and USD's integer metadata.
MAX_BUDGET_RAYS = 10**12
#: Highest --target-fps: a period of 1 ms is far below any frame's raster here.
MAX_TARGET_FPS = 1000.0
#: Largest |--exposure| in EV; larger values are clamped to it (with a warning): 2^40
#: (~1e12) already maps a 1e-6 radiance to display white or a 1e6 one to black, and
#: keeps ordinary radiance times the scale far inside float32 (max 3.4e38).
MAX_EXPOSURE_EV = 40.0


@dataclass(frozen=True)
class RenderOption:
    """One render option: the ``RenderOptions`` field and API keyword ``name``.

    ``kind``: str, int or float; ``default``: its value when neither the stage's settings
    nor the caller give one (None: not used, for a budget unbounded); ``nullable``: None
    is a value; ``choices`` (str) or ``low`` .. ``high`` (numbers; ``low_open``: low
    itself excluded; neither: any finite number); ``tokens``: the choices are USD tokens,
    matched exactly (else in any case); ``label``: what a range or choice message calls
    the option (default ``name``); ``unit``: of a number without a range; ``help``: the
    CLI's help; ``cli``: its CLI option (None: given another way, e.g. ``--resolution``);
    ``metavar``: how the CLI shows its value; ``schema_attribute``: the
    ``PhrtRenderSettingsAPI`` attribute a stage sets it with, and ``schema_unset``, that
    attribute's value for "not used" (``default`` None); ``default_doc``: the default
    as the docs state it when it depends on the machine."""

    name: str
    kind: type
    default: Any
    group: str
    help: str
    cli: str | None = None
    label: str | None = None
    choices: tuple[str, ...] = ()
    tokens: bool = False
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    unit: str | None = None
    nullable: bool = False
    metavar: str | None = None
    schema_attribute: str | None = None
    schema_unset: Any = None
    default_doc: str | None = None

    @property
    def message_name(self) -> str:
        return self.label or self.name

    def check(self, value: Any) -> Any:
        """``value`` as this option holds it (an int, a float, a lower-case word);
        ``BadOption`` (one line) for a value of the wrong kind or out of range. A wrong
        kind is named by ``name`` (the keyword given), a range by ``label``."""
        if value is None and self.nullable:
            return None
        if self.kind is str:
            checker = check_token if self.tokens else check_choice
            return checker(value, self.choices, self.message_name)
        if self.kind is int:
            value = check_integer(value, self.name)
        else:
            value = check_number(value, self.name)
        if self.low is None:
            what = f"a finite number of {self.unit}" if self.unit else "a finite number"
            return check_finite(value, self.message_name, what)
        return check_range(value, self.low, self.high, self.message_name, low_open=self.low_open)

    def doc_values(self) -> str:
        """The values it takes, as docs/api.md's option table states them."""
        if self.choices:
            return ", ".join(f'`"{c}"`' for c in self.choices)
        kind = self.kind.__name__
        if self.low is None:
            return f"{kind} ({self.unit})" if self.unit else kind
        if self.high is None:
            return f"{kind} {'>' if self.low_open else '≥'} {_number(self.low)}"
        if self.kind is int:
            return f"{kind} {_number(self.low)}..{_number(self.high)}"
        low = "(" if self.low_open else "["
        return f"{kind} in {low}{_number(self.low)}, {_number(self.high)}]"

    def doc_default(self) -> str:
        """The default, as docs/api.md's option table states it."""
        if self.default_doc is not None:
            return self.default_doc
        if self.default is None:
            return "none"
        if isinstance(self.default, str):
            return f'`"{self.default}"`'
        return f"`{_number(self.default)}`"


def _number(value: float) -> str:
    """A bound or default as text: ``10``, ``0.0001``, ``10^12``."""
    if isinstance(value, int) and value >= 10**6 and str(value).rstrip("0") == "1":
        return f"10^{len(str(value)) - 1}"
    return f"{value:g}" if isinstance(value, float) else str(value)


#: The render options, in the order the API lists them.
OPTIONS: dict[str, RenderOption] = {o.name: o for o in (
    RenderOption(
        "mode", str, "hybrid", SETUP, "raster | hybrid | rt.", cli="--mode",
        choices=MODES, tokens=True, schema_attribute="phrt:mode",
    ),
    RenderOption(
        "heuristic", str, "heu1", FRAME, "heu1 | heu2 | heu3 | all | none.",
        cli="--heuristic", choices=HEURISTICS, tokens=True, schema_attribute="phrt:heuristic",
    ),
    # The frame size (--resolution WxH, or the settings prim's resolution): its range is
    # the frame's, both sides together (check_resolution).
    RenderOption("width", int, 320, SETUP, "WxH, e.g. 320x240."),
    RenderOption("height", int, 240, SETUP, "WxH, e.g. 320x240."),
    RenderOption(
        "budget_ms", float, 10.0, FRAME, "Trace budget T per frame in ms (inf: unbounded).",
        cli="--budget-ms", label="--budget-ms", low=0.0, nullable=True,
        schema_attribute="phrt:budgetMs",
    ),
    RenderOption(
        "budget_rays", int, None, FRAME, "Trace budget in rays per frame (deterministic).",
        cli="--budget-rays", label="--budget-rays", low=0, high=MAX_BUDGET_RAYS, nullable=True,
        schema_attribute="phrt:budgetRays", schema_unset=-1,
    ),
    RenderOption(
        "bounce_limit", int, 5, FRAME, "Reflection bounce limit.", cli="--bounce-limit",
        label="bounce limit", low=0, high=MAX_BOUNCE_LIMIT, schema_attribute="phrt:bounceLimit",
    ),
    RenderOption(
        "selection_weight", float, 0.0001, FRAME, "I, the weight of the previous selection.",
        cli="--selection-weight", label="selection weight I", low=0.0,
        schema_attribute="phrt:selectionWeight",
    ),
    RenderOption(
        "threads", int, DEFAULT_THREADS, SETUP,
        "Threads of every pool, Embree batch, llvmpipe and BLAS (default: the cores this "
        "process may use).",
        cli="--threads", low=1, high=MAX_THREADS, metavar="N",
        default_doc="the cores this process may use",
    ),
    RenderOption(
        "gl", str, "auto", SETUP,
        "OpenGL platform of the raster phase (auto: EGL when a working EGL device is found, "
        "else OSMesa).",
        cli="--gl", choices=GL_PLATFORMS, metavar="|".join(GL_PLATFORMS),
    ),
    RenderOption(
        "primary", str, "auto", SETUP,
        "Source of the G-buffer: the raster id pass or Embree primary rays (auto: rays on a "
        "software rasterizer for stages of more triangles than pixels; rt mode: rays).",
        cli="--primary", choices=PRIMARY_SOURCES, metavar="|".join(PRIMARY_SOURCES),
    ),
    RenderOption(
        "trace_density", str, "full", FRAME,
        "Pixels of a traced reflector that start rays: every one, or for reflectors of 64+ "
        "pixels k/16 of them (k = 1..15; named: a checkerboard half, one in each 2x2 block "
        "quarter, the checkerboard of those eighth, one in each 4x4 block sixteenth), the "
        "others reused from the previous frame or interpolated from their traced "
        "neighbours (hybrid mode).",
        cli="--trace-density", label="trace density", choices=TRACE_DENSITIES,
        metavar="|".join(TRACE_DENSITIES),
    ),
    RenderOption(
        "screen_space", str, "off", FRAME,
        "Screen-space reflections first: each first reflection ray marched through the "
        "G-buffer (up to 32 pixels), Embree only for what that cannot resolve (hybrid "
        "mode; off by default: on a 2-core CPU the march costs more than the rays it "
        "saves, docs/screen-space.md).",
        cli="--screen-space", label="screen space", choices=SCREEN_SPACE,
        metavar="|".join(SCREEN_SPACE),
    ),
    RenderOption(
        "target_fps", float, None, FRAME,
        "Frame rate to hold: T = what raster and shading leave of 1000/F ms.",
        cli="--target-fps", label="--target-fps", low=0.0, low_open=True, high=MAX_TARGET_FPS,
        nullable=True, schema_attribute="phrt:targetFps", schema_unset=0.0,
    ),
    RenderOption(
        "exposure", float, 0.0, FRAME,
        f"Scale the image radiance by 2^EV before writing (the EXR too); "
        f"|EV| <= {MAX_EXPOSURE_EV:g}.",
        cli="--exposure", label="--exposure", unit="EV", metavar="EV",
    ),
)}  # fmt: skip


def _default(name: str) -> Any:
    return OPTIONS[name].default


def _check_part(options: Any, group: str) -> None:
    """Every field of ``options`` in ``group`` through its option's check, in the
    table's order; the checked value replaces the given one."""
    for option in OPTIONS.values():
        if option.group == group:
            setattr(options, option.name, option.check(getattr(options, option.name)))


def check_resolution(width: int, height: int) -> None:
    """BadOption (one line) for a frame size out of range (a side, or the pixels)."""
    side = MAX_RESOLUTION_SIDE
    if not (1 <= width <= side and 1 <= height <= side):
        raise BadOption(f"resolution {width}x{height} out of range 1..{side}")
    if width * height > MAX_RESOLUTION_PIXELS:
        raise BadOption(
            f"resolution {width}x{height}: more than {MAX_RESOLUTION_PIXELS} pixels a frame"
        )


@dataclass
class SetupOptions:
    """What a render is set up with, once. Checked when made (``BadOption``, one line)."""

    mode: str = _default("mode")
    width: int = _default("width")
    height: int = _default("height")
    #: Threads of every pool, llvmpipe, OpenBLAS and numba (``phrt_usd.threads``).
    threads: int = _default("threads")
    #: OpenGL platform of the raster phase: auto | egl | osmesa (auto: EGL when a working
    #: EGL device is found, else OSMesa; ``engine.raster.gl_platform``).
    gl: str = _default("gl")
    #: Source of the G-buffer: auto | raster | rays (``engine.primary_source``).
    primary: str = _default("primary")

    def __post_init__(self) -> None:
        self._check_setup()

    def _check_setup(self) -> None:
        _check_part(self, SETUP)
        check_resolution(self.width, self.height)
        if self.mode == "rt" and self.primary == "raster":
            raise BadOption("--primary raster: rt mode traces every ray, its primary rays too")


@dataclass
class FrameOptions:
    """What every frame's selection, tracing and images read. ``None`` budgets are
    unbounded. Checked when made (``BadOption``, one line)."""

    heuristic: str = _default("heuristic")
    budget_ms: float | None = _default("budget_ms")
    budget_rays: int | None = _default("budget_rays")
    #: Frame rate to hold (``--target-fps``): each frame's T is the frame period less the
    #: frame's measured raster and shading and the previous frame's selection, less
    #: ``engine.renderer.TARGET_FPS_MARGIN`` of the period. Exclusive with ``budget_ms``.
    target_fps: float | None = _default("target_fps")
    bounce_limit: int = _default("bounce_limit")
    selection_weight: float = _default("selection_weight")
    #: Pixels of a traced reflector that start rays: full | half | quarter | sixteenth (of
    #: reflectors of 64+ pixels; the others filled from their traced neighbours:
    #: ``engine.trace.sparse_pixels``).
    trace_density: str = _default("trace_density")
    #: Screen-space reflections before Embree: off | on (``engine.trace.screen_space``).
    screen_space: str = _default("screen_space")
    #: ``--exposure EV``: every frame's radiance is scaled by 2**EV before it is written
    #: (EXR and PNG alike); |EV| beyond MAX_EXPOSURE_EV is clamped (``exposure_ev``).
    exposure: float = _default("exposure")

    def __post_init__(self) -> None:
        self._check_frame()

    def _check_frame(self) -> None:
        _check_part(self, FRAME)
        if self.target_fps is not None and self.budget_ms is not None:
            raise BadOption("--budget-ms and --target-fps both given: use one of them")

    @property
    def exposure_ev(self) -> float:
        """``exposure`` clamped to +-MAX_EXPOSURE_EV (what the render applies)."""
        return min(max(self.exposure, -MAX_EXPOSURE_EV), MAX_EXPOSURE_EV)


@dataclass
class RenderOptions(SetupOptions, FrameOptions):
    """How to render: the set-up and the frame options together, made with any of the
    options by name; defaults are the table's (``OPTIONS``)."""

    def __post_init__(self) -> None:
        self._check_setup()
        self._check_frame()
        if self.mode == "rt" and self.trace_density != "full":
            raise BadOption(
                f"--trace-density {self.trace_density}: rt mode traces every pixel (hybrid only)"
            )
        if self.mode == "rt" and self.screen_space != "off":
            raise BadOption("--screen-space on: rt mode traces every ray (hybrid only)")

    @property
    def setup(self) -> SetupOptions:
        """The set-up part alone."""
        return SetupOptions(**{f.name: getattr(self, f.name) for f in fields(SetupOptions)})

    @property
    def frame(self) -> FrameOptions:
        """The frame part alone."""
        return FrameOptions(**{f.name: getattr(self, f.name) for f in fields(FrameOptions)})
