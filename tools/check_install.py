"""Install phrt-usd as a user would and check it keeps its promises there.

    python3 tools/check_install.py [--python PY ... | --python supported] [--work DIR]
        [--lowest] [--compare]

Builds the wheel (``uv build``), installs it with pip (the strict resolver) into a new
venv of each Python given with nothing else (no dev group, no extras), and there:

1. ``phrt --version``;
2. ``phrt kernels`` into an empty kernel cache (``PHRT_CACHE_DIR``): the first use
   compiles; then ``phrt kernels --check``: every kernel loads from the cache;
3. ``phrt render`` of two frames of the shipped demo stage (no stage given), whose
   ``--json`` summary says ``"kernels": "cached"``;
4. a throw-away project's pytest test through the plugin: a reference written with
   ``--phrt-update-references``, the unchanged render then passing, and a changed stage
   failing with its failure images written.

``--lowest``: install every runtime requirement at the lower bound of its range (the
oldest versions the package claims to work with) instead of the newest.

``--compare``: also time the first two-frame render of the demo (``--frames 521:522``)
in the installed copy and in this checkout's environment (``uv run phrt``), three runs
each, alternating; printed as medians (BENCHMARKS.md, "installed").

Exit 0 when every step holds, else 1 naming the step. CI runs it (``.ci/run``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

#: The throw-away project's stage: a mirror floor under a lit box, a camera, two frames.
STAGE = """#usda 1.0
(
    defaultPrim = "World"
    endTimeCode = 2
    metersPerUnit = 1
    startTimeCode = 1
    upAxis = "Y"
)

def Xform "World"
{
    def Mesh "Floor" (
        prepend apiSchemas = ["PhrtReflectorAPI", "MaterialBindingAPI"]
    )
    {
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 1, 2, 3]
        point3f[] points = [(-3, 0, -3), (-3, 0, 3), (3, 0, 3), (3, 0, -3)]
        float phrt:priority = 1
        rel material:binding = </World/Looks/Mirror>
    }

    def Cube "Box" (
        prepend apiSchemas = ["MaterialBindingAPI"]
    )
    {
        double size = 1
        double3 xformOp:translate = (0, 0.5, 0)
        uniform token[] xformOpOrder = ["xformOp:translate"]
        rel material:binding = </World/Looks/Paint>
    }

    def Scope "Looks"
    {
        def Material "Mirror"
        {
            token outputs:surface.connect = </World/Looks/Mirror/Surface.outputs:surface>
            def Shader "Surface"
            {
                uniform token info:id = "UsdPreviewSurface"
                color3f inputs:diffuseColor = (0.1, 0.1, 0.1)
                float inputs:metallic = 1
                float inputs:roughness = 0
                token outputs:surface
            }
        }

        def Material "Paint"
        {
            token outputs:surface.connect = </World/Looks/Paint/Surface.outputs:surface>
            def Shader "Surface"
            {
                uniform token info:id = "UsdPreviewSurface"
                color3f inputs:diffuseColor = PAINT
                token outputs:surface
            }
        }
    }

    def DistantLight "Sun"
    {
        float inputs:intensity = 3
        float3 xformOp:rotateXYZ = (-50, 30, 0)
        uniform token[] xformOpOrder = ["xformOp:rotateXYZ"]
    }

    def Camera "Cam"
    {
        float focalLength = 24
        double3 xformOp:translate.timeSamples = {1: (0, 1.5, 5), 2: (0.2, 1.5, 5)}
        float3 xformOp:rotateXYZ = (-15, 0, 0)
        uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:rotateXYZ"]
    }
}
"""

#: The throw-away project's test, as a pipeline would write it (docs/pipeline-tests.md).
TEST = """from pathlib import Path

from phrt_usd.pytest_plugin import assert_images_close

STAGE = Path(__file__).parent / "shot.usda"


def test_shot_renders_like_its_reference(phrt_render):
    result = phrt_render(STAGE, frames=1, budget_rays=100_000, resolution=(96, 72))
    assert_images_close(result.read_frame(1)["beauty"])  # the test's own reference file
