#!/usr/bin/env python3
"""Writes docs/rest-api.md from the service's OpenAPI document (crowdbake.api.app.create_app().openapi()).

    .venv/bin/python scripts/gen_rest_docs.py            # rewrite docs/rest-api.md
    .venv/bin/python scripts/gen_rest_docs.py --check    # exit 1 if the committed file is out of date

The reference is generated so that it cannot drift from the routes: tests/test_docs.py fails when the
committed file differs from what this script writes. The narrative (auth, problems, bakes) is in
docs/service.md. Output is deterministic: operations in the app's route order grouped by tag, schemas
sorted by name.
"""
from __future__ import annotations

import argparse
import difflib
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
OUTPUT = REPO_ROOT / "docs" / "rest-api.md"
PROBLEM_MEDIA_TYPE = "application/problem+json"
METHODS = ("get", "post", "put", "patch", "delete", "head")
# JSON Schema keywords shown in the constraints column, with how to write them.
CONSTRAINTS = {
    "minimum": "≥ {}", "maximum": "≤ {}", "exclusiveMinimum": "> {}", "exclusiveMaximum": "< {}",
    "minLength": "length ≥ {}", "maxLength": "length ≤ {}", "minItems": "items ≥ {}", "maxItems": "items ≤ {}",
    "pattern": "pattern `{}`",
}


def openapi_document() -> dict[str, Any]:
    """The app's OpenAPI document, built in a throwaway data folder (nothing is migrated or served)."""
    sys.path.insert(0, str(REPO_ROOT / "services"))
    from crowdbake.api.app import create_app
    from crowdbake.settings import Settings

    with tempfile.TemporaryDirectory(prefix="crowdbake-openapi-") as folder:
        app = create_app(Settings(data_dir=Path(folder), migrate_on_start=False))
        document = app.openapi()
        app.state.services.sessions.kw["bind"].dispose()
    return json.loads(json.dumps(document))  # plain data, in a stable form


# ------------------------------------------------------------------------------------- rendering


def anchor(text: str) -> str:
    """GitHub's heading anchor: lower case, punctuation dropped, spaces to hyphens."""
    kept = "".join(ch for ch in text.lower() if ch.isalnum() or ch in " -_")
    return kept.replace(" ", "-")


def cell(text: Any) -> str:
    """Text for a table cell: one line, pipes escaped."""
    return " ".join(str(text).split()).replace("|", "\\|")


def number(value: Any) -> str:
    return str(int(value)) if isinstance(value, float) and value.is_integer() else str(value)


