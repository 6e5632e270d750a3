"""Benchmark records: the one current table per suite that the documentation shows.

``lensfit bench --record DIR`` writes ``DIR/<suite>.json`` from the run's ``results.json``: when
and how it was made (date, command, machine, cores, wall time, seeds) and per quantity the RMS
relative error, the share of 95 % intervals holding the truth with its binomial interval over
the effective count, the RMS of error over sigma and the mean 95 % half-width over the mean
error. A new run of a suite replaces its record; the earlier ones live in version control.

The documentation site renders each record as a table (``docs/hooks.py``), and the README's
accuracy table is generated from the records (``python -m lensfit.bench.records --readme
README.md``, ``make readme-table``), between the lines ``<!-- accuracy-table:start -->`` and
``<!-- accuracy-table:end -->``.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from lensfit.bench.coverage import GAUSSIAN_HALF_WIDTH_RATIO
from lensfit.bench.suites import QUANTITIES
from lensfit.errors import InputError

#: Bumped when a record's fields change meaning.
RECORD_VERSION = 1
START, END = "<!-- accuracy-table:start -->", "<!-- accuracy-table:end -->"
#: Suites in the order the README lists them; others follow by name.
ORDER = ("independent", "standard", "coverage")
LABELS = {"focal_length_mm": "f", "f_number": "N", "focus_distance_mm": "focus distance"}


def make_record(doc: dict[str, Any]) -> dict[str, Any]:
    """A suite's record from a ``lensfit bench`` results document (its ``results.json``)."""
    from lensfit.bench.report import report_rows

    try:
        suite, prov, cases, coverage = doc["suite"], doc["provenance"], doc["cases"], doc["coverage"]
        rows = report_rows(cases, suite["tolerances"])
    except (KeyError, TypeError) as exc:
        raise InputError("results", "a bench results document", "one written by lensfit bench",
                         f"missing {exc}") from exc
    quantities = {}
    for q in QUANTITIES:
        errs = [r["relative_error"] for r in rows if r["quantity"] == q and r["relative_error"] is not None]
        c = coverage.get(q) or {}
        quantities[q] = {
            "estimates": len(errs),
            "rms_relative_error": math.sqrt(sum(e * e for e in errs) / len(errs)) if errs else None,
            "coverage95": c.get("coverage95"), "coverage95_ci95": c.get("coverage95_ci95"),
            "intervals": c.get("intervals"), "intervals_effective": c.get("intervals_effective"),
            "rms_error_over_sigma": c.get("rms_error_over_sigma"),
            "half_width95_over_mean_error": c.get("half_width95_over_mean_error"),
        }
    first = prov.get("first_run") or {}
    return {"record_version": RECORD_VERSION, "suite": suite["name"], "description": suite.get("description", ""),
            "date": prov.get("date"), "command": prov.get("command"), "version": prov.get("version"),
            "system": prov.get("system"), "cores": prov.get("cores"), "jobs": prov.get("jobs"),
            "seeds": prov.get("seeds"), "seconds_wall": prov.get("seconds_wall"),
            "seconds_wall_first_run": first.get("seconds_wall"), "cases": len(cases), "quantities": quantities}


def record_header(benchmark: str, command: str) -> dict[str, Any]:
    """What every benchmark record other than a suite's begins with: its name, the day (UTC), the
    command that regenerates it, the system and the cores it was measured on."""
    import os
    import platform
    from datetime import UTC, datetime

    return {"benchmark": benchmark, "date": datetime.now(UTC).strftime("%Y-%m-%d"), "command": command,
            "system": f"{platform.system()} {platform.machine()}", "cores": os.cpu_count()}


def write_json(folder: str | Path, name: str, data: dict[str, Any]) -> Path:
    """Write (or replace) the record ``folder/<name>.json``, the folder made where missing."""
    from lensfit.outputs.writers import write_text

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    return write_text(folder / f"{name}.json", json.dumps(data, indent=1, allow_nan=False) + "\n")


def write_record(doc: dict[str, Any], folder: str | Path) -> Path:
    """Write (or replace) ``folder/<suite>.json`` from a bench results document."""
    record = make_record(doc)
    return write_json(folder, record["suite"], record)


