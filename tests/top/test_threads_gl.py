"""The one thread setting (``--threads``, ``threads=``), the OpenGL platform (``--gl``) and
what startup loads: bad values are one line, the setting reaches llvmpipe and OpenBLAS
and is recorded, EGL renders the pixels OSMesa renders, the CLI module loads no OpenGL or
Embree, a raster render builds no BVH.

Renders run in subprocesses: llvmpipe reads its thread count and PyOpenGL its platform
once per process, and this test process already chose OSMesa (conftest)."""

import json
import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np
import pytest
from repo_paths import REPO
from scenes import mirror_floor_stage
from typer.testing import CliRunner

from phrt_usd.api import render_options
from phrt_usd.cli import app
from phrt_usd.engine.raster.gl_platform import egl_problem
from phrt_usd.errors import BadOption
from phrt_usd.run.images import read_frame_exr

CLI = [sys.executable, "-m", "typer", "phrt_usd.cli", "run"]
#: Modules a cheap start must not load: OpenGL, pyrender (trimesh, scipy, networkx),
#: Embree, the image library, the plots, the cluster and rich (tables printed at the end).
HEAVY = ("OpenGL", "pyrender", "trimesh", "embreex", "OpenImageIO", "scipy", "matplotlib",
         "dask", "networkx", "rich")  # fmt: skip


def _env() -> dict[str, str]:
    """The environment of a child render: its own platform choice (not conftest's), and
    bytecode cached outside the repo so that each child does not recompile every module
    (this machine sets PYTHONDONTWRITEBYTECODE)."""
    env = dict(os.environ)
    env.pop("PYOPENGL_PLATFORM", None)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    env["PYTHONPYCACHEPREFIX"] = str(Path(tempfile.gettempdir()) / "phrt-test-pycache")
    return env


def _python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                          text=True, timeout=120, cwd=REPO, env=_env())  # fmt: skip


@pytest.fixture(scope="module")
def stage(tmp_path_factory) -> Path:
    return mirror_floor_stage(tmp_path_factory.mktemp("threads") / "floor.usda", 64, 48)


@pytest.mark.slow
def test_startup_loads_only_what_the_mode_needs(stage, tmp_path):
    """``import phrt_usd.cli`` (every command's start, ``--help`` included) loads none of
    HEAVY, ``import phrt_usd.api`` only the image library, and an ``rt`` render adds
    Embree but no OpenGL, pyrender or its trimesh / scipy / networkx (no raster phase:
    no GL context, ``gl`` None): the rest is imported by the parts that need it."""
    done = _python(f"""
        import json, sys
        heavy = {HEAVY!r}
        def loaded():
            return sorted({{m.split(".")[0] for m in sys.modules}} & set(heavy))
        import phrt_usd.cli
        cli = loaded()
        import phrt_usd.api
        api = loaded()
        s = phrt_usd.render({str(stage)!r}, {str(tmp_path / "rt")!r}, mode="rt").summary
        print(json.dumps([cli, api, loaded(), s["gl"], s["llvmpipe_threads"]]))
    """)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.splitlines()[-1]) == [
        [],
        ["OpenImageIO"],
        ["OpenImageIO", "embreex"],
        None,
        None,
    ]


@pytest.mark.slow
@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--threads", "0"], "--threads must be in 1..1024, got 0"),
        (["--threads", "two"], "--threads 'two': expected a whole number"),
        (["--threads", "5000"], "--threads must be in 1..1024"),
        (["--gl", "vulkan"], "gl must be one of auto, egl, osmesa, got 'vulkan'"),
    ],
)
def test_bad_thread_and_gl_values_are_one_line_exit_2(stage, tmp_path, args, needle):
    result = CliRunner().invoke(app, ["render", str(stage), "--out", str(tmp_path / "o"), *args])
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], lines
    assert not (tmp_path / "o").exists()  # refused before anything was written


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--threads", "0"], "--threads must be in 1..1024, got 0"),
        (["--gl", "metal"], "gl must be one of auto, egl, osmesa, got 'metal'"),
    ],
)
def test_sweep_bad_thread_and_gl_values_are_one_line_exit_2(stage, tmp_path, args, needle):
    out = tmp_path / "sweep"
    argv = ["sweep", str(stage), "--budgets-rays", "100", "--out", str(out), *args]
    result = CliRunner().invoke(app, argv)
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], lines
    assert not out.exists()


