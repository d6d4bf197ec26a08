"""Numpy arrays as pydantic fields, with dtype and shape checked at validation.

``Annotated[np.ndarray, ArraySpec(...)]`` is how every message declares an array. The spec also
says what kind of data the array holds, so the codec can pick the link's encoding for it
(JPEG for RGB, PNG for depth, bit-packing for masks, zlib for label maps).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic_core import core_schema

ArrayKind = Literal["plain", "rgb", "depth", "mask", "label"]

ALLOWED_DTYPES = frozenset(
    {
        "bool",
        "uint8",
        "int8",
        "uint16",
        "int16",
        "uint32",
        "int32",
        "int64",
        "float16",
        "float32",
        "float64",
    }
)
"""The only dtypes that may cross the wire: no objects, strings, structured or big-endian."""

_NAMES = {np.dtype(n): n for n in ALLOWED_DTYPES}


def dtype_name(dtype: np.dtype) -> str:
    """``dtype.name``, from a table for the allowed dtypes: numpy builds the name in Python
    on every access, and a message of many small arrays asks for it thousands of times."""
    name = _NAMES.get(dtype)
    if name is None and dtype.byteorder == ">":
        name = _NAMES.get(dtype.newbyteorder("<"))
    return name if name is not None else dtype.name


@dataclass(frozen=True)
class ArraySpec:
    """Constraints of one array field.

    ``shape`` lists each dimension's size, or None where any size is allowed.
    Non-arrays (lists, scalars) are converted with the first allowed dtype; an ndarray of
    another dtype is refused rather than silently cast.
    """

    dtypes: tuple[str, ...]
    shape: tuple[int | None, ...] | None = None
    kind: ArrayKind = "plain"
    finite: bool = False

    def validate(self, value: Any) -> np.ndarray:
        if isinstance(value, np.ndarray):
            arr = value
            if dtype_name(arr.dtype) not in self.dtypes:
                raise ValueError(f"dtype {arr.dtype.name} not allowed, expected {'/'.join(self.dtypes)}")
        else:
            if isinstance(value, (list, tuple)) and any(isinstance(v, np.ndarray) for v in value):
                # Stacking decoded arrays would multiply what one payload may allocate.
                raise ValueError("expected one array, got a list of arrays")
            try:
                probe = np.asarray(value)
                if probe.dtype.kind not in "biuf":
                    raise ValueError(f"elements are {probe.dtype.name}, not numbers")
                with np.errstate(all="ignore"):
                    arr = probe.astype(self.dtypes[0]) if dtype_name(probe.dtype) != self.dtypes[0] else probe
                    lossy = arr.dtype.kind in "iub" and not np.array_equal(arr.astype(probe.dtype), probe)
                if lossy:
                    raise ValueError(f"values not representable as {self.dtypes[0]}")
            except (TypeError, ValueError, OverflowError) as exc:
                raise ValueError(f"not convertible to a {self.dtypes[0]} array ({exc})") from None
        if self.shape is not None:
            if arr.ndim != len(self.shape):
                raise ValueError(f"expected {len(self.shape)} dimensions {self._shape_str()}, got shape {arr.shape}")
            for want, got in zip(self.shape, arr.shape, strict=True):
                if want is not None and want != got:
                    raise ValueError(f"expected shape {self._shape_str()}, got {arr.shape}")
        if self.finite and arr.dtype.kind == "f" and not np.isfinite(arr).all():
            raise ValueError("contains NaN or infinity")
        return arr

    def _shape_str(self) -> str:
        assert self.shape is not None
        return "(" + ", ".join("*" if s is None else str(s) for s in self.shape) + ")"

    def __get_pydantic_core_schema__(self, source: Any, handler: Any) -> core_schema.CoreSchema:
        return core_schema.no_info_plain_validator_function(
            self.validate,
            serialization=core_schema.plain_serializer_function_ser_schema(
                lambda a: a.tolist(), when_used="json"
            ),
        )


def spec_of(annotation_metadata: list[Any]) -> ArraySpec | None:
    """The ArraySpec among a field's metadata, if any."""
    for m in annotation_metadata:
        if isinstance(m, ArraySpec):
            return m
    return None
