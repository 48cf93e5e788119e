"""Results memoised on the very tensors they were computed from.

The fit and the diagnosis simulate and compare the same frames hundreds of times; what depends only on a frame's
constant tensors (its speckle field, the real side of a comparison) is worth keeping. A key by content would cost a
hash of the tensors on every call; a key by ``id`` alone would go wrong when a tensor is freed and its id reused, or
changed in place. So an entry holds the tensors themselves (their ids cannot be reused while it lives) and is keyed
by their ids and version counters (an in-place change bumps the counter). The memo is a bounded dict: when full,
adding a key evicts the oldest entry.
"""

from __future__ import annotations

from typing import Callable, TypeVar

import torch

T = TypeVar("T")


def memoised(memo: dict, tensors: tuple[torch.Tensor, ...], key: tuple, capacity: int, compute: Callable[[], T]) -> T:
    """``compute()``, or its result stored in ``memo`` for these very ``tensors`` (unchanged) and ``key``.

    Args:
        memo: the dict that holds the entries (module-level, or on the object the tensors belong to).
        tensors: the tensors the result depends on.
        key: everything else the result depends on (hashable).
        capacity: at most this many entries.
        compute: computes the result. The stored result is shared: callers must not modify it.
    """
    full_key = (*(id(t) for t in tensors), *(t._version for t in tensors), *key)
    entry = memo.get(full_key)
    if entry is None or any(held is not given for held, given in zip(entry[0], tensors)):
        if full_key not in memo and len(memo) >= capacity:  # a stale entry under this key is overwritten
            memo.pop(next(iter(memo)))
        entry = memo[full_key] = (tuple(tensors), compute())
    return entry[1]
