"""Per-pixel combination of the frames of one view (depth cameras flicker; a median steadies)."""

from __future__ import annotations

import numpy as np

from .plan import COMBINE_METHODS


def combine_depths(depths, method: str = "median") -> np.ndarray:
    """Combine F depth frames (F, H, W) uint16 mm (0 = no measurement) into one (H, W) uint16.

    median : per pixel, the median of the valid (non-zero) values (the mean of the two middle
        values for an even count); 0 where no frame has a value.
    mean : the mean of the valid values.  first : the first frame unchanged.
    """
    stack = np.asarray(depths)
    if stack.ndim == 2:
        stack = stack[None]
    if stack.ndim != 3 or len(stack) == 0:
        raise ValueError(f"need (F, H, W) depth frames, got shape {stack.shape}")
    if method not in COMBINE_METHODS:
        raise ValueError(f"combine must be one of {', '.join(COMBINE_METHODS)}, got {method!r}")
    if method == "first" or len(stack) == 1:
        return stack[0].astype(np.uint16, copy=True)
    valid = stack != 0
    count = valid.sum(axis=0)
    if method == "mean":
        total = stack.sum(axis=0, dtype=np.uint32)
        out = np.divide(total, count, out=np.zeros(count.shape), where=count > 0)
        return np.round(out).astype(np.uint16)
    # Invalid pixels sort last (as the largest value), so the k valid ones come first.
    ordered = np.sort(np.where(valid, stack.astype(np.int32), np.iinfo(np.int32).max), axis=0)
    low = np.clip((count - 1) // 2, 0, None)
    high = np.clip(count // 2, 0, None)
    a = np.take_along_axis(ordered, low[None], axis=0)[0]
    b = np.take_along_axis(ordered, high[None], axis=0)[0]
    median = np.where(count > 0, (a.astype(np.int64) + np.where(count > 0, b, 0) + 1) // 2, 0)
    return median.astype(np.uint16)
