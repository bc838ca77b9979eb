"""Texel codecs of a bundle's UV maps and colour regions (shared_formats/SPEC.md pixel formats 5 and 6).

uv32 (one u32 a texel) and uvblock (4x4 blocks of 24 bytes) carry each texel's UV coordinate, material
and coverage; region codes are the colour-region numbers stored in alpha. Pure numpy functions, no file
I/O: the CBTX container that holds these layers is crowdbake.formats.binary.
"""
from __future__ import annotations

import numpy as np

# uv32 (SPEC.md): one u32 a texel, u in bits 0..13, v in 14..27, material in 28..30, coverage in 31.
# 14 bits address a 1024-texel texture to 1/16 texel, half the bytes of rgba16.
UV32_COORD_BITS = 14
UV32_COORD_MAX = (1 << UV32_COORD_BITS) - 1  # 16383
UV32_MATERIAL_SHIFT = 28
UV32_MAX_MATERIAL = 7
UV32_COVERAGE_SHIFT = 31


def region_codes(alpha: np.ndarray) -> np.ndarray:
    """Colour-region codes from alpha values (any shape, uint8): r = round(alpha / 17), see SPEC.md."""
    return np.rint(np.asarray(alpha, dtype=np.float32) / 17.0).astype(np.uint8)


def region_alpha(codes: np.ndarray) -> np.ndarray:
    """Alpha values for region codes 0..15: 17·r survives DXT3's 4-bit alpha exactly."""
    codes = np.asarray(codes)
    if codes.size and (codes.min() < 0 or codes.max() > 15):
        raise ValueError("region codes must lie in 0..15")
    return (codes.astype(np.uint8) * 17).astype(np.uint8)


