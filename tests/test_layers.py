"""The architecture, checked: imports run one way, there are no import cycles, modules stay
readable, and the code speaks the house vocabulary of data_specs/CONVENTIONS.md.

Layers, bottom up::

    lensfit core (optics, psf, targets, stack, calibration, measure, estimators, fitting, ...)
        <- synth (renders; uses the core's optics, files, errors, writers)
            <- lensfit.bench (renders with synth, then measures and fits)
                <- lensfit.cli (the command line; synth.cli beside it)

Every import counts, also those inside functions (lazy imports only move the cycle to run time).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("lensfit", "synth")
#: Readable at once: about 500 lines. Modules still above it may not grow (a ratchet: lower a
#: ceiling when a module shrinks, remove it when it is under the limit).
MAX_LINES = 500
OVERSIZE_CEILING: dict[str, int] = {}


def modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


MODULES = modules()


def imports_of(path: Path) -> set[str]:
    """Every lensfit/synth module ``path`` imports (``from lensfit import optics`` -> lensfit.optics)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in MODULES else node.module
                     for a in node.names]
        else:
            continue
        found |= {n for n in names if n.split(".")[0] in PACKAGES}
    return found


GRAPH = {name: imports_of(path) for name, path in MODULES.items()}


def layer(name: str) -> str:
    if name == "lensfit.cli" or name.startswith("lensfit.cli.") or name in ("lensfit.__main__", "synth.cli",
                                                                           "synth.bench"):
        return "cli"
    if name == "lensfit.bench" or name.startswith("lensfit.bench.") or name == "synth.plan_costs":
        return "bench"  # (synth.plan_costs: renders and times synth, writes a benchmark record)
    return "synth" if name.split(".")[0] == "synth" else "core"


RANK = {"core": 0, "synth": 1, "bench": 2, "cli": 3}


def test_the_graph_sees_the_known_imports():
    # the test itself must see imports, lazy ones included: guards against a parser that finds none
    assert "lensfit.fitting.core" in GRAPH["lensfit.fitting"] and "lensfit.fitting.model" in GRAPH["lensfit.fitting.solve"]
    assert "synth.rendering" in GRAPH["lensfit.bench.runs"]
    assert "lensfit.optics" in GRAPH["synth.geometry"]


@pytest.mark.parametrize("name", sorted(MODULES))
def test_imports_point_down_the_layers(name):
    mine = layer(name)
    for target in GRAPH[name]:
        if target in PACKAGES:  # the package facade (__version__, lazy attributes)
            continue
        theirs = layer(target)
        assert RANK[theirs] <= RANK[mine], f"{name} ({mine}) imports {target} ({theirs}): imports must point down"
    if name.startswith("synth") and layer(name) == "synth":
        assert not any(t.startswith("synth.cli") or t == "synth.bench" for t in GRAPH[name]), name


def test_no_import_cycles():
    graph = {n: {t for t in ts if t in GRAPH and t not in PACKAGES} for n, ts in GRAPH.items() if n not in PACKAGES}
    index, low, stack, on, cycles = {}, {}, [], set(), []
    counter = [0]

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"


def test_modules_stay_readable():
    for name, path in MODULES.items():
        rel = str(path.relative_to(ROOT))
        n = len(path.read_text().splitlines())
        ceiling = OVERSIZE_CEILING.get(rel, MAX_LINES)
        assert n <= ceiling, f"{rel} has {n} lines (limit {ceiling}); split it by responsibility"
    for rel, ceiling in OVERSIZE_CEILING.items():
        assert len((ROOT / rel).read_text().splitlines()) > MAX_LINES, f"{rel} is under {MAX_LINES}: drop its ceiling"


#: Spellings the house does not use (data_specs/CONVENTIONS.md), with the word it does.
NOT_HOUSE_WORDS = {
    r"\bf_?num\b|\bfnumber\b|\bf_stop\b": "f_number",
    r"\bfocal_len\b|\bfocallength\b|\bfocal_mm\b": "focal_length_mm",
    r"\bpixel_size(_mm)?\b|\bpx_size\b": "pixel_pitch_mm",
    r"\bcoc_radius\w*|\bblur_radius\w*": "coc_diameter_* (a blur is a diameter)",
    r"\bexposure_time\w*|\bshutter_time\w*|\bshutter_speed\w*": "shutter_s",
    r"\bfocus_dist\b|\bfocus_distance_m\b|\bsubject_distance_mm\b": "focus_distance_mm",
    r"\baperture_radius\b(?!_)": "aperture_diameter_mm or ..._radius_...",
    r"^inv_d$|^inv_focus$|^inverse_focus_per_mm$|^inverse_focus_distance$|^channel_inverse_focus_per_mm$":
        "inverse_focus_distance_per_mm (the fit's parameter: inv_focus_per_m, dioptres)",
}


