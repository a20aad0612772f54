"""The JSON Schema of the scene description (`scene.schema.json`, shipped in the package),
generated from the model (`sync4d.export.model.Scene`: `generate`, `schema_text`; ``python
scripts/gen_docs.py`` rewrites the file and a test fails when it is not current), and
`validate`, which checks a description against it with jsonschema (draft 2020-12)."""

from __future__ import annotations

import functools
import json
from pathlib import Path

from sync4d.errors import Sync4dError

__all__ = ["SCHEMA_FILE", "SceneError", "generate", "schema", "schema_text", "validate"]

#: The schema, beside this module.
SCHEMA_FILE = Path(__file__).with_name("scene.schema.json")


class SceneError(Sync4dError, ValueError):
    """A scene description that is malformed or cannot be written; the message names the file."""


#: The schema's address and title (its description is the `Scene` model's).
SCHEMA_ID = "https://github.com/sync4d/sync4d/export/scene.schema.json"
SCHEMA_TITLE = "sync4d scene description"
#: Keywords first, in this order, in every schema object of the file (then the others, as
#: pydantic gives them).
_ORDER = ("$schema", "$id", "$ref", "title", "description", "type", "const", "enum", "pattern",
          "minimum", "maximum", "items", "minItems", "maxItems", "required",
          "additionalProperties", "properties", "anyOf", "$defs")  # fmt: skip


def _tidy(node: object) -> object:
    """`node` (a part of pydantic's schema) without pydantic's titles and null defaults
    (annotations the file never had), its keywords in `_ORDER`."""
    if isinstance(node, list):
        return [_tidy(v) for v in node]
    if not isinstance(node, dict):
        return node
    out = {}
    for key in sorted(node, key=lambda k: _ORDER.index(k) if k in _ORDER else len(_ORDER)):
        value = node[key]
        if key == "title" or (key == "default" and value is None):
            continue
        if key in ("properties", "$defs"):  # names, not keywords: kept as they are
            out[key] = {name: _tidy(v) for name, v in value.items()}
        elif key == "description":  # a docstring: on one line
            out[key] = " ".join(value.split())
        else:
            out[key] = _tidy(value)
    return out


def generate() -> dict:
    """The scene description's JSON Schema, generated from `sync4d.export.model.Scene`: draft
    2020-12, the records under ``$defs``; ``embeddings`` required (a file always has it)."""
    from sync4d.export.model import Scene

    raw = Scene.model_json_schema(mode="validation")
    raw["required"] = [*raw["required"], "embeddings"]
    body = _tidy(raw)
    assert isinstance(body, dict)
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "$id": SCHEMA_ID,
            "title": SCHEMA_TITLE, **body}  # fmt: skip


def schema_text() -> str:
    """`generate()` as the shipped file holds it (laid out as the description is: one key a
    line, lists of scalars on one line)."""
    from sync4d.export.model import dumps

    return dumps(generate()) + "\n"


@functools.cache
def schema() -> dict:
    """The scene description's JSON Schema as a dict."""
    return json.loads(SCHEMA_FILE.read_text(encoding="utf-8"))


def validate(doc: object, path: str | Path) -> None:
    """SceneError naming `path` and the first offending field unless `doc` is valid."""
    import jsonschema

    validator = jsonschema.Draft202012Validator(schema())
    error = jsonschema.exceptions.best_match(validator.iter_errors(doc))
    if error is not None:
        where = "/".join(str(p) for p in error.absolute_path) or "(the top level)"
        raise SceneError(f"{path}: not a sync4d scene description: at {where}: "
                         f"{error.message}")  # fmt: skip