@pytest.mark.parametrize("value", [0, -1, 1.5, True, "2", 2000])
def test_api_threads_bad_values(stage, value):
    from pxr import Usd

    with pytest.raises(BadOption, match="threads"):
        render_options(Usd.Stage.Open(str(stage)), threads=value)


@pytest.mark.slow
def test_threads_reach_openblas_numba_and_the_environment():
    """``apply_threads`` sets the OpenBLAS numpy loaded (read back through its own
    getter) and the load-time variables; numba follows when it is loaded."""
    done = _python("""
        import ctypes, json, os
        import numpy
        from phrt_usd.threads import apply_threads
        maps = open("/proc/self/maps").read().split()
        lib = next(p for p in maps if "openblas" in p.lower() and ".so" in p)
        blas = ctypes.CDLL(lib)
        get = next(getattr(blas, n) for n in ("scipy_openblas_get_num_threads64_",
                   "openblas_get_num_threads64_", "openblas_get_num_threads") if hasattr(blas, n))
        seen = []
        for n in (1, 2, 1):
            apply_threads(n)
            seen.append([get(), os.environ["LP_NUM_THREADS"], os.environ["OMP_NUM_THREADS"]])
        print(json.dumps(seen))
    """)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == [[1, "1", "1"], [2, "2", "2"], [1, "1", "1"]]


@pytest.mark.slow
def test_threads_and_gl_end_to_end(stage, tmp_path):
    """API (OSMesa, 1 thread) and CLI (EGL when this machine has a working EGL device,
        2 threads) render the same raster frame: the settings are recorded in the summary
        and stats.json, llvmpipe runs as many render threads as asked (counted in the
        process), a raster render builds no BVH (phrt's Embree module is never loaded; pyrender's
    trimesh imports embreex itself), and EGL's pixels equal
        OSMesa's exactly (both are Mesa's llvmpipe here: same rasterizer, same shaders)."""
    api_out = tmp_path / "api"
    done = _python(f"""
        import json, sys
        import phrt_usd
        result = phrt_usd.render({str(stage)!r}, {str(api_out)!r}, mode="raster", threads=1,
                                 gl="osmesa")
        s = result.summary
        print(json.dumps({{"threads": s["threads"], "gl": s["gl"],
                          "llvmpipe_threads": s["llvmpipe_threads"],
                          "bvh": "phrt_usd.engine.trace.bvh" in sys.modules}}))
    """)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.splitlines()[-1]) == {
        "threads": 1, "gl": "osmesa", "llvmpipe_threads": 1, "bvh": False,
    }  # fmt: skip
    run = json.loads((api_out / "stats.json").read_text())["run"]
    assert (run["threads"], run["gl"], run["llvmpipe_threads"]) == (1, "osmesa", 1)

    cli_out = tmp_path / "cli"
    args = ["render", str(stage), "--out", str(cli_out), "--mode", "raster", "--threads", "2",
            "--gl", "egl", "--json"]  # fmt: skip
    cli = subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=120, env=_env())
    problem = egl_problem()
    if problem is not None:  # no EGL device here: one clear line, exit 1, nothing faked
        lines = cli.stderr.strip().splitlines()
        assert cli.returncode == 1 and len(lines) == 1
        assert lines[0] == f"error: --gl egl: no working EGL device here: {problem}"
        return
    assert cli.returncode == 0, cli.stderr
    summary = json.loads(cli.stdout)
    assert (summary["threads"], summary["gl"], summary["llvmpipe_threads"]) == (2, "egl", 2)
    a = read_frame_exr(api_out / "frames" / "0001.exr")
    b = read_frame_exr(cli_out / "frames" / "0001.exr")
    assert set(a) == set(b)
    for name in a:
        assert np.array_equal(a[name], b[name]), name  # depth: inf equals inf


