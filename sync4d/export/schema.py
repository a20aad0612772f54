"""The JSON Schema of the scene description (`scene.schema.json`, shipped in the package) and
`validate`, which checks a description against it with jsonschema (draft 2020-12)."""

from __future__ import annotations

import functools
import json
from pathlib import Path

__all__ = ["SCHEMA_FILE", "SceneError", "schema", "validate"]

#: The schema, beside this module.
SCHEMA_FILE = Path(__file__).with_name("scene.schema.json")


class SceneError(ValueError):
    """A scene description that is malformed or cannot be written; the message names the file."""


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
