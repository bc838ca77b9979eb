"""A search result (a tree of crowdbake dataclasses, numpy arrays and plain values) as JSON plus arrays,
and back, exactly: how one clip's loop travels from the task that searched it to the one that joins
the loops (crowdbake.stages.loops).

    tree, arrays = to_tree(value)        # tree: JSON-ready; arrays: {"a0": ndarray, ...} for an .npz
    value = from_tree(tree, arrays)

Not pickle: these files may come back from the object store, and reading them must run no code. Only
dataclasses defined in crowdbake modules are rebuilt. Floats keep every bit (JSON writes a float's
shortest repr, which reads back to the same double; NaN and infinities as JSON's NaN/Infinity); numpy
scalars and arrays keep their dtype and shape.
"""
from __future__ import annotations

import dataclasses
import importlib
from typing import Any

import numpy as np

_PACKAGE = "crowdbake."


def to_tree(value: Any) -> tuple[Any, dict[str, np.ndarray]]:
    """(JSON-ready tree, arrays by name) of `value`. TypeError on a value of another kind."""
    arrays: dict[str, np.ndarray] = {}

    def walk(item: Any) -> Any:
        if item is None or isinstance(item, (bool, int, float, str)) and not isinstance(item, np.generic):
            return item
        if isinstance(item, (np.ndarray, np.generic)):
            name = f"a{len(arrays)}"
            arrays[name] = np.asarray(item)
            return {"__array__": name, "scalar": isinstance(item, np.generic)}
        if dataclasses.is_dataclass(item) and not isinstance(item, type):
            kind = type(item)
            if not kind.__module__.startswith(_PACKAGE):
                raise TypeError(f"{kind.__module__}.{kind.__qualname__} is not a crowdbake dataclass")
            fields = {field.name: walk(getattr(item, field.name)) for field in dataclasses.fields(item)}
            return {"__dataclass__": f"{kind.__module__}:{kind.__qualname__}", "fields": fields}
        if isinstance(item, tuple):
            return {"__tuple__": [walk(element) for element in item]}
        if isinstance(item, list):
            return [walk(element) for element in item]
        if isinstance(item, dict) and all(isinstance(key, str) for key in item):
            # Pairs, not an object: the JSON writer may sort an object's keys, and a dict's order is kept.
            return {"__dict__": [[key, walk(element)] for key, element in item.items()]}
        raise TypeError(f"cannot store a {type(item).__name__}")

    return walk(value), arrays


def from_tree(tree: Any, arrays: dict[str, np.ndarray]) -> Any:
    """The value to_tree stored. ValueError on a tree naming something outside crowdbake's dataclasses."""

    def walk(item: Any) -> Any:
        if isinstance(item, list):
            return [walk(element) for element in item]
        if not isinstance(item, dict):
            return item
        if "__array__" in item:
            array = arrays[item["__array__"]]
            return array[()] if item["scalar"] else array
        if "__tuple__" in item:
            return tuple(walk(element) for element in item["__tuple__"])
        if "__dict__" in item:
            return {key: walk(element) for key, element in item["__dict__"]}
        module, _, name = item["__dataclass__"].partition(":")
        if not module.startswith(_PACKAGE):
            raise ValueError(f"{module}:{name} is not a crowdbake dataclass")
        kind = importlib.import_module(module)
        for part in name.split("."):
            kind = getattr(kind, part)
        if not (isinstance(kind, type) and dataclasses.is_dataclass(kind)):
            raise ValueError(f"{module}:{name} is not a dataclass")
        # Field by field, past __init__ (frozen classes, fields with init=False): the object as it was.
        value = object.__new__(kind)
        for key, element in item["fields"].items():
            object.__setattr__(value, key, walk(element))
        return value

    return walk(tree)
