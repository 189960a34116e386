"""small_pages turns numpy's huge-page request off inside its block only, nested too."""

from __future__ import annotations

import pytest

from phrt_usd import small_pages as sp


@pytest.mark.skipif(sp._set_madvise_hugepage is None, reason="numpy without the switch")
def test_small_pages_is_off_inside_and_restored_after():
    switch = sp._set_madvise_hugepage
    before = switch(True)  # a known state: numpy's default asks for huge pages
    try:
        with sp.small_pages():
            assert switch(False) is False  # off inside (the call reports the state)
            with sp.small_pages():
                assert switch(False) is False
            assert switch(False) is False  # still off after the inner block
        assert switch(True) is True  # restored after the outer block
    finally:
        switch(before)
