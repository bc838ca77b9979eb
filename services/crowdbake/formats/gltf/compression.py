"""Compressed glTF geometry: EXT_meshopt_compression bufferViews and KHR_draco_mesh_compression streams.

The decoders are the libraries' own (meshoptimizer's vertex, index and filter decoders; DracoPy); this
module checks what a file claims before asking them for anything, and turns their errors into
ValueError naming the place in the file. Bytes in, bytes (or DracoPy's decoded mesh) out; which
bufferView or primitive is read is the caller's business (crowdbake.formats.gltf.document, .meshes).
"""
from __future__ import annotations

import numpy as np

DRACO = "KHR_draco_mesh_compression"
MESHOPT = "EXT_meshopt_compression"
# A compressed bufferView may claim any decoded size; a character's biggest view (positions of a
# million vertices) is 12 MB, so 256 MiB refuses a lying count before it becomes an allocation.
MAX_DECODED_VIEW_BYTES = 1 << 28
# What one document may decode in all (meshopt views and Draco primitives together), checked from the
# sizes the file claims before anything decodes: a per-view cap alone lets eight views of one 4 MB stream
# each claim 256 MiB (2 GB decoded in 18 s, inside the API). A million-vertex character with normals,
# UVs, skin and 2 million triangles decodes to about 100 MB; 128 MiB keeps an upload's check within
# the service's +300 MB memory target.
MAX_DECODED_DOCUMENT_BYTES = 1 << 27


def claimed_meshopt_bytes(ext: dict, label: str) -> int:
    """The decoded size (count * byteStride) an EXT_meshopt_compression bufferView claims; raises
    ValueError naming `label` when count or byteStride is not a positive integer."""
    count, stride = ext.get("count"), ext.get("byteStride")
    if not _positive_int(count) or not _positive_int(stride):
        raise ValueError(f"{label}: count {count!r} and byteStride {stride!r} must be positive integers")
    return count * stride


def _positive_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 1


def decode_meshopt_view(source: bytes, ext: dict, label: str) -> bytes:
    """Decode an EXT_meshopt_compression bufferView (its ATTRIBUTES, TRIANGLES or INDICES mode and
    its NONE, OCTAHEDRAL, QUATERNION or EXPONENTIAL filter) with meshoptimizer's decoders.

    source: the compressed bytes the extension points at; ext: the extension's JSON object (count,
    byteStride, mode, filter); label: the file and bufferView, for messages. Returns count * byteStride
    decoded bytes; raises ValueError for a count, stride, mode or filter it cannot honour, or a stream
    that does not decode."""
    import meshoptimizer

    claimed = claimed_meshopt_bytes(ext, label)
    count, stride = ext["count"], ext["byteStride"]
    mode, filter_name = ext.get("mode"), ext.get("filter", "NONE")
    if claimed > MAX_DECODED_VIEW_BYTES:
        raise ValueError(f"{label} decodes to {count * stride} bytes, more than {MAX_DECODED_VIEW_BYTES}")
    try:
        if mode == "ATTRIBUTES":
            if stride % 4 or stride > 256:
                raise ValueError(f"byteStride {stride} must be a multiple of 4 up to 256")
            # The float32 view the decoder returns is only a container: its bytes are the vertices.
            decoded = np.ascontiguousarray(meshoptimizer.decode_vertex_buffer(count, stride, source)).view(np.uint8)
            filters = {"OCTAHEDRAL": meshoptimizer.decode_filter_oct, "QUATERNION": meshoptimizer.decode_filter_quat,
                       "EXPONENTIAL": meshoptimizer.decode_filter_exp}
            if filter_name in filters:
                decoded = filters[filter_name](decoded, count, stride)
            elif filter_name != "NONE":
                raise ValueError(f"unknown filter {filter_name!r}")
            result = decoded.tobytes()
        elif mode in ("TRIANGLES", "INDICES"):
            if stride not in (2, 4) or (mode == "TRIANGLES" and count % 3):
                raise ValueError(f"index byteStride {stride} must be 2 or 4 (and count a multiple of 3 for TRIANGLES)")
            decode = meshoptimizer.decode_index_buffer if mode == "TRIANGLES" else meshoptimizer.decode_index_sequence
            # The decoder writes count * stride bytes at the start of its uint32 array.
            result = decode(count, stride, source).tobytes()[: count * stride]
        else:
            raise ValueError(f"unknown mode {mode!r}")
    except (ValueError, RuntimeError) as error:
        raise ValueError(f"{label} does not decode: {error}") from None
    return result


def decode_draco_mesh(data: bytes, where: str):
    """Decode a KHR_draco_mesh_compression stream with DracoPy -> its mesh (faces, attributes by unique id)."""
    import DracoPy

    try:
        return DracoPy.decode(data)
    except Exception as error:  # DracoPy raises its own exception types for a bad stream
        raise ValueError(f"{where}: the {DRACO} data does not decode: {error}") from None
