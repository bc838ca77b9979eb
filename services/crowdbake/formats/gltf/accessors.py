"""Typed accessor reads: a glTF accessor into a numpy array, every extent checked before anything is allocated.

An accessor's elements are checked against its bufferView (offset, stride, count) before numpy is asked
to view them, sparse blocks against theirs, and every accessor's size against MAX_ACCESSOR_COMPONENTS,
so a lying count raises ValueError instead of becoming an allocation. Integer components come back as
int64, floats and normalised integers as float32 (glTF 2.0 section 3.11).
"""
from __future__ import annotations

import numpy as np
import pygltflib

# Components (count x width) of one accessor. Checked before anything is allocated, because a
# zero-filled accessor (no bufferView) costs the file nothing: "count 10^7 of MAT4" in 200 bytes of JSON
# would otherwise become 640 MB of zeros and twice that once converted. 2^24 components hold 4 million
# triangles' indices or 5.5 million positions, beyond any character a crowd needs, and cost at most
# 128 MiB as int64.
MAX_ACCESSOR_COMPONENTS = 1 << 24

# glTF componentType -> numpy dtype (little-endian, as glTF stores them), and the width of each accessor type.
COMPONENT_TYPES = {
    pygltflib.BYTE: np.dtype("i1"),
    pygltflib.UNSIGNED_BYTE: np.dtype("u1"),
    pygltflib.SHORT: np.dtype("<i2"),
    pygltflib.UNSIGNED_SHORT: np.dtype("<u2"),
    pygltflib.UNSIGNED_INT: np.dtype("<u4"),
    pygltflib.FLOAT: np.dtype("<f4"),
}
TYPE_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def read_accessor(doc, index: int) -> np.ndarray:
    """Accessor `index` of `doc` (a crowdbake.formats.gltf.document._Document) as a (count, width) array:
    float32 for floats and normalised ints, else int64."""
    accessor = doc.item("accessors", index)
    where = f"{doc.where}: accessors[{index}]"
    dtype = COMPONENT_TYPES.get(accessor.componentType)
    width = TYPE_WIDTHS.get(accessor.type)
    count = accessor.count
    if dtype is None or width is None:
        raise ValueError(f"{where}: unknown componentType {accessor.componentType} or type {accessor.type}")
    if not isinstance(count, int) or count < 1:
        raise ValueError(f"{where}: count {count!r} must be a positive integer")
    if count * width > MAX_ACCESSOR_COMPONENTS:
        raise ValueError(f"{where}: {count} elements of {accessor.type} are {count * width} components, more than {MAX_ACCESSOR_COMPONENTS}")
    if accessor.type in ("MAT2", "MAT3") and dtype.itemsize < 4:
        raise ValueError(f"{where}: padded {accessor.type} of {dtype} components is not supported")
    element_size = dtype.itemsize * width
    if accessor.bufferView is not None:
        # The extent is checked against the view's (claimed) length before a compressed view decodes.
        stride = int(doc.view_stride(accessor.bufferView) or element_size)
        offset = int(accessor.byteOffset or 0)
        if stride < element_size or offset < 0:
            raise ValueError(f"{where}: byteStride {stride} is smaller than an element ({element_size} bytes)")
        end = offset + stride * (count - 1) + element_size
        length = doc.view_length(accessor.bufferView)
        if end > length:  # checked before numpy (or a decoder) is asked for anything
            raise ValueError(
                f"{where}: {count} elements of {element_size} bytes (stride {stride}) from byte {offset} need "
                f"{end} bytes, its bufferView has {length}"
            )
        data, _ = doc.view_bytes(accessor.bufferView)
        values = np.ndarray((count, width), dtype=dtype, buffer=data, offset=offset, strides=(stride, dtype.itemsize)).copy()
    else:
        values = np.zeros((count, width), dtype=dtype)
    if accessor.sparse is not None:
        values = _apply_sparse(doc, accessor.sparse, values, dtype, width, where)
    return accessor_values(values, bool(accessor.normalized), where)


def _apply_sparse(doc, sparse, values: np.ndarray, dtype, width: int, where: str) -> np.ndarray:
    count = sparse.count
    indices_info, values_info = sparse.indices, sparse.values
    index_dtype = COMPONENT_TYPES.get(getattr(indices_info, "componentType", None))
    if not isinstance(count, int) or count < 1 or index_dtype is None or index_dtype.kind != "u" or values_info is None:
        raise ValueError(f"{where}: malformed sparse block")
    sparse_indices = None
    for info, item_dtype, item_width, label in ((indices_info, index_dtype, 1, "indices"), (values_info, dtype, width, "values")):
        data, _ = doc.view_bytes(info.bufferView)
        offset = int(info.byteOffset or 0)
        if offset < 0 or offset + count * item_dtype.itemsize * item_width > len(data):
            raise ValueError(f"{where}: sparse {label} lie outside their bufferView")
        array = np.frombuffer(data, dtype=item_dtype, count=count * item_width, offset=offset).reshape(count, item_width)
        if label == "indices":
            sparse_indices = array[:, 0].astype(np.int64)
            if sparse_indices.max() >= len(values):
                raise ValueError(f"{where}: sparse index {sparse_indices.max()} >= count {len(values)}")
        else:
            values = values.copy()
            values[sparse_indices] = array
    return values


def accessor_values(values: np.ndarray, normalized: bool, where: str) -> np.ndarray:
    """Raw accessor components -> float32 (floats; normalised integers) or int64 (other integers)."""
    if values.dtype.kind == "f":
        result = values.astype(np.float32)
    elif normalized:
        # glTF 2.0 section 3.11: signed values map with max(c / (2^(n-1) - 1), -1), unsigned with c / (2^n - 1).
        info = np.iinfo(values.dtype)
        result = np.maximum(values.astype(np.float64) / info.max, -1.0).astype(np.float32)
    else:
        result = values.astype(np.int64)
    if result.dtype.kind == "f" and not np.isfinite(result).all():
        raise ValueError(f"{where}: contains NaN or infinity")
    return result
