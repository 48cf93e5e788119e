"""``with torch_threads(n):``: torch's intra-op thread count for a block, restored after it.

Some results depend on the thread count (refine's trajectory, a fit's last digits), so a count a test leaves behind
changes the tests after it; tests/conftest.py fails a test that leaks it.
"""

from __future__ import annotations

from contextlib import contextmanager

import torch


@contextmanager
def torch_threads(count: int):
    """torch runs with ``count`` intra-op threads inside the block; the previous count comes back after it."""
    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)
