"""MkDocs hooks: the pages that are generated from the code and the data, never written by hand.

A page holds a marker comment where generated text belongs:

- ``<!-- cli:lensfit -->`` / ``<!-- cli:synth -->``: every subcommand from the program's own
  argparse parser (usage, description, options with their defaults);
- ``<!-- schemas -->``: every file format from ``data_specs/schemas/*.schema.json``;
- ``<!-- conventions -->``: ``data_specs/CONVENTIONS.md``;
- ``<!-- validation -->``: one table per benchmark suite from ``docs/validation/records/``;
- ``<!-- changelog -->``: ``CHANGELOG.md``;
- ``<!-- example:NAME -->``: ``docs/examples/NAME.py`` as a code block.

So the reference cannot drift from the code: a renamed option or a new schema field shows up
in the next build.
"""

from __future__ import annotations

import argparse
import importlib
import json
import re
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

MARKER = re.compile(r"<!-- (cli:\w+|schemas|conventions|validation|changelog|example:\w+) -->")


def _escape(text: str) -> str:
    return text.replace("|", "\\|").replace("<", "&lt;").replace(">", "&gt;").replace("\n", " ")


def cli_markdown(program: str) -> str:
    """Markdown for every subcommand of ``program`` (``lensfit`` or ``synth``), from its parser."""
    if program == "lensfit":
        from lensfit.cli import build_parser
    elif program == "synth":
        from synth.cli import build_parser
    else:
        raise ValueError(f"no program {program!r}")
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    out = [parser.description or "", ""]
    helps = {c.dest: c.help for c in sub._choices_actions}
    for name, p in sub.choices.items():
        out += [f"## `{program} {name}`", "", _escape(p.description or helps.get(name) or ""), "",
                "```text", p.format_usage().strip(), "```", ""]
        rows = []
        formatter = p._get_formatter()
        for action in p._actions:
            if isinstance(action, argparse._HelpAction) or action.help == argparse.SUPPRESS:
                continue
            names = ", ".join(action.option_strings) or action.dest
            meta = ""
            if action.nargs != 0:
                meta = action.metavar if isinstance(action.metavar, str) else (
                    " ".join(action.metavar) if action.metavar else action.dest.upper())
            choices = f" (one of {', '.join(map(str, action.choices))})" if action.choices else ""
            helptext = formatter._expand_help(action) if action.help else ""
            default = ""
            if action.option_strings and action.default not in (None, False, argparse.SUPPRESS) \
                    and "default" not in helptext.lower():
                default = f" Default: `{action.default}`."
            rows.append(f"| `{names}` | {_escape(str(meta))} | {_escape(helptext + choices)}{default} |")
        if rows:
            out += ["| option | value | meaning |", "|---|---|---|", *rows, ""]
    return "\n".join(out)


def _schema_rows(schema: dict, prefix: str = "", depth: int = 0) -> list[str]:
    rows = []
    required = set(schema.get("required", []))
    for key, prop in (schema.get("properties") or {}).items():
        name = f"{prefix}{key}"
        kind = prop.get("type", "")
        if isinstance(kind, list):
            kind = " or ".join(kind)
        if not kind and "enum" in prop:
            kind = "one of " + ", ".join(f"`{v}`" for v in prop["enum"])
        desc = prop.get("description", "")
        rows.append(f"| `{name}` | {_escape(str(kind))} | {'yes' if key in required else ''} | {_escape(desc)} |")
        if depth < 2:
            if prop.get("type") == "object":
                rows += _schema_rows(prop, name + ".", depth + 1)
            items = prop.get("items")
            if isinstance(items, dict) and items.get("type") == "object":
                rows += _schema_rows(items, name + "[].", depth + 1)
    return rows


def schemas_markdown() -> str:
    out = []
    for path in sorted((ROOT / "data_specs" / "schemas").glob("*.schema.json")):
        schema = json.loads(path.read_text())
        out += [f"## {schema.get('title', path.stem)}", "",
                f"Schema: `data_specs/schemas/{path.name}`. " + _escape(schema.get("description", "")), ""]
        rows = _schema_rows(schema)
        if rows:
            out += ["| field | type | required | meaning |", "|---|---|---|---|", *rows, ""]
    return "\n".join(out)


def conventions_markdown() -> str:
    text = (ROOT / "data_specs" / "CONVENTIONS.md").read_text()
    return re.sub(r"^# .*\n", "", text, count=1)  # the page has its own title


def changelog_markdown() -> str:
    text = (ROOT / "CHANGELOG.md").read_text()
    return re.sub(r"^# .*\n", "", text, count=1)


def validation_markdown() -> str:
    from lensfit.bench.records import load_records, suite_table

    folder = DOCS / "validation" / "records"
    records = load_records(folder)
    parts = [suite_table(r) for r in records] or [
        "No benchmark record yet: run `lensfit bench --suite NAME --out DIR --record docs/validation/records`."]
    # the other benchmarks' records, each shown by its own module's markdown()
    # (bench-lenses writes one record per variant, lenses*.json: lensfit.bench.lenses.record_name)
    lenses = sorted(p.stem for p in folder.glob("lenses*.json"))
    for name, module in (("api_vs_cli", "lensfit.bench.api"), ("developed", "lensfit.bench.developed"),
                         *((name, "lensfit.bench.lenses") for name in lenses),
                         ("stages", "lensfit.bench.stages"), ("plan_costs", "synth.plan_costs"),
                         ("synth_vs_mitsuba", "synth.bench"),
                         ("hostile", "lensfit.bench.hostile")):
        record = folder / f"{name}.json"
        if record.is_file():
            parts.append(importlib.import_module(module).markdown(json.loads(record.read_text())))
    return "\n\n".join(parts)


def example_markdown(name: str) -> str:
    path = DOCS / "examples" / f"{name}.py"
    return f"```python\n{path.read_text().rstrip()}\n```"


def _expand(match: re.Match) -> str:
    key = match.group(1)
    if key.startswith("cli:"):
        return cli_markdown(key[4:])
    if key.startswith("example:"):
        return example_markdown(key[8:])
    return {"schemas": schemas_markdown, "conventions": conventions_markdown,
            "validation": validation_markdown, "changelog": changelog_markdown}[key]()


def on_page_markdown(markdown: str, page, config, files) -> str:  # noqa: ARG001 (MkDocs' signature)
    return MARKER.sub(_expand, markdown)
