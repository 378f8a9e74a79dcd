"""Architecture guards (cf. prysm's import-linting test), issue 17.

Every import statement in ``raywave/`` — module level and inside functions alike — is read with ``ast`` and
checked against the layer table in docs/architecture.md (parsed from the doc, so the doc is the rule):

* a module may import raywave modules of its own package, or of packages in a **lower** layer; never a package of
  the same layer or a higher one;
* the external-import limits of the doc's second table (matplotlib only in plotting / the CLI; no torch in io);
* no import cycles between modules (every edge counted, lazy ones too), and none between packages;
* exceptions only from :data:`ALLOWED`, each with its reason.

Plus the runtime guards: importing physics never loads matplotlib or the CLI; ``import raywave`` changes no torch
global state and loads neither matplotlib nor the heavy layers (the façade is lazy).
"""

import ast
import re
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PKG = ROOT / "raywave"
DOC = ROOT / "docs" / "architecture.md"

#: (importer, imported) edges that break the layering on purpose, with the reason. Keep this list short.
ALLOWED = {
    ("raywave.hybrid", "raywave.assembly"):
        "compatibility: `raywave.hybrid.load_hybrid` / `hybrid_from_spec` are lazy (PEP 562) aliases of "
        "raywave.assembly.build, where building a hybrid from a spec moved in issue 17",
    ("raywave.hybrid.build", "raywave.assembly.build"):
        "compatibility: the old module path `raywave.hybrid.build` re-exports raywave.assembly.build (issue 17)",
}


# ---------------------------------------------------------------------------- the doc's tables
def _table(marker: str) -> list[list[str]]:
    """Rows (cells) of the markdown table that follows ``<!-- marker -->`` in docs/architecture.md."""
    text = DOC.read_text(encoding="utf-8")
    start = text.index(f"<!-- {marker} -->")
    rows = []
    for line in text[start:].splitlines()[1:]:
        if not line.startswith("|"):
            if rows:
                break
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if set("".join(cells)) <= set("-: "):
            continue
        rows.append(cells)
    return rows[1:]  # without the header


def layer_table() -> dict[str, int]:
    """package -> layer number, from the doc's layer table."""
    layers = {}
    for cells in _table("layer-table"):
        for name in re.findall(r"`([\w.]+)`", cells[1]):
            layers[name] = int(cells[0])
    return layers


def external_limits() -> list[tuple[str, list[str], list[str], bool]]:
    """(external module, packages that may import it (empty: any but the forbidden), packages that must not,
    whether the limit holds for imports inside functions too ("anywhere") or at module level only)."""
    out = []
    for cells in _table("external-table"):
        ext = re.findall(r"`([\w.]+)`", cells[0])[0]
        out.append((ext, re.findall(r"`([\w.]+)`", cells[1]), re.findall(r"`([\w.]+)`", cells[2]),
                    cells[3].startswith("anywhere")))
    return out


# ---------------------------------------------------------------------------- the imports
def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


MODULES = {_module_name(p): p for p in sorted(PKG.rglob("*.py"))}


def _resolve(name: str) -> str:
    """The raywave module an imported dotted name lives in (``raywave.doe.DOE`` → ``raywave.doe``)."""
    while name not in MODULES and "." in name:
        name = name.rsplit(".", 1)[0]
    return name


def _lazy_lines(tree) -> set[int]:
    """Line numbers of the import statements inside function bodies (run on call, not on import)."""
    out = set()
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            out |= {n.lineno for n in ast.walk(fn) if isinstance(n, (ast.Import, ast.ImportFrom))}
    return out


def imports(lazy: bool = False) -> list[tuple]:
    """Every (importer, imported module, line) of every import statement in raywave/ (module level and inside
    functions); raywave targets resolved to the module they name. ``lazy=True``: (…, line, inside a function)."""
    out = []
    for mod, path in MODULES.items():
        is_pkg = path.name == "__init__.py"
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        in_function = _lazy_lines(tree)
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:  # relative: from the importer's package
                    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                    base = base[: len(base) - node.level + 1]
                    module = ".".join(base + ([node.module] if node.module else []))
                else:
                    module = node.module
                # `from pkg import submodule` imports the submodule
                names = [f"{module}.{a.name}" if f"{module}.{a.name}" in MODULES else module for a in node.names]
            else:
                continue
            for n in names:
                target = _resolve(n) if n.split(".")[0] == "raywave" else n
                out.append((mod, target, node.lineno) + ((node.lineno in in_function,) if lazy else ()))
    return out


def _package(mod: str, layers: dict) -> str | None:
    """The table entry a module belongs to (the longest matching prefix; ``raywave`` itself only exactly)."""
    best = None
    for name in layers:
        if mod == name or (name != "raywave" and mod.startswith(name + ".")):
            if best is None or len(name) > len(best):
                best = name
    return best


def _edges():
    layers = layer_table()
    return layers, [(a, b, line) for a, b, line in imports() if b.split(".")[0] == "raywave"]


# ---------------------------------------------------------------------------- tests
def test_the_layer_table_covers_every_module():
    layers = layer_table()
    assert len(layers) >= 10, "the layer table in docs/architecture.md was not found or is too short"
    missing = sorted(m for m in MODULES if _package(m, layers) is None)
    assert not missing, f"modules in no layer of docs/architecture.md's table: {missing}"


