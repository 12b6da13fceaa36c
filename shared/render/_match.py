"""Kernel that finds a point by its integer position: which source point each tile point is.

The COPC export carries the properties the tiles do not (``confidence``, ``view``...) by
looking every tile point up among the source cloud's points quantised the same way.
"""

from __future__ import annotations

import numba


@numba.njit(cache=True, inline="always")
def _less(a, i, b, j) -> bool:
    """Row ``i`` of ``a`` before row ``j`` of ``b`` (x, then y, then z)."""
    for k in range(3):
        if a[i, k] != b[j, k]:
            return a[i, k] < b[j, k]
    return False


@numba.njit(cache=True)
def match_points(sorted_q, order, query, used, out) -> int:
    """For each row of ``query`` (M, 3) int32, the index (``order[...]``) of an equal row of
    ``sorted_q`` (N, 3) int32, rows sorted by x, y, z; ``used`` (N,) bool marks rows already
    given out, so coincident points each get their own. Returns how many found no match
    (their ``out`` is -1)."""
    n = sorted_q.shape[0]
    missing = 0
    for i in range(query.shape[0]):
        lo, hi = 0, n
        while lo < hi:  # first row not before the query
            mid = (lo + hi) // 2
            if _less(sorted_q, mid, query, i):
                lo = mid + 1
            else:
                hi = mid
        j = lo
        found = -1
        while j < n and not _less(query, i, sorted_q, j):  # equal rows from here on
            if not used[j]:
                used[j] = True
                found = order[j]
                break
            j += 1
        if found < 0:
            missing += 1
        out[i] = found
    return missing
