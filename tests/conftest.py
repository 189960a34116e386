import os

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")


import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="session")
def _kernels_called_as_built():
    """Every kernel call of the suite matched its ahead-of-time build's argument types
    (a mismatch falls back to the JIT kernel at run time: ``phrt_usd.kernels._Guarded``;
    here it is a failure, so a caller passing other dtypes is found)."""
    yield
    from phrt_usd import kernels

    assert not kernels.FALLBACKS, f"kernels called with other argument types: {kernels.FALLBACKS}"
