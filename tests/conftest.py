"""The suite, one folder a phase (model, usd, select, engine, run, evaluate, and top for
what spans them), each with its conftest; the modules here beside this file are the
builders and references the tests share (pytest puts this folder on ``sys.path``): scenes
and stages (``scenes.py``, ``textured_stages.py``), fake selection frames
(``selection_fakes.py``), a synthetic sweep (``synthetic_sweep.py``), the numpy forms the
kernels replaced (``numpy_paths.py``, ``*_reference.py``), shared thresholds
(``image_thresholds.py``) and the repository's folders (``repo_paths.py``). A test module
never imports another test module, and no two test files share a name.

``slow`` marks whole frames and camera paths, subprocesses (CLI, workers, browser) and
whatever else takes over about 0.2 s; ``uv run pytest -m "not slow"`` is the quick loop,
``./run tests`` the whole suite."""

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")


import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="session")
def _kernels_called_as_warmed_up():
    """Every kernel call of the suite used argument types its module's ``warm_up``
    compiles: then ``phrt kernels`` (which the set-up runs before any render) compiled all a
    render needs, and no render compiles a variant on the way (seconds each, uncached
    on a fresh installation). A caller passing other dtypes is found here."""
    from phrt_usd import kernels

    kernels.warm_up()
    warmed = kernels.signatures()
    yield
    extra = {
        name: sorted(map(str, found - warmed.get(name, set())))
        for name, found in kernels.signatures().items()
        if found - warmed.get(name, set())
    }
    assert not extra, f"kernels called with argument types warm_up does not compile: {extra}"
