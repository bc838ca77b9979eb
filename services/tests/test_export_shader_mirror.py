"""The export's impostor shaders (services/crowdbake/export/shaders/impostor_uv.glsl and .hlsl) carry a
copy of crowdview's uv32 decode (runtime/src/shaders/impostor_uv_map.glsl) and of its ambient term
(runtime/src/config.h CV_AMBIENT), so an engine draws the impostor as crowdview does. Nothing compiles the
two sides together, so this test reads both from their sources: the ambient constants must be equal, and
each decode, evaluated on sample words, must give what crowdbake's own codec gives
(crowdbake.formats.texel_codecs.unpack_uv32, the format's reference). Evaluating rather than comparing
text lets the copies differ in language (GLSL, HLSL) and names; the self-checks at the end show a change
to either side is caught."""
from __future__ import annotations

import re
from functools import lru_cache

import numpy as np
import pytest

from crowdbake.formats.texel_codecs import unpack_uv32
from repo_paths import REPO_ROOT

RUNTIME_CONFIG = REPO_ROOT / "runtime" / "src" / "config.h"
RUNTIME_UV_MAP = REPO_ROOT / "runtime" / "src" / "shaders" / "impostor_uv_map.glsl"
EXPORT_SHADERS = REPO_ROOT / "services" / "crowdbake" / "export" / "shaders"
EXPORT_GLSL = EXPORT_SHADERS / "impostor_uv.glsl"
EXPORT_HLSL = EXPORT_SHADERS / "impostor_uv.hlsl"

# Every field boundary of the word (SPEC.md pixel format 5: u bits 0..13, v 14..27, material 28..30,
# coverage 31) set and clear, and random words: a shifted or masked field in a copy changes some of them.
EDGE_WORDS = [0, 0xFFFFFFFF, 0x3FFF, 0x3FFF << 14, 7 << 28, 1 << 31, 1, 1 << 13, 1 << 14, 1 << 27, 1 << 28, 1 << 30, 0x80000001]
SAMPLE_WORDS = EDGE_WORDS + [int(w) for w in np.random.default_rng(20061).integers(0, 1 << 32, size=500, dtype=np.uint64)]


# -------------------------------------------------------------------------------------- extraction


def define_value(header: str, name: str) -> float:
    match = re.search(rf"^\s*#define\s+{name}\s+([-+0-9.eE]+)\s*$", header, re.M)
    if match is None:
        raise ValueError(f"no #define {name} <number> in the header")
    return float(match.group(1))


def const_value(shader: str, name: str) -> float:
    """The value of `[static] const float NAME = <number>;` (GLSL and HLSL alike)."""
    match = re.search(rf"^\s*(?:static\s+)?const\s+float\s+{name}\s*=\s*([-+0-9.eE]+)\s*;", shader, re.M)
    if match is None:
        raise ValueError(f"no `const float {name} = <number>;` in the shader")
    return float(match.group(1))


def function_body(source: str, name: str) -> str:
    """The text between the braces of the first definition of function `name` (braces balanced)."""
    match = re.search(rf"\b{name}\s*\([^)]*\)\s*\{{", source)
    if match is None:
        raise ValueError(f"no function {name} in the shader")
    depth, start = 1, match.end()
    for end in range(start, len(source)):
        depth += {"{": 1, "}": -1}.get(source[end], 0)
        if depth == 0:
            return source[start:end]
    raise ValueError(f"function {name} does not close")


def assigned(body: str, target: str) -> str:
    """The expression of `target = EXPR;` (target may carry a type: `float2 uv`)."""
    match = re.search(rf"(?:^|[;{{\s]){re.escape(target)}\s*=\s*([^;]+);", body)
    if match is None:
        raise ValueError(f"no assignment to {target}")
    return match.group(1).strip()


def runtime_uv32_decode(source: str) -> dict[str, str]:
    """crowdview's decode: fetch_uv_map in the CV_UV_MAP_UV32 branch of impostor_uv_map.glsl."""
    branch = source.split("#elif CV_UV_MAP_UV32", 1)[1].split("#else", 1)[0]
    body = function_body(branch, "fetch_uv_map")
    return {"uv": assigned(body, "t.uv"), "material": assigned(body, "t.material"), "covered": assigned(body, "t.covered")}


def export_glsl_uv32_decode(source: str) -> dict[str, str]:
    body = function_body(source, "cb_fetch_uv")
    return {"uv": assigned(body, "t.uv"), "material": assigned(body, "t.material"), "covered": assigned(body, "t.covered")}


def export_hlsl_uv32_decode(source: str) -> dict[str, str]:
    """The HLSL shader decodes inline (one material shown, so no material): the coordinates, and the
    coverage test that ends the function where the word is not covered."""
    body = function_body(source, "CbImpostorColour")
    refused = re.search(r"if\s*\(([^;]*\bword\b[^;]*)\)\s*return\s+false\s*;", body)
    if refused is None:
        raise ValueError("no `if (<test of word>) return false;` in CbImpostorColour")
    return {"uv": assigned(body, "float2 uv"), "covered": f"!({refused.group(1)})"}


# -------------------------------------------------------------------------------------- evaluation


