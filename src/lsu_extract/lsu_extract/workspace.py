"""Per-thread buffers reused from frame to frame for the extractor's large temporaries.

The full-row stages of a frame (the fallback search over a few hundred rows) make temporaries of
hundreds of KB: the gathered pixels, their colour planes, the signal. Allocated and freed once
per frame, blocks that size come from fresh pages under glibc's default malloc settings (a new
mapping, or heap top just given back to the kernel), and the first touch of every page faults
and zero-fills it: for these arrays that costs more than the arithmetic on them. Kept here, they
stay mapped. Each thread has its own buffers, so concurrent extractions never share one.

A pure module: numpy only, no ROS.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from lsu_common.arrays import AnyArray


class _Buffers(threading.local):
    def __init__(self) -> None:
        self.by_name: dict[str, AnyArray] = {}


_BUFFERS = _Buffers()


def scratch(name: str, shape: tuple[int, ...], dtype: type | np.dtype) -> AnyArray:
    """An uninitialised C-contiguous array of ``shape`` and ``dtype`` in this thread's buffer ``name``.

    The array is valid until the next ``scratch`` call of the same thread with the same
    ``name``, which hands out the same memory: one name per temporary that is never alive twice
    at once, and never returned to the extractor's callers. The buffer grows to the largest
    request and is kept.
    """
    dtype = np.dtype(dtype)
    size = dtype.itemsize * math.prod(shape)
    buffer = _BUFFERS.by_name.get(name)
    if buffer is None or buffer.size < size:
        buffer = np.empty(size, np.uint8)
        _BUFFERS.by_name[name] = buffer
    return buffer[:size].view(dtype).reshape(shape)
