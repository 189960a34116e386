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
