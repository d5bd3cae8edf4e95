"""A growable numeric table: rows appended one at a time into one numpy block.

Ingest keeps every joint state of a recording (hundreds per image at a
controller's joint rate) until the pass ends. Held as a Python list of small
arrays, each row costs an array object (~110 bytes of header) plus a list slot
and a boxed stamp, about 4x its 8 bytes per value; here a row costs its values
only, in a block whose capacity doubles when full (amortised O(1) append; at
most 2x the rows' bytes), and :meth:`RowBuffer.array` is a view, not a copy.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray


class RowBuffer:
    """Rows of ``width`` values of one dtype, appended in order.

    Parameters
    ----------
    width : values per row (0: a 1-D buffer of scalars)
    dtype : numpy dtype of the values
    capacity : rows allocated at first
    """

    def __init__(self, width: int, dtype: DTypeLike = np.float64, capacity: int = 1024) -> None:
        shape = (max(1, capacity), width) if width else (max(1, capacity),)
        self._data: NDArray = np.empty(shape, dtype=dtype)
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def append(self, row: ArrayLike) -> None:
        """Append one row (``width`` values, or one scalar for a 1-D buffer)."""
        if self._n == self._data.shape[0]:
            grown = np.empty((2 * self._n, *self._data.shape[1:]), dtype=self._data.dtype)
            grown[: self._n] = self._data
            self._data = grown
        self._data[self._n] = row
        self._n += 1

    def array(self) -> NDArray:
        """The rows so far, shape (n, width) or (n,): a view of the buffer."""
        return self._data[: self._n]
