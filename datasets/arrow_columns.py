"""Numeric columns of LeRobot data files (Arrow) as flat numpy arrays, for the reader and the
quality checks alike."""

from __future__ import annotations

from typing import Any

import numpy as np


def column_to_numpy(col: Any, dtype: np.dtype) -> np.ndarray:
    """The values of a numeric Arrow column, row after row, as one flat array of `dtype`: lists and
    fixed-size lists (vector features) and datasets' ArrayND extension types are flattened; the
    caller reshapes to (rows, *shape)."""
    import pyarrow as pa

    col = col.combine_chunks() if isinstance(col, pa.ChunkedArray) else col
    while pa.types.is_list(col.type) or pa.types.is_fixed_size_list(col.type) or pa.types.is_large_list(col.type):
        col = col.flatten()
    if hasattr(col, "storage"):  # datasets' ArrayND extension types
        col = col.storage
        while hasattr(col, "flatten") and not pa.types.is_primitive(col.type) and not pa.types.is_boolean(col.type):
            col = col.flatten()
    return np.asarray(col.to_numpy(zero_copy_only=False), dtype=dtype)
