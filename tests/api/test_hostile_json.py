"""Hostile JSON sent to every JSON operation of the generated OpenAPI document.

The operations, their body properties and their parameters are read from the live app's own
OpenAPI document (a route added later is covered without editing this file). Each gets
non-finite numbers (``NaN``, ``Infinity``, ``-Infinity``, ``1e400``) in every property and
inside arrays, nesting 100 000 deep (and just past the limit), and names of 300 characters
(values, keys, path parameters). Every answer must be a 4xx whose ``detail`` is one line;
a non-finite number must be refused naming the property that holds it. The app runs on the
simulator (its lifespan started), so a request that got through would reach the instrument.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.core.jsonlimits import MAX_JSON_DEPTH
from app.main import create_app
from tests.helpers.live_app import live_settings

NON_FINITE = ("NaN", "Infinity", "-Infinity", "1e400")
LONG = "n" * 300


def _resolve(spec: dict[str, Any], schema: dict[str, Any]) -> dict[str, Any]:
    while "$ref" in schema:
        schema = spec["components"]["schemas"][schema["$ref"].rsplit("/", 1)[1]]
    return schema


def _properties(spec: dict[str, Any], schema: dict[str, Any]) -> list[str]:
    """Top-level property names of a body schema (through $ref, anyOf and oneOf)."""
    schema = _resolve(spec, schema)
    names = list(schema.get("properties", {}))
    for alt in schema.get("anyOf", []) + schema.get("oneOf", []):
        names += [n for n in _properties(spec, alt) if n not in names]
    return names


def _tag_rest(schema: dict[str, Any]) -> str:
    """The rest of a body that keeps a union alternative's ``type`` tag (so the property under
    test is what fails), or ""."""
    tag = schema.get("properties", {}).get("type", {})
    tag_value = tag.get("const", (tag.get("enum") or [None])[0])
    return "" if tag_value is None else f', "type": {json.dumps(tag_value)}'


def _json_body_schemas(spec: dict[str, Any]) -> Iterator[tuple[str, str, dict[str, Any]]]:
    """(method, path, body schema) of every operation whose body is JSON."""
    for path, item in spec["paths"].items():
        for method, op in item.items():
            content = op.get("requestBody", {}).get("content", {})
            if "application/json" in content:
                yield method.upper(), path, content["application/json"]["schema"]


def json_operations(spec: dict[str, Any]) -> list[tuple[str, str, list[str]]]:
    """(method, path, body properties) of every operation that takes a JSON body."""
    return [(method, path, _properties(spec, schema))
            for method, path, schema in _json_body_schemas(spec)]


def parameter_cases(spec: dict[str, Any]) -> list[tuple[str, str, str, str]]:
    """(method, path, where, name) of every path parameter and numeric query parameter."""
    out = []
    for path, item in spec["paths"].items():
        for method, op in item.items():
            for p in op.get("parameters", []):
                types = {s.get("type") for s in [p["schema"], *p["schema"].get("anyOf", [])]}
                if p["in"] == "path" or types & {"number", "integer"}:
                    out.append((method.upper(), path, p["in"], p["name"]))
    return out


@pytest.fixture(scope="module")
def client(
    tmp_path_factory: pytest.TempPathFactory, sim_calibration_file: Path
) -> Iterator[TestClient]:
    """The app on the simulator, its instrument started (no need to wait for a first result)."""
    settings = live_settings(tmp_path_factory.mktemp("hostile"), sim_calibration_file)
    with TestClient(create_app(settings)) as client:
        yield client
        inst = client.app.state.instrument  # type: ignore[attr-defined]
        assert inst.acquisition is not None and inst.acquisition.alive, "the instrument stopped"
        assert (summary := inst.calibrations.summary()) is not None and summary.name == "sim", (
            "the hostile input changed the calibration"
        )


@pytest.fixture(scope="module")
def spec(client: TestClient) -> dict[str, Any]:
    return client.app.openapi()  # type: ignore[attr-defined, no-any-return]


def _send(client: TestClient, method: str, path: str, body: str | bytes) -> Any:
    url = path.replace("{index}", "0").replace("{name}", "op")
    return client.request(method, url, content=body, headers={"content-type": "application/json"})


def _one_line_4xx(r: Any, what: str) -> str:
    assert 400 <= r.status_code < 500, f"{what}: {r.status_code} {r.text[:300]}"
    detail = r.json()["detail"]
    assert isinstance(detail, str) and detail and "\n" not in detail, f"{what}: {detail!r}"
    assert len(detail) < 600, f"{what}: a {len(detail)}-character reason"
    return detail


def test_the_document_has_json_operations(spec: dict[str, Any]) -> None:
    ops = {(m, p) for m, p, _ in json_operations(spec)}
    # the probe's list of routes that answered 500 to NaN: all must be covered here
    for op in [
        ("PUT", "/api/exposure"),
        ("PUT", "/api/led"),
        ("PUT", "/api/mode"),
        ("POST", "/api/measure"),
        ("POST", "/api/analysis/plane"),
        ("POST", "/api/analysis/feature"),
        ("PUT", "/api/measure/tool"),
        ("POST", "/api/exposure/auto"),
        ("POST", "/api/calibration/session"),
        ("POST", "/api/calibration/session/solve"),
        ("PUT", "/api/schedule"),
        ("POST", "/api/recording/start"),
        ("PUT", "/api/calibration/file"),
    ]:
        assert op in ops, op
    assert all(props for m, p, props in json_operations(spec)), "an operation without properties"


def test_non_finite_numbers_are_422_naming_the_field(
    client: TestClient, spec: dict[str, Any]
) -> None:
    seen = 0
    for method, path, props in json_operations(spec):
        for prop in props:
            for lit in NON_FINITE:
                for body, where in (
                    (f'{{"{prop}": {lit}}}', f"body.{prop}"),
                    (f'{{"{prop}": [1, [2, {lit}]]}}', f"body.{prop}[1][1]"),
                ):
                    r = _send(client, method, path, body)
                    what = f"{method} {path} {body}"
                    assert r.status_code == 422, f"{what}: {r.status_code} {r.text[:200]}"
                    detail = _one_line_4xx(r, what)
                    assert detail.startswith(where + ":") and lit in detail, f"{what}: {detail}"
                    seen += 1
    assert seen > 200


def _numeric_properties(spec: dict[str, Any], schema: dict[str, Any]) -> list[tuple[str, str]]:
    """(property, the rest of a body) for each top-level number property (through
    $ref, anyOf and oneOf; an alternative's ``type`` tag is kept so the number is what fails)."""
    schema = _resolve(spec, schema)
    rest = _tag_rest(schema)
    out = []
    for name, prop in schema.get("properties", {}).items():
        prop = _resolve(spec, prop)
        types = {_resolve(spec, s).get("type") for s in [prop, *prop.get("anyOf", [])]}
        if "number" in types:
            out.append((name, rest))
    for alt in schema.get("anyOf", []) + schema.get("oneOf", []):
        out += [case for case in _numeric_properties(spec, alt) if case not in out]
    return out


def test_a_boolean_or_a_string_for_a_number_is_422_naming_the_field(
    client: TestClient, spec: dict[str, Any]
) -> None:
    """JSON ``false`` is not 0 and ``"0.1"`` is not 0.1: a number field refuses both (a
    lax parser read ``{"saturation_limit": false}`` as a 0 % saturation limit)."""
    seen = 0
    for method, path, schema in _json_body_schemas(spec):
        for prop, rest in _numeric_properties(spec, schema):
            for lit in ("false", "true", '"0.1"'):
                body = f'{{"{prop}": {lit}{rest}}}'
                r = _send(client, method, path, body)
                what = f"{method} {path} {body}"
                assert r.status_code == 422, f"{what}: {r.status_code} {r.text[:200]}"
                detail = _one_line_4xx(r, what)
                assert f".{prop}: " in detail, f"{what}: {detail}"  # names it
                seen += 1
    assert seen >= 9  # exposure, auto-exposure (2), and the rest the document has


def _integer_properties(
    spec: dict[str, Any], schema: dict[str, Any]
) -> list[tuple[str, int, str]]:
    """(property, its minimum item count (0 for a scalar), the rest of a body) for each top-level
    property holding integers: an integer, or an array of them."""
    schema = _resolve(spec, schema)
    rest = _tag_rest(schema)
    out = []
    for name, prop in schema.get("properties", {}).items():
        for alt in [_resolve(spec, s) for s in [_resolve(spec, prop), *prop.get("anyOf", [])]]:
            if alt.get("type") == "integer":
                out.append((name, 0, rest))
            elif (alt.get("type") == "array"
                  and _resolve(spec, alt["items"]).get("type") == "integer"):
                out.append((name, max(1, alt.get("minItems", 1)), rest))
    for alt in schema.get("anyOf", []) + schema.get("oneOf", []):
        out += [case for case in _integer_properties(spec, alt) if case not in out]
    return out


def test_a_boolean_or_a_string_for_an_integer_is_422_naming_the_field(
    client: TestClient, spec: dict[str, Any]
) -> None:
    """JSON ``false`` is not 0 and ``"5"`` is not 5 where an integer belongs (a ROI, a board's
    corners, a set's index), alone or in an array; ``19.0`` stays an integer (JSON Schema's)."""
    seen = 0
    for method, path, schema in _json_body_schemas(spec):
        if (method, path) == ("PUT", "/api/calibration/file"):
            continue  # a calibration file, read by its format's reader (tests/calib)
        for prop, items, rest in _integer_properties(spec, schema):
            for lit, kind in (("false", "a boolean"), ("true", "a boolean"), ('"5"', "a string")):
                value = lit if items == 0 else "[" + ", ".join([lit] * items) + "]"
                body = f'{{"{prop}": {value}{rest}}}'
                r = _send(client, method, path, body)
                what = f"{method} {path} {body}"
                assert r.status_code == 422, f"{what}: {r.status_code} {r.text[:200]}"
                detail = _one_line_4xx(r, what)
                assert f".{prop}: must be a JSON integer, not {kind}" in detail, (
                    f"{what}: {detail}")
                seen += 1
    assert seen >= 12  # ROI (2 routes), board corners (2 board types), reference and set index


def test_non_finite_query_and_path_parameters_are_4xx_naming_them(
    client: TestClient, spec: dict[str, Any]
) -> None:
    cases = parameter_cases(spec)
    assert any(name == "min_mm" for *_, name in cases)
    for method, path, where, name in cases:
        for lit in NON_FINITE:
            if where == "query":
                url = path.replace("{index}", "0").replace("{name}", "op") + f"?{name}={lit}"
            else:
                url = (
                    path.replace("{" + name + "}", lit)
                    .replace("{index}", "0")
                    .replace("{name}", "op")
                )
            r = client.request(method, url)
            what = f"{method} {url}"
            detail = _one_line_4xx(r, what)
            if r.status_code == 422:
                assert f"{where}.{name}" in detail, f"{what}: {detail}"


def test_deep_nesting_is_refused_before_parsing(client: TestClient, spec: dict[str, Any]) -> None:
    deep = 100_000
    for method, path, props in json_operations(spec):
        for body in (
            "[" * deep + "]" * deep,
            f'{{"{props[0]}": ' + "[" * deep + "]" * deep + "}",
            '{"a": ' + '{"a": ' * MAX_JSON_DEPTH + "1" + "}" * (MAX_JSON_DEPTH + 1),
        ):
            r = _send(client, method, path, body)
            detail = _one_line_4xx(r, f"{method} {path} nested")
            assert r.status_code in (413, 422), (method, path, detail)
            assert detail.startswith("body"), detail
            if r.status_code == 422:
                assert "nested" in detail and str(MAX_JSON_DEPTH) in detail, detail


def test_names_of_300_characters_are_4xx(client: TestClient, spec: dict[str, Any]) -> None:
    for method, path, props in json_operations(spec):
        bodies = [{LONG: 1}] + [{prop: LONG} for prop in props]
        for body in bodies:
            r = _send(client, method, path, json.dumps(body))
            _one_line_4xx(r, f"{method} {path} {list(body)[0][:20]}")
    for method, path, where, name in parameter_cases(spec):
        if where != "path":
            continue
        url = path.replace("{" + name + "}", LONG).replace("{index}", "0").replace("{name}", "op")
        r = client.request(method, url)
        detail = _one_line_4xx(r, f"{method} {path} long {name}")
        if r.status_code == 422:
            assert f"path.{name}" in detail, detail


def test_the_error_body_is_serialisable_whatever_the_input(client: TestClient) -> None:
    """pydantic's errors echo the input: made plain JSON, cut short, in ``errors``."""
    r = client.put("/api/exposure", json={"exposure_ms": "x" * 10_000})
    assert r.status_code == 422
    body = r.json()
    assert body["detail"].startswith("body.exposure_ms: ")
    item = body["errors"][0]
    assert item["loc"] == ["body", "exposure_ms"] and len(item["input"]) < 100
    r = client.put(
        "/api/exposure",
        content=b'{"exposure_ms": "\xff\xfe"}',
        headers={"content-type": "application/json"},
    )
    _one_line_4xx(r, "invalid UTF-8")