"""


class Failed(Exception):
    """A step did not hold."""


def run(cmd: list, step: str, ok=(0,), **kwargs) -> subprocess.CompletedProcess:
    """Run ``cmd``; Failed (naming ``step``, with its output) when its exit code is not
    one of ``ok``."""
    done = subprocess.run(cmd, capture_output=True, text=True, **kwargs)
    if done.returncode not in ok:
        raise Failed(
            f"{step}: exit {done.returncode} from {' '.join(map(str, cmd))}\n"
            f"{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
        )
    return done


def build_wheel(work: Path) -> Path:
    dist = work / "dist"
    run(["uv", "build", "-q", "--wheel", "--out-dir", dist, str(REPO)], "build the wheel")
    (wheel,) = dist.glob("phrt_usd-*.whl")
    return wheel


def lower_bounds() -> list[str]:
    """``name==version`` of each runtime requirement's lower bound (pyproject.toml)."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    pins = []
    for requirement in project["dependencies"]:
        found = re.match(r"([A-Za-z0-9_.-]+)>=([0-9][^,;]*)", requirement)
        if found:
            pins.append(f"{found[1]}=={found[2]}")
    return pins


def install(python: str, wheel: Path, venv: Path, lowest: bool = False) -> Path:
    """A new venv with the wheel installed by pip (and pytest, which a project that tests
    with the plugin has); its bin directory. ``lowest``: each requirement at its lower
    bound."""
    run([python, "-m", "venv", venv], "make a venv")
    pip = [venv / "bin" / "python", "-m", "pip", "install", "-q", "--disable-pip-version-check"]
    pins = []
    if lowest:
        pins = lower_bounds()
        print(f"lower bounds: {' '.join(pins)}")
    run([*pip, wheel, *pins], "pip install the wheel")
    run([*pip, "pytest"], "pip install pytest")
    return venv / "bin"


def check(bin_dir: Path, work: Path) -> None:
    env = {**os.environ, "PHRT_CACHE_DIR": str(work / "cache")}
    env.pop("VIRTUAL_ENV", None)
    phrt = bin_dir / "phrt"
    version = run([phrt, "--version"], "phrt --version", env=env).stdout.strip()
    print(f"installed: {version}")

    start = time.perf_counter()
    first = run([phrt, "kernels"], "phrt kernels (first use compiles)", env=env)
    took = time.perf_counter() - start
    print(f"kernels compiled in {took:.1f} s: {first.stdout.splitlines()[-1]}")
    run([phrt, "kernels", "--check"], "phrt kernels --check (all in the cache)", env=env)

    out = work / "demo"
    done = run(
        [phrt, "-q", "render", "--frames", "521:522", "--out", out, "--json"],
        "phrt render of the shipped demo",
        env=env,
    )
    summary = json.loads(done.stdout)
    if summary.get("frames") != 2 or summary.get("kernels") != "cached":
        raise Failed(f"demo render: frames {summary.get('frames')}, kernels "
                     f"{summary.get('kernels')} (expected 2 and cached)")  # fmt: skip
    if "compiling" in done.stderr:
        raise Failed(f"demo render compiled kernels: {done.stderr}")
    print(f"demo: 2 frames, kernels cached, {len(list((out / 'frames').glob('*.exr')))} EXR")

    project = work / "project"
    project.mkdir()
    (project / "shot.usda").write_text(STAGE.replace("PAINT", "(0.8, 0.3, 0.1)"))
    (project / "test_shot.py").write_text(TEST)
    pytest = [bin_dir / "python", "-m", "pytest", "-q", "-p", "no:cacheprovider", project]
    run([*pytest, "--phrt-update-references"], "pytest --phrt-update-references", env=env,
        cwd=project)  # fmt: skip
    run(pytest, "pytest unchanged (must pass)", env=env, cwd=project)
    (project / "shot.usda").write_text(STAGE.replace("PAINT", "(0.1, 0.3, 0.8)"))
    run(pytest, "pytest on a changed stage (must fail)", ok=(1,), env=env, cwd=project)
    failures = sorted(
        p.name for p in project.rglob("*")
        if "phrt-failures" in p.parts and p.suffix in (".png", ".exr")
    )  # fmt: skip
    if not failures:
        raise Failed("pytest on a changed stage: no failure images written")
    print(f"plugin: reference written, unchanged passes, changed fails ({', '.join(failures)})")