def pack_uv32(u: np.ndarray, v: np.ndarray, material: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """UV-map texels as uv32 words (SPEC.md pixel format 5).

    u, v: (...) float in [0, 1] (clipped), texture coordinates; material: (...) int in 0..7;
    coverage: (...) bool, True inside the character. All broadcast to one shape S.
    Returns (S) uint32: round(u·16383) | round(v·16383) << 14 | material << 28 | coverage << 31.
    Uncovered texels are stored as 0 whatever their other fields, so a map has one encoding.
    """
    u, v, material, coverage = np.broadcast_arrays(np.asarray(u, np.float64), np.asarray(v, np.float64), np.asarray(material), np.asarray(coverage, bool))
    if material.size and (material.min() < 0 or material.max() > UV32_MAX_MATERIAL):
        raise ValueError(f"uv32 material indices must lie in 0..{UV32_MAX_MATERIAL}, got {material.min()}..{material.max()}")
    if not (np.isfinite(u).all() and np.isfinite(v).all()):
        raise ValueError("uv32 coordinates contain NaN or infinity")
    qu = np.rint(np.clip(u, 0.0, 1.0) * UV32_COORD_MAX).astype(np.uint32)
    qv = np.rint(np.clip(v, 0.0, 1.0) * UV32_COORD_MAX).astype(np.uint32)
    words = qu | (qv << UV32_COORD_BITS) | (material.astype(np.uint32) << UV32_MATERIAL_SHIFT) | (np.uint32(1) << UV32_COVERAGE_SHIFT)
    return np.where(coverage, words, np.uint32(0)).astype(np.uint32)


def unpack_uv32(words: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """uv32 words (...) uint32 -> (u, v, material, coverage): u, v (...) float64 in [0, 1],
    material (...) int64 in 0..7, coverage (...) bool."""
    words = np.asarray(words, dtype=np.uint32)
    u = (words & UV32_COORD_MAX).astype(np.float64) / UV32_COORD_MAX
    v = ((words >> UV32_COORD_BITS) & UV32_COORD_MAX).astype(np.float64) / UV32_COORD_MAX
    material = ((words >> UV32_MATERIAL_SHIFT) & UV32_MAX_MATERIAL).astype(np.int64)
    coverage = (words >> UV32_COVERAGE_SHIFT).astype(bool)
    return u, v, material, coverage




# uvblock (SPEC.md pixel format 6): blocks of 4x4 texels in 24 bytes (1.5 bytes a texel), six little-endian
# u32 words. w0: each texel's state, 2 bits (0 outside the character, 1..3 subset 0..2). w1 | w2 << 32:
# three 21-bit subset headers (bits 21s..): u base 8 bits, v base 8 bits (units of 16/4095), material
# 2 bits, shift 3 bits. w3..w5: a 96-bit stream, texel i's 3-bit u offset at bit 6i and v offset at 6i + 3.
# A covered texel's coordinate is (16·base + (offset << shift)) / 4095. Texel i sits at (i % 4, i // 4).
UVBLOCK_BLOCK = 4
UVBLOCK_BYTES = 24
UVBLOCK_COORD_MAX = 4095  # coordinates in 1/4095: a quarter texel of a 1024² texture
UVBLOCK_BASE_UNIT = 16
UVBLOCK_OFFSET_MAX = 7  # 3-bit offsets
UVBLOCK_SHIFT_MAX = 7  # 3-bit shifts
UVBLOCK_SUBSETS = 3
UVBLOCK_HEADER_BITS = 21
UVBLOCK_MAX_MATERIAL = 3  # 2 bits: crowdview addresses 4 materials (CV_MAX_MATERIALS)
# Distance between texels of different materials when seeding subsets: larger than any coordinate span.
_OTHER_MATERIAL = 1 << 20


def _uvblock_shift(span: np.ndarray) -> np.ndarray:
    """Smallest shift s in 0..7 with span <= 7 · 2^s (7 where none is), for integer spans (any shape)."""
    shift = np.full(span.shape, UVBLOCK_SHIFT_MAX, np.int64)
    for s in range(UVBLOCK_SHIFT_MAX, -1, -1):
        shift = np.where(span <= UVBLOCK_OFFSET_MAX << s, s, shift)
    return shift


def _blocks(array: np.ndarray) -> np.ndarray:
    """(H, W, ...) -> (blocks, 16, ...), blocks in row-major order, texels row-major inside."""
    height, width = array.shape[:2]
    rows, columns = height // 4, width // 4
    return array.reshape(rows, 4, columns, 4, *array.shape[2:]).swapaxes(1, 2).reshape(rows * columns, 16, *array.shape[2:])


def unblocks(array: np.ndarray, height: int, width: int) -> np.ndarray:
    """Inverse of _blocks for (blocks, 16) arrays."""
    rows, columns = height // 4, width // 4
    return array.reshape(rows, columns, 4, 4).swapaxes(1, 2).reshape(height, width)


def uvblock_subsets(q: np.ndarray, material: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """Subset 0..2 of every covered texel of each block (-1 outside): (N, 16, 2) int coordinates, (N, 16) int
    materials, (N, 16) bool -> (N, 16) int.

    Farthest-point seeding (Chebyshev distance in coordinate units, another material counting as farther
    than any coordinate): seed 0 is the first covered texel, each next seed the texel farthest from the
    seeds so far; every texel joins its nearest seed of its own material. So a block's materials (up to
    three) and its UV charts (a seam inside the block) fall into separate subsets, each with a small span.
    Raises ValueError for a block with four materials.
    """
    count = len(q)
    index = np.arange(count)
    # u and v as separate (N, 16) planes: every pass then runs along contiguous rows.
    qu, qv = np.ascontiguousarray(q[..., 0]), np.ascontiguousarray(q[..., 1])

    def distance(seed: np.ndarray) -> np.ndarray:
        d = np.maximum(np.abs(qu - qu[index, seed][:, None]), np.abs(qv - qv[index, seed][:, None]))
        return np.where(material == material[index, seed][:, None], d, _OTHER_MATERIAL + d)

    seeds = [np.argmax(covered, axis=1)]
    nearest = distance(seeds[0])
    for _ in range(UVBLOCK_SUBSETS - 1):
        seeds.append(np.argmax(np.where(covered, nearest, -1), axis=1))
        nearest = np.minimum(nearest, distance(seeds[-1]))
    distances = np.stack([distance(seed) for seed in seeds], axis=2)  # (N, 16, 3)
    subset = np.argmin(distances, axis=2)
    if (covered & (np.take_along_axis(distances, subset[..., None], axis=2)[..., 0] >= _OTHER_MATERIAL)).any():
        bad = int(np.argmax((covered & (distances.min(axis=2) >= _OTHER_MATERIAL)).any(axis=1)))
        raise ValueError(f"uvblock: block {bad} has more than {UVBLOCK_SUBSETS} materials")
    return np.where(covered, subset, -1)


def pack_uvblock(u: np.ndarray, v: np.ndarray, material: np.ndarray, coverage: np.ndarray) -> bytes:
    """UV-map texels as one layer of uvblock bytes (SPEC.md pixel format 6), blocks in row-major order.

    u, v: (H, W) float in [0, 1] (clipped); material: (H, W) int in 0..3; coverage: (H, W) bool; H and W
    multiples of 4. Coverage and material are kept exactly (uvblock_subsets); each subset's offsets take
    the smallest shift that spans its coordinates, so the rounding error is at most half a step of
    2^shift / 4095 (offsets past 7 steps are clipped: a subset spanning more than 7·128/4095 of the texture).
    """
    u, v = np.asarray(u, np.float64), np.asarray(v, np.float64)
    material, coverage = np.asarray(material, np.int64), np.asarray(coverage, bool)
    height, width = coverage.shape
    if height % 4 or width % 4 or not (u.shape == v.shape == material.shape == coverage.shape):
        raise ValueError(f"uvblock needs (H, W) arrays alike with H and W multiples of 4, got {coverage.shape}")
    if not (np.isfinite(u).all() and np.isfinite(v).all()):
        raise ValueError("uvblock coordinates contain NaN or infinity")
    if coverage.any() and (material[coverage].min() < 0 or material[coverage].max() > UVBLOCK_MAX_MATERIAL):
        raise ValueError(f"uvblock material indices must lie in 0..{UVBLOCK_MAX_MATERIAL}")
    c = _blocks(coverage)
    live = c.any(axis=1)
    q = np.stack([_blocks(u)[live], _blocks(v)[live]], axis=-1)
    return pack_uvblock_blocks(live, uvblock_coordinates(q), _blocks(material)[live], c[live])


def uvblock_coordinates(uv: np.ndarray) -> np.ndarray:
    """Texture coordinates in [0, 1] (clipped), any shape, float -> the same shape of int32 in 1/4095."""
    # int32 throughout the block passes: coordinates, distances (below _OTHER_MATERIAL + 4095) and offsets
    # all fit, and they move half the bytes of int64.
    return np.rint(np.clip(uv, 0.0, 1.0) * UVBLOCK_COORD_MAX).astype(np.int32)


def pack_uvblock_blocks(live: np.ndarray, q: np.ndarray, material: np.ndarray, covered: np.ndarray) -> bytes:
    """One uvblock layer's bytes from its live blocks alone (pack_uvblock without its checks).

    live: (B,) bool, every block of the layer in row-major order, True where the character touches it (a
    block it does not touch is six zero words; an impostor atlas is mostly such blocks, so only the others
    are encoded). For the N live blocks, texels row-major inside: q (N, 16, 2) int32 coordinates in
    1/4095 (uvblock_coordinates), material (N, 16) int in 0..3 where covered, covered (N, 16) bool.
    """
    words = np.zeros((len(live), 6), np.uint64)
    if len(q):
        words[live] = _uvblock_words(q, np.where(covered, material, 0).astype(np.int32), covered)
    return words.astype("<u4").tobytes()


def _uvblock_words(q: np.ndarray, m: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The six words of each block: (N, 16, 2) int coordinates in 1/4095, (N, 16) materials, (N, 16)
    coverage -> (N, 6) uint64 holding u32 values (pack_uvblock's layout)."""
    subset = uvblock_subsets(q, m, c)
    count = len(c)
    words = np.zeros((count, 6), np.uint64)
    words[:, 0] = (np.where(c, subset + 1, 0).astype(np.uint64) << (2 * np.arange(16, dtype=np.uint64))).sum(axis=1)
    planes = (np.ascontiguousarray(q[..., 0]), np.ascontiguousarray(q[..., 1]))  # u, v: (N, 16) each
    offsets = (np.zeros((count, 16), np.int32), np.zeros((count, 16), np.int32))
    headers = np.zeros(count, np.uint64)
    big = np.iinfo(q.dtype).max
    for s in range(UVBLOCK_SUBSETS):
        members = subset == s
        present = members.any(axis=1)
        bases, highs = [], []
        for plane in planes:
            low = np.where(present, np.where(members, plane, big).min(axis=1), 0)
            highs.append(np.where(present, np.where(members, plane, -1).max(axis=1), 0))
            bases.append(low // UVBLOCK_BASE_UNIT)
        origins = [base * UVBLOCK_BASE_UNIT for base in bases]
        shift = _uvblock_shift(np.maximum(highs[0] - origins[0], highs[1] - origins[1]))
        step = (1 << shift)[:, None]
        for plane, origin, out in zip(planes, origins, offsets):
            room = (UVBLOCK_COORD_MAX - origin)[:, None] >> shift[:, None]
            offset = np.clip(np.rint((plane - origin[:, None]) / step), 0, np.minimum(UVBLOCK_OFFSET_MAX, room)).astype(np.int32)
            np.copyto(out, offset, where=members)
        subset_material = np.where(present, m[np.arange(count), np.argmax(members, axis=1)], 0)
        header = bases[0].astype(np.int64) | bases[1].astype(np.int64) << 8 | subset_material.astype(np.int64) << 16 | shift << 18
        headers |= np.where(present, header, 0).astype(np.uint64) << np.uint64(UVBLOCK_HEADER_BITS * s)
    words[:, 1] = headers & np.uint64(0xFFFFFFFF)
    words[:, 2] = headers >> np.uint64(32)
    fields = (offsets[0] | offsets[1] << 3).astype(np.uint64)  # (N, 16) 6-bit fields
    low64 = np.zeros(count, np.uint64)
    high32 = np.zeros(count, np.uint64)
    for i in range(16):
        position = 6 * i
        if position < 64:
            low64 |= fields[:, i] << np.uint64(position)
        if position + 6 > 64:
            high32 |= fields[:, i] >> np.uint64(64 - position) if position < 64 else fields[:, i] << np.uint64(position - 64)
    words[:, 3] = low64 & np.uint64(0xFFFFFFFF)
    words[:, 4] = low64 >> np.uint64(32)
    words[:, 5] = high32 & np.uint64(0xFFFFFFFF)
    return words


def unpack_uvblock(data: bytes, width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One uvblock layer (bytes) of `height` × `width` texels -> (u, v, material, coverage), each (H, W):
    u, v float64 in [0, 1] (0 outside), material int64 (0 outside), coverage bool. Raises ValueError for
    a coordinate above 4095 (SPEC.md: invalid_data)."""
    live, texels = uvblock_live_texels(data, width, height)
    qu_all = np.zeros((len(live), 16), np.int64)
    qv_all, material_all = np.zeros_like(qu_all), np.zeros_like(qu_all)
    covered_all = np.zeros((len(live), 16), bool)
    qu_all[live], qv_all[live], material_all[live], covered_all[live] = texels
    u = unblocks(qu_all, height, width) / UVBLOCK_COORD_MAX
    v = unblocks(qv_all, height, width) / UVBLOCK_COORD_MAX
    return u, v, unblocks(material_all, height, width), unblocks(covered_all, height, width)


def uvblock_live_texels(data: bytes, width: int, height: int) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """The blocks of a uvblock layer the character touches, decoded: (live, (qu, qv, material, covered)).

    live: (B,) bool over every block in row-major order; for the N live blocks, texels row-major inside,
    qu, qv (N, 16) int64 coordinates in 1/4095, material (N, 16) int64 (0 outside), covered (N, 16) bool.
    Texels of a block whose states word is 0 are all outside whatever its other words hold, so only the
    other blocks are decoded. Raises ValueError for a covered coordinate above 4095.
    """
    words = np.frombuffer(data, "<u4", (height // 4) * (width // 4) * 6).reshape(-1, 6)
    live = words[:, 0] != 0
    if not live.any():
        empty = np.zeros((0, 16), np.int64)
        return live, (empty, empty, empty, np.zeros((0, 16), bool))
    return live, _uvblock_texels(words[live].astype(np.uint64))


def check_uvblock(data: bytes, width: int, height: int) -> None:
    """Raise ValueError where unpack_uvblock would (a covered coordinate above 4095), decoding only the
    blocks that could hold one: a subset's coordinates are at most 16·base + (7 << shift), so a block whose
    used subsets all stay within 4095 by that bound needs no texel decoded (every block of a baked map)."""
    words = np.frombuffer(data, "<u4", (height // 4) * (width // 4) * 6).reshape(-1, 6)
    words = words[words[:, 0] != 0].astype(np.uint64)
    if not len(words):
        return
    states = (words[:, :1] >> (2 * np.arange(16, dtype=np.uint64))) & np.uint64(3)  # (N, 16): 0 outside, 1..3
    headers = words[:, 1] | words[:, 2] << np.uint64(32)
    risky = np.zeros(len(words), bool)
    for s in range(UVBLOCK_SUBSETS):
        used = (states == s + 1).any(axis=1)
        header = (headers >> np.uint64(UVBLOCK_HEADER_BITS * s)) & np.uint64((1 << UVBLOCK_HEADER_BITS) - 1)
        reach = np.uint64(UVBLOCK_OFFSET_MAX) << ((header >> np.uint64(18)) & np.uint64(7))
        base_u = (header & np.uint64(255)) * np.uint64(UVBLOCK_BASE_UNIT)
        base_v = ((header >> np.uint64(8)) & np.uint64(255)) * np.uint64(UVBLOCK_BASE_UNIT)
        risky |= used & (np.maximum(base_u, base_v) + reach > UVBLOCK_COORD_MAX)
    if risky.any():
        _uvblock_texels(words[risky])


def _uvblock_texels(words: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(N, 6) uint64 block words -> (qu, qv, material, covered), each (N, 16): coordinates in 1/4095 and
    materials 0 outside the character. Raises ValueError for a covered coordinate above 4095."""
    count = len(words)
    states = ((words[:, :1] >> (2 * np.arange(16, dtype=np.uint64))) & np.uint64(3)).astype(np.int64)
    low64 = words[:, 3] | words[:, 4] << np.uint64(32)
    fields = np.zeros((count, 16), np.uint64)
    for i in range(16):
        position = 6 * i
        if position + 6 <= 64:
            fields[:, i] = (low64 >> np.uint64(position)) & np.uint64(63)
        elif position >= 64:
            fields[:, i] = (words[:, 5] >> np.uint64(position - 64)) & np.uint64(63)
        else:  # straddles bit 64
            fields[:, i] = ((low64 >> np.uint64(position)) | (words[:, 5] << np.uint64(64 - position))) & np.uint64(63)
    headers = words[:, 1] | words[:, 2] << np.uint64(32)
    subset = np.maximum(states - 1, 0).astype(np.uint64)
    header = (headers[:, None] >> (np.uint64(UVBLOCK_HEADER_BITS) * subset)) & np.uint64((1 << UVBLOCK_HEADER_BITS) - 1)
    shift = (header >> np.uint64(18)) & np.uint64(7)
    qu = ((header & np.uint64(255)) * np.uint64(UVBLOCK_BASE_UNIT) + ((fields & np.uint64(7)) << shift)).astype(np.int64)
    qv = (((header >> np.uint64(8)) & np.uint64(255)) * np.uint64(UVBLOCK_BASE_UNIT) + ((fields >> np.uint64(3)) << shift)).astype(np.int64)
    covered = states != 0
    if (covered & ((qu > UVBLOCK_COORD_MAX) | (qv > UVBLOCK_COORD_MAX))).any():
        raise ValueError(f"uvblock: a coordinate above {UVBLOCK_COORD_MAX}")
    material = ((header >> np.uint64(16)) & np.uint64(3)).astype(np.int64)
    return np.where(covered, qu, 0), np.where(covered, qv, 0), np.where(covered, material, 0), covered
