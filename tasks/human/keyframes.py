"""Key-frames regularly spaced over a clip or a track (light: the tracking stage uses them too)."""

from __future__ import annotations

import numpy as np


def evenly_spaced(n: int, k: int) -> list[int]:
    """``min(n, k)`` indices of ``range(n)`` spread evenly, first and last included."""
    if n <= 0:
        return []
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, min(n, k))})


def regular_keyframes(timestamps: list[int], k: int) -> list[int]:
    """Indices of ``min(len, k)`` frames regularly spaced in time: for each of ``k`` times evenly
    spread from the first to the last timestamp (ascending), the nearest frame; evenly spaced
    indices instead when two times share a frame (irregular timestamps)."""
    n = len(timestamps)
    if n <= k:
        return list(range(n))
    t = np.asarray(timestamps, np.float64)
    pick = sorted({int(np.argmin(np.abs(t - target))) for target in np.linspace(t[0], t[-1], k)})
    return pick if len(pick) == k else evenly_spaced(n, k)