def load_records(folder: str | Path) -> list[dict[str, Any]]:
    """Every suite's record in ``folder``, in the README's order (other benchmarks' records,
    such as ``lensfit bench-api``'s, are left out)."""
    records = [r for r in (json.loads(p.read_text()) for p in sorted(Path(folder).glob("*.json"))) if "suite" in r]
    rank = {name: i for i, name in enumerate(ORDER)}
    return sorted(records, key=lambda r: (rank.get(r["suite"], len(ORDER)), r["suite"]))


def _pct(x: float | None, digits: int = 2) -> str:
    return "-" if x is None else f"{100 * x:.{digits}f} %"


def _num(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def _when(record: dict[str, Any]) -> str:
    return (record.get("date") or "")[:10] or "undated"


def _minutes(record: dict[str, Any]) -> str:
    seconds = record.get("seconds_wall_first_run") or record.get("seconds_wall")
    return "" if seconds is None else f"{seconds / 60:.1f} min"


def suite_table(record: dict[str, Any]) -> str:
    """Markdown: a suite's record as the validation page shows it."""
    head = [f"## Suite `{record['suite']}`", "", record.get("description", "").strip(), "",
            f"{record['cases']} cases; measured {_when(record)} with `{record.get('command')}` "
            f"(lensfit {record.get('version')}, {record.get('cores')} cores, {_minutes(record)}).", "",
            f"| quantity | estimates | RMS error | 95 % intervals holding the truth | binomial 95 % interval "
            f"(effective count) | error / sigma, RMS (1 if right) | 95 % half-width / mean error "
            f"({GAUSSIAN_HALF_WIDTH_RATIO:.2f} if right) |", "|---|---|---|---|---|---|---|"]
    for q, v in record["quantities"].items():
        ci = v.get("coverage95_ci95")
        ci_text = "-" if not ci else f"{100 * ci[0]:.0f}-{100 * ci[1]:.0f} % ({v.get('intervals_effective') or 0:.0f})"
        head.append(f"| {LABELS.get(q, q)} | {v['estimates']} | {_pct(v['rms_relative_error'])} | "
                    f"{_pct(v['coverage95'], 0)} of {v.get('intervals') or 0} | {ci_text} | "
                    f"{_num(v['rms_error_over_sigma'])} | {_num(v['half_width95_over_mean_error'])} |")
    return "\n".join(head)


def headline_table(records: list[dict[str, Any]]) -> str:
    """Markdown: the README's accuracy table, one row per suite, then when and how each was made."""
    qs = QUANTITIES
    lines = ["| suite | what is in it | RMS error: f / N / focus distance | 95 % intervals holding the truth "
             "| error / sigma, RMS (1 if right) |", "|---|---|---|---|---|"]
    for r in records:
        v = r["quantities"]
        lines.append(
            f"| `{r['suite']}` | {r.get('description', '').strip()} ({r['cases']} cases) | "
            + " / ".join(_pct(v[q]["rms_relative_error"]).replace(" %", "") for q in qs) + " % | "
            + " / ".join(_pct(v[q]["coverage95"], 0).replace(" %", "") for q in qs) + " % | "
            + " / ".join(_num(v[q]["rms_error_over_sigma"]) for q in qs) + " |")
    lines.append("")
    lines += [f"- `{r['suite']}`: {_when(r)}, `{r.get('command')}` ({r.get('cores')} cores, {_minutes(r)})"
              for r in records]
    return "\n".join(lines)


def replace_readme_table(text: str, records: list[dict[str, Any]]) -> str:
    """``text`` with the block between the accuracy-table markers generated from ``records``."""
    start, end = text.find(START), text.find(END)
    if start < 0 or end < start:
        raise InputError("README", "no accuracy-table markers", f"the lines {START} and {END}")
    return text[:start + len(START)] + "\n" + headline_table(records) + "\n" + text[end:]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lensfit.bench.records",
                                     description="Write the README's accuracy table from the benchmark records.")
    parser.add_argument("--readme", default="README.md", help="the README to update (default README.md)")
    parser.add_argument("--records", default="docs/validation/records", help="the records' folder")
    args = parser.parse_args(argv)
    from lensfit.outputs.writers import write_text

    readme = Path(args.readme)
    new = replace_readme_table(readme.read_text(), load_records(args.records))
    if new != readme.read_text():
        write_text(readme, new)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