def compare(bin_dir: Path, work: Path, runs: int = 3) -> None:
    """The first two-frame render of the demo, installed against this checkout."""
    commands = {
        "installed": [bin_dir / "phrt"],
        "checkout": ["uv", "run", "--project", REPO, "phrt"],
    }
    times: dict[str, list[float]] = {k: [] for k in commands}
    for k in range(runs):
        for name, phrt in commands.items():
            out = work / f"time-{name}-{k}"
            start = time.perf_counter()
            run([*phrt, "-q", "render", "--frames", "521:522", "--out", out, "--json"],
                f"timed render ({name})")  # fmt: skip
            times[name].append(time.perf_counter() - start)
    for name, values in times.items():
        shown = ", ".join(f"{v:.2f}" for v in values)
        print(f"first 2-frame demo render, {name}: median {statistics.median(values):.2f} s "
              f"({shown})")  # fmt: skip
    ratio = statistics.median(times["installed"]) / statistics.median(times["checkout"])
    print(f"installed / checkout: {ratio:.2f}")


#: The Pythons the package supports (pyproject.toml's requires-python).
SUPPORTED = ("3.11", "3.12", "3.13")


def supported_pythons() -> list[str]:
    """An interpreter of each SUPPORTED version found on this machine: ``pythonX.Y`` on
    PATH, else pyenv's newest ``X.Y.*`` (``$PYENV_ROOT``, ``~/.pyenv``)."""
    found = []
    pyenv = Path(os.environ.get("PYENV_ROOT", Path.home() / ".pyenv")) / "versions"
    for version in SUPPORTED:
        candidates = [shutil.which(f"python{version}")]
        candidates += [str(p) for p in sorted(pyenv.glob(f"{version}.*/bin/python3"))[::-1]]
        for candidate in filter(None, candidates):
            done = subprocess.run([candidate, "-c", "import sys, venv; print(sys.version[:5])"],
                                  capture_output=True, text=True)  # fmt: skip
            if done.returncode == 0 and done.stdout.startswith(version + "."):
                found.append(candidate)
                break
        else:
            print(f"Python {version}: not on this machine, not checked")
    return found


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--python", action="append",
                        help="the Python of a new venv (repeatable; default python3; "
                             "'supported': each of 3.11-3.13 found here)")  # fmt: skip
    parser.add_argument("--work", type=Path, help="keep the venvs and outputs here")
    parser.add_argument("--compare", action="store_true", help="time installed vs checkout")
    parser.add_argument("--lowest", action="store_true", help="requirements at lower bounds")
    args = parser.parse_args()
    pythons = args.python or ["python3"]
    if "supported" in pythons:
        pythons = supported_pythons()
    work = args.work or Path(tempfile.mkdtemp(prefix="phrt-install-"))
    try:
        wheel = build_wheel(work)
        for k, python in enumerate(pythons):
            start = time.perf_counter()
            here = work / f"python-{k}"
            here.mkdir(parents=True, exist_ok=True)
            bin_dir = install(python, wheel, here / "venv", args.lowest)
            version = run([bin_dir / "python", "--version"], "python --version").stdout.strip()
            print(f"{version}: installed {wheel.name} with pip in "
                  f"{time.perf_counter() - start:.0f} s")  # fmt: skip
            check(bin_dir, here)
            if args.compare:
                compare(bin_dir, here)
    except Failed as failed:
        print(f"install check failed: {failed}", file=sys.stderr)
        return 1
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    print(f"install check passed ({len(pythons)} Python(s))")
    return 0


if __name__ == "__main__":
    sys.exit(main())
