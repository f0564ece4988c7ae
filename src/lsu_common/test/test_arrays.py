"""The array aliases name the dtypes they promise (what mypy checks callers against)."""

from typing import Any, get_args

import numpy as np

from lsu_common import arrays


def _dtype_of(alias: Any) -> Any:
    # NDArray[X] is ndarray[shape, dtype[X]]: the scalar type is the dtype's argument
    _, dtype = get_args(alias)
    (scalar,) = get_args(dtype)
    return scalar


def test_each_alias_names_its_dtype():
    expected = {"FloatArray": np.float64, "Float32Array": np.float32, "IntArray": np.int64,
                "Int32Array": np.int32, "BoolArray": np.bool_, "U8Image": np.uint8, "U16Image": np.uint16,
                "AnyArray": Any}
    assert {name: _dtype_of(getattr(arrays, name)) for name in expected} == expected


def test_every_exported_name_exists():
    assert all(hasattr(arrays, name) for name in arrays.__all__)
