"""A least-recently-used memo in a caller's ``OrderedDict`` (the engines' per-instance memos: plain values, never
state)."""

from __future__ import annotations

from collections import OrderedDict


def recent(memo: OrderedDict, key, build, keep: int):
    """The value of ``build()`` for the hashable ``key``, kept in ``memo`` with at most ``keep`` entries (the least
    recently used dropped first): a hit is moved to the end and returned as it was built."""
    hit = memo.get(key)
    if hit is None:
        hit = build()
        memo[key] = hit
        while len(memo) > keep:
            memo.popitem(last=False)
    else:
        memo.move_to_end(key)
    return hit