def test_shading_pool_follows_the_setting(monkeypatch):
    """Local shading splits a large batch over the process's setting (3 workers here,
    an uneven split on any machine) and gives the same pixels as one thread."""
    from phrt_usd.engine import shading
    from phrt_usd.model.scene import DistantLight, Lights
    from phrt_usd.threads import DEFAULT_THREADS, LOAD_TIME_VARIABLES, apply_threads

    for name in LOAD_TIME_VARIABLES:  # restored after the test
        monkeypatch.setenv(name, os.environ.get(name, str(DEFAULT_THREADS)))
    rng = np.random.default_rng(3)
    n = 2 * shading.SHADE_MIN_THREADED_POINTS
    pos = rng.normal(size=(n, 3))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    albedo = rng.uniform(size=(n, 3)).astype(np.float32)
    view = -nrm
    lights = Lights(distant=[DistantLight(np.array([0.3, -1.0, 0.2]), np.full(3, 2.0))])
    vis = np.ones((n, 1), dtype=np.float32)
    monkeypatch.setattr(shading, "SHADE_THREADS", None)
    try:
        images = []
        for threads in (3, 1):
            apply_threads(threads)
            images.append(shading.shade_local(pos, nrm, albedo, view, np.zeros(3), lights, vis))
            if threads == 3:
                assert set(shading._POOL) == {3}
    finally:
        apply_threads(DEFAULT_THREADS)
    # 1 ulp: numpy's SIMD loops may round a chunk's ends differently (test_shading.py).
    np.testing.assert_allclose(images[0], images[1], rtol=1e-6, atol=1e-7)
    assert float(images[0].max()) > 0.0


@pytest.mark.slow
def test_egl_contexts_of_one_process_outlive_each_other(stage):
    """EGL hands every context of a device the same display; closing one renderer must
    not end the others (pyrender's own EGL platform terminates the display with each
    context, which fails the next one): two renderers, the first closed before the
    second renders, then a third; all render the same pixels. Without EGL here: the
    one-line refusal."""
    done = _python(f"""
        import json
        import numpy as np
        import phrt_usd
        from phrt_usd.errors import PhrtError
        try:
            a = phrt_usd.open({str(stage)!r}, mode="raster", gl="egl")
        except PhrtError as exc:
            print(json.dumps({{"refused": str(exc)}}))
            raise SystemExit(0)
        b = phrt_usd.open({str(stage)!r}, mode="raster", gl="egl")
        first = a.render(1.0).beauty
        a.close()
        second = b.render(1.0).beauty
        b.close()
        with phrt_usd.open({str(stage)!r}, mode="raster", gl="egl") as c:
            third = c.render(1.0).beauty
        print(json.dumps({{"same": [bool(np.array_equal(first, second)),
                                   bool(np.array_equal(first, third))],
                          "lit": float(first.max())}}))
    """)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout.splitlines()[-1])
    problem = egl_problem()
    if problem is not None:
        assert result == {"refused": f"--gl egl: no working EGL device here: {problem}"}
        return
    assert result["same"] == [True, True] and result["lit"] > 0.0


def test_shader_programs_compile_once(stage):
    """Every raster pass's programs come from the context's cache: after the first
    frame no frame compiles one (pyrender's own cache keys by a context pointer that
    OSMesa hands out anew on every call, so it would compile, and leak, per frame)."""
    import phrt_usd

    with phrt_usd.open(stage, frames="1:4", mode="hybrid") as renderer:
        cache = renderer._renderer._rasterizer._ctx.renderer._program_cache._program_cache
        sizes = []
        for t in (1.0, 1.0, 1.0, 1.0):
            renderer.render(t)
            sizes.append(len(cache))
    assert sizes[0] >= 2 and sizes == [sizes[0]] * 4, sizes  # id pass + shadow depth at least