class Vec2(tuple):
    """GLSL vec2 / HLSL float2 for the decode's arithmetic: built from two numbers, divided by a scalar."""

    def __new__(cls, x, y):
        return super().__new__(cls, (float(x), float(y)))

    def __truediv__(self, scalar):
        return Vec2(self[0] / scalar, self[1] / scalar)


@lru_cache(maxsize=None)
def as_python(expression: str):
    """A decode expression (unsigned integer ops, casts, vec2/float2) compiled as Python: the `u` suffixes
    dropped (Python's ints hold every 32-bit value, and & and >> never leave that range), `!` as `not`."""
    python = re.sub(r"\b(0x[0-9A-Fa-f]+|\d+)u\b", r"\1", expression)
    python = re.sub(r"\b(vec2|float2)\(", "Vec2(", python)
    python = re.sub(r"!(?!=)", " not ", python)
    return compile(python.strip(), "<shader expression>", "eval")


def evaluate(expression: str, word: int):
    """A decode expression on one 32-bit word."""
    return eval(as_python(expression), {"__builtins__": {}, "Vec2": Vec2, "float": float, "int": int}, {"word": word})


def decode_disagreements(decode: dict[str, str], words: list[int]) -> list[str]:
    """Where a shader's decode differs from unpack_uv32 (coordinates to float32 precision)."""
    u, v, material, covered = unpack_uv32(np.asarray(words, dtype=np.uint32))
    found = []
    for k, word in enumerate(words):
        got = {name: evaluate(expression, word) for name, expression in decode.items()}
        if abs(got["uv"][0] - u[k]) > 1e-7 or abs(got["uv"][1] - v[k]) > 1e-7:
            found.append(f"{word:#010x}: uv {got['uv']} != ({u[k]}, {v[k]})")
        if "material" in got and got["material"] != material[k]:
            found.append(f"{word:#010x}: material {got['material']} != {material[k]}")
        if bool(got["covered"]) != bool(covered[k]):
            found.append(f"{word:#010x}: covered {got['covered']} != {covered[k]}")
    return found


def mirror_disagreements(config_h: str, runtime_uv_map: str, export_glsl: str, export_hlsl: str) -> list[str]:
    """Every way the export shaders' copies differ from crowdview's sources (empty: they agree)."""
    found = []
    ambient = define_value(config_h, "CV_AMBIENT")
    for name, shader in (("impostor_uv.glsl", export_glsl), ("impostor_uv.hlsl", export_hlsl)):
        if const_value(shader, "CB_AMBIENT") != ambient:
            found.append(f"{name}: CB_AMBIENT {const_value(shader, 'CB_AMBIENT')} != config.h CV_AMBIENT {ambient}")
    for name, decode in (("runtime impostor_uv_map.glsl", runtime_uv32_decode(runtime_uv_map)),
                         ("impostor_uv.glsl", export_glsl_uv32_decode(export_glsl)),
                         ("impostor_uv.hlsl", export_hlsl_uv32_decode(export_hlsl))):
        found += [f"{name}: {line}" for line in decode_disagreements(decode, SAMPLE_WORDS)[:3]]
    return found


@pytest.fixture(scope="module")
def sources() -> dict[str, str]:
    return {"config_h": RUNTIME_CONFIG.read_text(), "runtime_uv_map": RUNTIME_UV_MAP.read_text(),
            "export_glsl": EXPORT_GLSL.read_text(), "export_hlsl": EXPORT_HLSL.read_text()}


def test_the_export_shaders_agree_with_crowdview(sources):
    assert mirror_disagreements(**sources) == []


def test_the_decodes_read_the_fields_they_name(sources):
    """The evaluation is not vacuous: a covered word with every field set decodes to known values."""
    word = (1 << 31) | (5 << 28) | (8191 << 14) | 16383
    decode = runtime_uv32_decode(sources["runtime_uv_map"])
    assert evaluate(decode["uv"], word) == pytest.approx((1.0, 8191 / 16383))
    assert evaluate(decode["material"], word) == 5 and evaluate(decode["covered"], word) is True


@pytest.mark.parametrize("side, old, new", [
    ("config_h", "#define CV_AMBIENT 0.35", "#define CV_AMBIENT 0.3"),
    ("export_hlsl", "static const float CB_AMBIENT = 0.35;", "static const float CB_AMBIENT = 0.4;"),
    ("runtime_uv_map", "(word >> 14u) & 0x3FFFu", "(word >> 13u) & 0x3FFFu"),
    ("runtime_uv_map", "int((word >> 28u) & 7u)", "int((word >> 28u) & 3u)"),
    ("export_glsl", "/ 16383.0", "/ 16384.0"),
    ("export_glsl", "(word >> 31u) != 0u", "(word >> 30u) != 0u"),
    ("export_hlsl", "if ((word >> 31) == 0) return false;", "if ((word & 1) == 0) return false;"),
])
def test_a_change_to_either_side_is_caught(sources, side, old, new):
    assert sources[side].count(old) >= 1, f"the self-check's text {old!r} is no longer in {side}"
    changed = {**sources, side: sources[side].replace(old, new)}
    assert mirror_disagreements(**changed) != []