def identifiers(path: Path) -> set[str]:
    """Names the code defines or reads (not its comments or prose), and string keys."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Name):
            out.add(node.id)
        elif isinstance(node, ast.Attribute):
            out.add(node.attr)
        elif isinstance(node, ast.arg):
            out.add(node.arg)
        elif isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            out.add(node.name)
        elif isinstance(node, ast.keyword) and node.arg:
            out.add(node.arg)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and re.fullmatch(r"[a-z_][a-z0-9_]*",
                                                                                               node.value):
            out.add(node.value)
    return out


#: Names another library's API spells its own way: (module, name).
FOREIGN_NAMES = {("synth/mitsuba.py", "aperture_radius")}  # Mitsuba 3's thinlens camera


def test_code_speaks_the_house_words():
    bad = []
    for name, path in MODULES.items():
        for ident in identifiers(path):
            if (str(path.relative_to(ROOT)), ident) in FOREIGN_NAMES:
                continue
            for pattern, word in NOT_HOUSE_WORDS.items():
                if re.search(pattern, ident):
                    bad.append(f"{path.relative_to(ROOT)}: {ident!r} (house word: {word})")
    assert not bad, "\n".join(sorted(bad))
    conventions = (ROOT / "data_specs" / "CONVENTIONS.md").read_text()
    for word in ("f_number", "focal_length_mm", "pixel_pitch_mm", "coc_diameter_px", "shutter_s",
                 "focus_distance_mm", "aperture_diameter_mm"):
        assert f"`{word}`" in conventions, f"CONVENTIONS.md does not define {word}"


#: Lines a function of the fit and of the measure path may take, its docstring aside: their
#: stages are functions with names (lensfit.fitting.stages, lensfit.measurement.measure._Run), not one body of
#: closures.
FIT_FUNCTION_LINES = 100
MEASURE_PATH = ("measurement/*.py", "calibration/camera.py", "calibration/sigma.py", "estimators/*.py")


def test_the_fit_and_measure_functions_are_short():
    long = []
    paths = list((ROOT / "lensfit" / "fitting").glob("*.py"))
    for pattern in MEASURE_PATH:
        paths += (ROOT / "lensfit").glob(pattern)
    for path in sorted(paths):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                first = node.body[0]
                if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(
                        first.value.value, str):
                    lines -= first.end_lineno - first.lineno + 1
                if lines > FIT_FUNCTION_LINES:
                    long.append(f"{path.name}:{node.lineno} {node.name} ({lines} lines)")
    assert not long, long


def test_no_private_name_crosses_a_module():
    """A module's underscored names are its own: another module (the tests too) imports only what
    a module offers, so that a private helper can change without reading the whole house."""
    crossing = []
    paths = list(MODULES.values()) + sorted((ROOT / "tests").rglob("*.py"))
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] in PACKAGES:
                crossing += [f"{path.relative_to(ROOT)}:{node.lineno} {node.module}.{a.name}" for a in node.names
                             if a.name.startswith("_") and not a.name.startswith("__")]
    assert not crossing, "\n".join(crossing)


def test_one_array_backend_idiom():
    """Code that runs on NumPy and JAX alike takes its namespace from its inputs
    (``lensfit.optics.checks.namespace``): no function is handed the namespace as an argument, and
    no setting holds it."""
    handed = []
    for name, path in MODULES.items():
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                args = node.args
                names = [a.arg for a in (*args.posonlyargs, *args.args, *args.kwonlyargs)]
                if "xp" in names:
                    handed.append(f"{name}:{node.lineno} {getattr(node, 'name', 'lambda')}(xp)")
            elif isinstance(node, ast.Call) and "ContextVar" in (getattr(node.func, "attr", None),
                                                                    getattr(node.func, "id", None)):
                handed.append(f"{name}:{node.lineno} ContextVar")
    assert not handed, handed
