"""Hostile JSON, refused cheaply: nesting depth measured without parsing, non-finite numbers
found with the path that holds them.

Python's :func:`json.loads` recurses once per level (a document nested 100 000 deep raises
``RecursionError``) and reads ``NaN``, ``Infinity`` and ``1e400`` as floats that JSON cannot
carry back out. These helpers let every reader refuse both with a one-line reason.
"""

from __future__ import annotations

import json
import math
import re
from typing import Any

import numpy as np

#: deepest nesting any Fringescope document needs (a calibration file is 6 deep)
MAX_JSON_DEPTH = 32

_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"', re.DOTALL)  # unrolled: linear and fast


def json_depth(data: bytes) -> int:
    """The deepest nesting of arrays and objects in the JSON text ``data`` (0 for a scalar).

    A byte scan, not a parse: brackets inside strings do not count, the text need not be
    valid JSON (an unclosed bracket still counts). Linear time, no recursion.

    Args:
        data: UTF-8 JSON text.
    """
    if not isinstance(data, bytes | bytearray | memoryview):
        raise ValueError(f"data: expected bytes, got {type(data).__name__}")
    bare = _STRING.sub(b"", bytes(data))
    opens = bare.count(b"[") + bare.count(b"{")
    if opens == 0:
        return 0
    codes = np.frombuffer(bare, np.uint8)
    step = np.isin(codes, (0x5B, 0x7B)).astype(np.int32) - np.isin(codes, (0x5D, 0x7D)).astype(
        np.int32
    )
    return int(np.cumsum(step).max(initial=0))


def check_json_depth(data: bytes, what: str, max_depth: int = MAX_JSON_DEPTH) -> None:
    """``ValueError`` naming ``what`` when ``data`` nests deeper than ``max_depth`` levels."""
    depth = json_depth(data)
    if depth > max_depth:
        raise ValueError(f"{what}: JSON nested {depth} levels deep, at most {max_depth} allowed")


class _NonFinite:
    """Stands in for a number JSON cannot hold while the document is parsed."""

    __slots__ = ("text",)

    def __init__(self, text: str) -> None:
        self.text = text


def _float(text: str) -> Any:
    value = float(text)
    return value if math.isfinite(value) else _NonFinite(text)


def _int(text: str) -> Any:
    # beyond float range: pydantic cannot take it as a number, Python refuses > 4300 digits
    return _NonFinite(text[:20] + "…") if len(text.lstrip("-")) > 308 else int(text)


def loads_finite(data: bytes | str, what: str, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """Parse JSON refusing deep nesting and non-finite numbers; ``ValueError`` names the place.

    ``NaN``, ``Infinity``, ``-Infinity`` and literals that overflow a float (``1e400``) are
    refused with their path, e.g. ``"body.points[0][1]: NaN is not a finite number"``;
    the depth is checked before parsing (:func:`check_json_depth`).

    Args:
        data: UTF-8 JSON text.
        what: the document's name, the start of every message and path.
        max_depth: deepest nesting allowed.

    Raises:
        ValueError: too deep, non-finite, or not JSON (``json.JSONDecodeError``, a subclass).
    """
    raw = data.encode("utf-8") if isinstance(data, str) else data
    check_json_depth(raw, what, max_depth)
    doc = json.loads(raw, parse_constant=_NonFinite, parse_float=_float, parse_int=_int)
    bad = _find_nonfinite(doc, what)
    if bad is not None:
        path, text = bad
        raise ValueError(f"{path}: {text} is not a finite number (JSON numbers must be finite)")
    return doc


def _find_nonfinite(doc: Any, path: str) -> tuple[str, str] | None:
    """The first (path, literal) of a non-finite number in ``doc``; iterative (no recursion)."""
    stack: list[tuple[Any, str]] = [(doc, path)]
    while stack:
        node, where = stack.pop()
        if isinstance(node, _NonFinite):
            return where, node.text
        if isinstance(node, dict):
            stack.extend((v, f"{where}.{_short(k)}") for k, v in reversed(node.items()))
        elif isinstance(node, list):
            stack.extend((v, f"{where}[{i}]") for i, v in reversed(list(enumerate(node))))
    return None


def _short(name: str, limit: int = 40) -> str:
    """A key as it appears in a message: printable, at most ``limit`` characters."""
    text = name if name.isprintable() else repr(name)
    return text if len(text) <= limit else text[:limit] + f"…({len(name)} chars)"
