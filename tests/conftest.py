"""Shared fixtures: torch's thread count never leaks from one test into the next.

Results of some computations depend on torch's intra-op thread count (refine's trajectory, a fit's last digits), so a
test that leaves it changed makes the tests after it depend on their order. A test sets it with the
``set_torch_threads`` fixture, a module fixture with ``with torch_threads(n):`` (tests/torch_threads.py) around its
``yield``; :func:`torch_thread_count_is_restored` fails any test that leaks it.
"""

from __future__ import annotations

import sys

import pytest


@pytest.fixture
def set_torch_threads():
    """``set_torch_threads(n)``: torch runs with n intra-op threads for the rest of the test, then as before."""
    import torch  # here, not at the top: collecting the tests that never use torch does not import it

    before = torch.get_num_threads()
    yield torch.set_num_threads
    torch.set_num_threads(before)


@pytest.fixture(autouse=True)
def torch_thread_count_is_restored(request):
    """Fail a test that leaves torch's thread count changed, and restore it, so the next test starts as this one did."""
    torch = sys.modules.get("torch")  # not imported yet: the test starts from torch's own default
    if torch is None:
        yield
        return
    before = torch.get_num_threads()
    yield
    after = torch.get_num_threads()
    if after == before:
        return
    torch.set_num_threads(before)
    pytest.fail(f"{request.node.nodeid} left torch's thread count at {after} (it was {before}): set it with the "
                f"set_torch_threads fixture or torch_threads.torch_threads", pytrace=False)  # fmt: skip