def schema_type(schema: dict[str, Any]) -> str:
    """A short human name of a schema: `BakeParamsIn`, `integer or null`, `array of string`, ..."""
    if not schema:
        return "any"
    if "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        return f"[{name}](#{anchor(name)})"
    for key in ("anyOf", "oneOf"):
        if key in schema:
            return " or ".join(dict.fromkeys(schema_type(option) for option in schema[key]))
    if "allOf" in schema and len(schema["allOf"]) == 1:
        return schema_type(schema["allOf"][0])
    if "const" in schema:
        return f"`{json.dumps(schema['const'])}`"
    if "enum" in schema:
        return "one of " + ", ".join(f"`{value}`" for value in schema["enum"])
    kind = schema.get("type", "any")
    if kind == "array":
        return f"array of {schema_type(schema.get('items', {}))}"
    if kind == "object" and isinstance(schema.get("additionalProperties"), dict):
        return f"object of {schema_type(schema['additionalProperties'])}"
    if kind == "string" and schema.get("format") == "binary":
        return "file"
    if "format" in schema:
        return f"{kind} ({schema['format']})"
    return str(kind)


def constraints(schema: dict[str, Any]) -> str:
    parts = []
    for source in [schema, *schema.get("anyOf", [])]:
        for key, template in CONSTRAINTS.items():
            if key in source:
                parts.append(template.format(number(source[key])))
    return ", ".join(dict.fromkeys(parts))


def default(schema: dict[str, Any]) -> str:
    return f"`{json.dumps(schema['default'])}`" if "default" in schema else ""


def field_facts(schema: dict[str, Any], required: bool) -> str:
    """Type, whether required, default and constraints of one field or parameter, comma-separated."""
    facts = [schema_type(schema)]
    if required:
        facts.append("required")
    if "default" in schema:
        facts.append(f"default {default(schema)}")
    if constraints(schema):
        facts.append(constraints(schema))
    return ", ".join(facts)


def field_list(schema: dict[str, Any]) -> list[str]:
    """The fields of an object schema: inline when none has a description, else one line each."""
    required = set(schema.get("required", []))
    props = schema.get("properties", {})
    if not any(prop.get("description") for prop in props.values()):
        return ["Fields: " + "; ".join(f"`{name}` {field_facts(prop, name in required)}" for name, prop in props.items()) + "."]
    lines = []
    for name, prop in props.items():
        description = " ".join(prop.get("description", "").split())
        lines.append(f"- `{name}` ({field_facts(prop, name in required)})" + (f": {description}" if description else ""))
    return lines


def is_problem(status: str, response: dict[str, Any]) -> bool:
    return status >= "400" and PROBLEM_MEDIA_TYPE in (response.get("content") or {})


def common_errors(document: dict[str, Any]) -> dict[str, str]:
    """The usual meaning of each error status (the one most operations give it)."""
    counts: dict[tuple[str, str], int] = {}
    for item in document["paths"].values():
        for method in METHODS:
            for status, response in item.get(method, {}).get("responses", {}).items():
                if is_problem(status, response):
                    key = (status, response.get("description", ""))
                    counts[key] = counts.get(key, 0) + 1
    usual: dict[str, str] = {}
    for (status, description), count in sorted(counts.items(), key=lambda entry: -entry[1]):
        usual.setdefault(status, description)
    return dict(sorted(usual.items()))


def render_operation(method: str, path: str, operation: dict[str, Any], errors: dict[str, str]) -> list[str]:
    title = f"`{method.upper()} {path}`"
    lines = [f"### {title}", ""]
    text = []
    if operation.get("summary"):
        text.append(operation["summary"] + ("" if operation["summary"].endswith(".") else "."))
    if operation.get("description"):
        text.append(" ".join(operation["description"].split()))
    if not operation.get("security"):
        text.append("Authentication: none.")
    if text:
        lines += [" ".join(text), ""]
    # Path parameters that are plain required strings are already named by the path.
    parameters = [parameter for parameter in operation.get("parameters", [])
                  if not (parameter["in"] == "path" and parameter.get("schema", {}).get("type") == "string"
                          and not parameter.get("description") and not constraints(parameter.get("schema", {})))]
    for parameter in parameters:
        description = " ".join(parameter.get("description", "").split())
        lines.append(f"- `{parameter['name']}` ({parameter['in']}, {field_facts(parameter.get('schema', {}), parameter.get('required', False))})"
                     + (f": {description}" if description else ""))
    if parameters:
        lines.append("")
    body = operation.get("requestBody")
    if body:
        for media_type, content in body.get("content", {}).items():
            schema = content.get("schema", {})
            head = f"Request body (`{media_type}`{', required' if body.get('required') else ''})"
            if "$ref" in schema or "properties" not in schema:
                lines += [f"{head}: {schema_type(schema)}.", ""]
            else:
                fields = field_list(schema)
                if fields[0].startswith("Fields: "):
                    lines += [f"{head}, fields: {fields[0][len('Fields: '):]}", ""]
                else:
                    lines += [f"{head}:", "", *fields, ""]
    answers, problems = [], []
    for status, response in sorted(operation.get("responses", {}).items()):
        description = response.get("description", "")
        if is_problem(status, response):
            problems.append(status if errors.get(status) == description else f"{status} ({description})")
            continue
        content = response.get("content") or {}
        schema = next((entry.get("schema") for entry in content.values() if entry.get("schema")), None)
        parts = [status]
        if schema and "$ref" in schema:
            parts.append(schema_type(schema))
        else:
            parts += [f"`{media}`" for media in content]
            if schema and schema_type(schema) not in ("string", "any"):
                parts.append(schema_type(schema))
        answer = " ".join(parts)
        if description and description != "Successful Response":
            answer += f" ({description})"
        answers.append(answer)
    lines.append("Returns " + "; ".join(answers) + "." + (f" Errors: {', '.join(problems)}." if problems else ""))
    lines.append("")
    return lines


def render(document: dict[str, Any]) -> str:
    info = document["info"]
    tags = [tag["name"] for tag in document.get("tags", [])]
    by_tag: dict[str, list[tuple[str, str, dict]]] = {tag: [] for tag in tags}
    for path, item in document["paths"].items():
        for method in METHODS:
            if method in item:
                operation = item[method]
                by_tag.setdefault((operation.get("tags") or ["other"])[0], []).append((method, path, operation))
    descriptions = {tag["name"]: tag.get("description", "") for tag in document.get("tags", [])}
    errors = common_errors(document)

    lines = [
        "# REST API reference",
        "",
        f"<!-- Generated by scripts/gen_rest_docs.py from the OpenAPI document of {info['title']} {info['version']}; "
        "do not edit by hand (tests/test_docs.py checks it is current). -->",
        "",
        f"{info['title']} {info['version']}, OpenAPI {document['openapi']}. A running service serves the same document at "
        "`/openapi.json` and interactive docs at `/docs`; [service.md](service.md) explains keys, scopes, uploads, bakes and "
        "problem types, and [quickstart.md](quickstart.md) walks through a first bake.",
        "",
        info.get("description", "").strip(),
        "",
        "How to read an operation: path parameters in braces are required strings; query parameters and body fields are "
        "listed as name (type, required, default, constraints): description; \"Returns\" gives each success status with its "
        "body (JSON unless a media type is named). \"Errors\" lists the statuses that answer a "
        f"[Problem](#problem) document (`{PROBLEM_MEDIA_TYPE}`), with these meanings unless the operation says otherwise: "
        + "; ".join(f"{status} {description}" for status, description in errors.items()) + ".",
        "",
    ]
    for tag, operations in by_tag.items():
        if not operations:
            continue
        lines += [f"## {tag}", ""]
        if descriptions.get(tag):
            lines += [descriptions[tag], ""]
        for method, path, operation in operations:
            lines += render_operation(method, path, operation, errors)
    body_text = "\n".join(lines)
    lines += ["## Schemas", "", "Objects that operations return or accept, by name.", ""]
    schemas = document.get("components", {}).get("schemas", {})
    # Only schemas some operation (or a shown schema) refers to; the rest are FastAPI's unused defaults.
    shown = {name for name in schemas if f"](#{anchor(name)})" in body_text}
    pending = list(shown)
    while pending:
        text = json.dumps(schemas[pending.pop()])
        for name in schemas:
            if name not in shown and f'"#/components/schemas/{name}"' in text:
                shown.add(name)
                pending.append(name)
    for name, schema in sorted(schemas.items()):
        if name not in shown:
            continue
        lines += [f"### {name}", ""]
        if schema.get("description"):
            lines += [" ".join(schema["description"].split()), ""]
        if schema.get("properties"):
            lines += field_list(schema)
            if schema.get("additionalProperties") is False:
                lines += ["", "Other fields are refused."]
        else:
            lines.append(f"Type: {schema_type(schema)}.")
        lines.append("")
    security = document.get("components", {}).get("securitySchemes", {})
    if security:
        lines += ["## Authentication schemes", ""]
        for name, scheme in sorted(security.items()):
            how = f"header `{scheme['name']}`" if scheme.get("type") == "apiKey" else f"{scheme.get('type')} {scheme.get('scheme', '')}".strip()
            lines.append(f"- {name} ({how}): {' '.join(scheme.get('description', '').split())}")
        lines.append("")
    return "\n".join(lines).rstrip() + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true", help="compare with the committed file instead of writing it")
    parser.add_argument("--out", type=Path, default=OUTPUT, help=f"output (default {OUTPUT.relative_to(REPO_ROOT)})")
    args = parser.parse_args()
    text = render(openapi_document())
    if args.check:
        current = args.out.read_text(encoding="utf-8") if args.out.exists() else ""
        if current == text:
            print(f"{args.out} is up to date")
            return 0
        sys.stdout.writelines(difflib.unified_diff(current.splitlines(True), text.splitlines(True), str(args.out), "generated", n=1))
        print(f"\n{args.out} is out of date: run scripts/gen_rest_docs.py", file=sys.stderr)
        return 1
    args.out.write_text(text, encoding="utf-8")
    print(f"wrote {args.out} ({len(text.splitlines())} lines)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