def test_every_import_respects_the_layers():
    layers, edges = _edges()
    bad = []
    used_allowances = set()
    for a, b, line in edges:
        pa, pb = _package(a, layers), _package(b, layers)
        if pa == pb:
            continue
        if layers[pb] < layers[pa]:
            continue
        key = next((k for k in ALLOWED if a == k[0] and (b == k[1] or b.startswith(k[1] + "."))), None)
        if key is not None:
            used_allowances.add(key)
            continue
        how = "same layer" if layers[pb] == layers[pa] else "upward"
        bad.append(f"{MODULES[a].relative_to(ROOT)}:{line}: {a} → {b} ({how}: {pa} is layer {layers[pa]}, "
                   f"{pb} layer {layers[pb]})")
    assert not bad, "imports against docs/architecture.md's layer table:\n" + "\n".join(bad)
    stale = set(ALLOWED) - used_allowances
    assert not stale, f"allow-list entries no longer needed (remove them): {sorted(stale)}"


def test_external_import_limits():
    layers = layer_table()
    bad = []
    for ext, only, never, anywhere in external_limits():
        for a, b, line, lazy in imports(lazy=True):
            if (b != ext and not b.startswith(ext + ".")) or (lazy and not anywhere):
                continue
            pa = _package(a, layers)
            if (only and pa not in only) or pa in never:
                bad.append(f"{MODULES[a].relative_to(ROOT)}:{line}: {a} imports {b}")
    assert not bad, "external imports against docs/architecture.md:\n" + "\n".join(bad)


def _cycles(graph: dict) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v), on.add(v)
        for w in graph.get(v, ()):
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
                out.append(sorted(comp))

    for v in list(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles_between_modules():
    _, edges = _edges()
    graph = defaultdict(set)
    for a, b, _ in edges:
        if a != b:
            graph[a].add(b)
    cycles = _cycles(graph)
    assert not cycles, f"import cycles (modules importing each other, lazily or not): {cycles}"


def test_no_import_cycles_between_packages():
    layers, edges = _edges()
    graph = defaultdict(set)
    for a, b, _ in edges:
        if any(a == k[0] and (b == k[1] or b.startswith(k[1] + ".")) for k in ALLOWED):
            continue
        pa, pb = _package(a, layers), _package(b, layers)
        if pa != pb:
            graph[pa].add(pb)
    assert not _cycles(graph)


def test_the_checker_sees_imports_inside_functions(tmp_path):
    """The AST walk finds a lazy import in a function body (what the old sys.modules test missed)."""
    found = [(a, b) for a, b, _ in imports() if a == "raywave.models.exit_pupil" and b == "raywave.lens.analysis"]
    assert found, "the lazy import of beam_half_extent in ExitPupilModel._check_clear was not seen"


# ---------------------------------------------------------------------------- runtime guards
PHYSICS = ["raywave.materials", "raywave.surfaces", "raywave.rays", "raywave.lens", "raywave.io", "raywave.doe",
           "raywave.doe.fabrication", "raywave.doe.tolerance", "raywave.wave", "raywave.hybrid",
           "raywave.hybrid.metrics", "raywave.assembly", "raywave.assembly.build", "raywave.assembly.tolerance",
           "raywave.models", "raywave.imaging", "raywave.imaging.data", "raywave.training",
           "raywave.training.trainer", "raywave.training.distributed", "raywave.training.baselines",
           "raywave.training.parallel", "raywave.training.replay"]


def _modules_after_import(code):
    code = "import sys\n" + code + "\nprint('\\n'.join(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return set(out.stdout.split())


def test_physics_does_not_import_plotting_or_cli():
    loaded = _modules_after_import("".join(f"import {m}\n" for m in PHYSICS))
    assert "matplotlib" not in loaded
    assert not any(m.startswith("raywave.plotting") or m.startswith("raywave.cli") for m in loaded)


def test_io_does_not_import_torch():
    assert "torch" not in _modules_after_import("import raywave.io")


def test_import_raywave_is_light_and_leaves_torch_alone():
    """The façade is lazy: `import raywave` loads no layer above the lens and no matplotlib, and touching one of
    its names leaves torch's defaults alone."""
    loaded = _modules_after_import("import raywave")
    assert "matplotlib" not in loaded
    assert not any(m.startswith(("raywave.training", "raywave.imaging", "raywave.cli", "raywave.plotting"))
                   for m in loaded)
    code = ("import torch; d = torch.get_default_dtype(); g = torch.is_grad_enabled(); import raywave;"
            "raywave.Lens, raywave.HybridLens, raywave.psf_map, raywave.Trainer, raywave.make_model;"
            "assert torch.get_default_dtype() == d == torch.float32 and torch.is_grad_enabled() == g")
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("edge", sorted(ALLOWED))
def test_allowed_edges_say_why(edge):
    assert len(ALLOWED[edge]) > 30


# ---------------------------------------------------------------------------- value types over long lists (issue 43)
#: the most parameters a function of the engine's packages takes (``*args`` and ``**kwargs`` count one each)
MAX_PARAMETERS = 10


def _parameter_count(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    a = fn.args
    names = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs if x.arg not in ("self", "cls")]
    return len(names) + (a.vararg is not None) + (a.kwarg is not None)


def test_engine_functions_take_at_most_ten_parameters():
    """Issue 43: ≤ 10 parameters per function in ``raywave/hybrid`` and ``raywave/wave`` (value types instead)."""
    long = []
    for pkg in ("hybrid", "wave"):
        for path in sorted((PKG / pkg).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    k = _parameter_count(node)
                    if k > MAX_PARAMETERS:
                        long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({k})")
    assert not long, "functions with more than 10 parameters: " + "; ".join(long)
