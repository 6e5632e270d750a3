"""Reading the files people write: TOML/JSON loading and JSON-Schema validation.

Errors are :class:`lensfit.errors.SpecError`: one line naming the file, the field (a dotted
path such as ``object[2].distance_mm``), the bad value and what is expected.
"""

from __future__ import annotations

import functools
import json
import math
import re
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from lensfit.errors import SpecError


def specs_dir() -> Path:
    """The ``data_specs`` folder (schemas, conventions, sensor formats, scenes, suites)."""
    try:
        path = Path(str(resources.files("lensfit.data_specs")))
        if path.is_dir():
            return path
    except ModuleNotFoundError:  # running from a source tree without installation
        pass
    return Path(__file__).resolve().parents[2] / "data_specs"


def load_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file; unreadable or malformed files raise :class:`SpecError`."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            data = fh.read()
        # A byte-order mark (some Windows editors write one) is no TOML; it is read past.
        return tomllib.loads(data.removeprefix(b"\xef\xbb\xbf").decode("utf-8"))
    except FileNotFoundError:
        raise SpecError(path, "", "file not found") from None
    except IsADirectoryError:
        raise SpecError(path, "", "is a folder, expected a TOML file") from None
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(path, "", f"not valid TOML ({exc})") from None
    except RecursionError:
        raise SpecError(path, "", "is nested too deeply (arrays or tables within each other) to be a stack or "
                        "scene file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SpecError(path, "", f"cannot be read ({exc})") from None


#: The largest JSON file lensfit reads or writes (a samples file of about a million rows): a bigger one is
#: refused before it is read, not parsed into memory many times its size.
MAX_JSON_BYTES = 256 * 1024 * 1024


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    seen: dict[str, Any] = {}
    for key, value in pairs:
        if key in seen:
            raise ValueError(f"the key {key!r} appears twice in one object")
        seen[key] = value
    return seen


def load_json(path: str | Path, max_bytes: int = MAX_JSON_BYTES) -> Any:
    """Parse a JSON file; unreadable, oversized, malformed or too deeply nested files, and objects
    with a key twice, raise :class:`SpecError` naming the file."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > max_bytes:
            raise SpecError(path, "", f"is {size / 1e6:.0f} MB, more than the {max_bytes / 1e6:.0f} MB lensfit reads "
                            "as JSON; is it the file you meant?")
        text = path.read_text(encoding="utf-8-sig")
        return json.loads(text, object_pairs_hook=_unique_keys)
    except RecursionError:
        raise SpecError(path, "", "is nested too deeply to be a file lensfit wrote") from None
    except json.JSONDecodeError as exc:
        raise SpecError(path, "", f"not valid JSON ({exc})") from None
    except ValueError as exc:  # a key twice (_unique_keys)
        raise SpecError(path, "", f"not valid here: {exc}; remove the duplicate") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SpecError(path, "", f"cannot be read ({exc})") from None


@functools.cache
def schema(name: str) -> dict[str, Any]:
    """A JSON Schema from ``data_specs/schemas/NAME.schema.json``."""
    return json.loads((specs_dir() / "schemas" / f"{name}.schema.json").read_text())


def _field_path(parts) -> str:
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


def _first_non_finite(data: Any, parts: tuple = ()) -> tuple[tuple, float] | None:
    """(field path, value) of the first NaN or infinite number in nested dicts and lists."""
    if isinstance(data, float) and not math.isfinite(data):
        return parts, data
    if isinstance(data, dict):
        items = data.items()
    elif isinstance(data, list):
        items = enumerate(data)
    else:
        return None
    for key, value in items:
        found = _first_non_finite(value, (*parts, key))
        if found is not None:
            return found
    return None


def _unknown_key(error, field: str, schema_name: str) -> tuple[str, str]:
    """(field, message) for a key the schema does not know: its full name, the nearest valid
    one ("did you mean"), and the valid keys."""
    import difflib

    known = sorted(error.schema.get("properties", {}))
    allowed = set(known)
    patterns = list(error.schema.get("patternProperties", {}))
    unknown = [k for k in (error.instance or {}) if k not in allowed
               and not any(re.match(p, k) for p in patterns)]
    key = unknown[0] if unknown else "?"
    where = f"{field}.{key}" if field else key
    close = difflib.get_close_matches(key, known, n=1, cutoff=0.6)
    hint = f"did you mean {close[0]!r}? " if close else ""
    extra = "; your own fields may start with x_" if patterns else ""
    return where, (f"unknown key; {hint}valid here: {', '.join(known)}{extra} "
                   f"(data_specs/schemas/{schema_name}.schema.json)")


def validate(data: Any, schema_name: str, path: str | Path) -> None:
    """Validate ``data`` against a schema; the first (most relevant) problem raises SpecError.

    NaN and infinite numbers are refused everywhere before the schema is consulted (JSON Schema's
    bounds let NaN through: every comparison with NaN is false); where a file may say infinity
    it writes the string "inf".
    """
    import jsonschema

    bad = _first_non_finite(data)
    if bad is not None:
        where, value = bad
        raise SpecError(path, _field_path(where) or "(top level)",
                        f"got {value}: write a finite number (where infinity is meant, the string \"inf\" "
                        "if the field allows it)")

    validator = jsonschema.Draft202012Validator(schema(schema_name))
    error = jsonschema.exceptions.best_match(validator.iter_errors(data))
    if error is None:
        return
    field = _field_path(error.absolute_path)
    if error.validator == "required":
        missing = error.message.split("'")[1] if "'" in error.message else error.message
        raise SpecError(path, _field_path([*error.absolute_path, missing]), "is required but missing")
    if error.validator == "additionalProperties":
        raise SpecError(path, *_unknown_key(error, field, schema_name))
    if error.validator in ("anyOf", "oneOf") and all(set(sub) == {"required"} for sub in error.validator_value):
        options = " or ".join("+".join(sub["required"]) for sub in error.validator_value)
        raise SpecError(path, field or "(top level)", f"needs {options}; none is given")
    raise SpecError(path, field or "(top level)", f"got {error.instance!r}: {error.message}")
