"""JSON depth without recursion, non-finite numbers refused with their path."""

from __future__ import annotations

import json
import time

import pytest

from app.core.jsonlimits import MAX_JSON_DEPTH, check_json_depth, json_depth, loads_finite


@pytest.mark.parametrize(
    "text, depth",
    [
        (b"1", 0),
        (b"[]", 1),
        (b'{"a": [1, {"b": 2}]}', 3),
        (b'{"a": "[[[{{{"}', 1),
        (b'["\\"[[[", [2]]', 2),
        (b"[[[", 3),
    ],
)
def test_depth_skips_strings_and_needs_no_valid_json(text: bytes, depth: int) -> None:
    assert json_depth(text) == depth


def test_depth_of_100000_levels_is_measured_not_recursed() -> None:
    deep = b"[" * 100_000 + b"]" * 100_000
    t0 = time.perf_counter()
    assert json_depth(deep) == 100_000
    assert time.perf_counter() - t0 < 1.0
    with pytest.raises(
        ValueError, match=f"^doc: JSON nested 100000 levels deep, at most {MAX_JSON_DEPTH}"
    ):
        check_json_depth(deep, "doc")
    with pytest.raises(ValueError, match="nested 100000 levels"):
        loads_finite(deep, "doc")


@pytest.mark.parametrize(
    "text, where, literal",
    [
        ('{"x": NaN}', "body.x", "NaN"),
        ('{"a": [1, {"b": Infinity}]}', "body.a[1].b", "Infinity"),
        ("[-Infinity]", "body[0]", "-Infinity"),
        ('{"k": 1e400}', "body.k", "1e400"),
        ('{"k": -1E+999}', "body.k", "-1E+999"),
        ('{"k": ' + "9" * 400 + "}", "body.k", "999"),
        ('{"' + "n" * 300 + '": NaN}', "body." + "n" * 40 + "…(300 chars)", "NaN"),
    ],
)
def test_non_finite_numbers_are_refused_naming_the_place(
    text: str, where: str, literal: str
) -> None:
    with pytest.raises(ValueError) as info:
        loads_finite(text, "body")
    message = str(info.value)
    assert message.startswith(where + ": " + literal) and "not a finite number" in message, message
    assert "\n" not in message


def test_finite_documents_parse_as_json_does() -> None:
    doc = {"a": [1, 2.5, -3e-7, 1e308, {"b": None, "c": "NaN"}], "d": True}
    assert loads_finite(json.dumps(doc), "body") == doc
    with pytest.raises(json.JSONDecodeError):
        loads_finite("{", "body")
