"""Type aliases for numpy arrays: the one place every LSU package takes them from.

Annotate an array with the alias of its dtype when the function fixes it (an image from the
camera is ``U8Image``, triangulated points are ``FloatArray``); ``AnyArray`` where the function
accepts or returns several dtypes. Shapes go in the docstring or a comment (numpy's typing does not
check them).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "AnyArray",
    "BoolArray",
    "Float32Array",
    "FloatArray",
    "Int32Array",
    "IntArray",
    "NDArray",
    "U8Image",
    "U16Image",
]

# dtype decided by the caller or varying (generic helpers, arrays read from messages or files)
AnyArray = NDArray[Any]
# metres, pixels, radians: every float computation (float64)
FloatArray = NDArray[np.float64]
# float32 buffers: PointCloud2 fields, OpenCV maps and float images
Float32Array = NDArray[np.float32]
# indices, counts, integer positions (int64)
IntArray = NDArray[np.int64]
Int32Array = NDArray[np.int32]
# masks
BoolArray = NDArray[np.bool_]
# 8-bit camera images (mono8, rgb8/bgr8) and other byte buffers
U8Image = NDArray[np.uint8]
# 16-bit camera images (mono16)
U16Image = NDArray[np.uint16]
