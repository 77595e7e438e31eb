"""The brief's structure, checked on the source: a pure numerical core (numpy/scipy arrays in, arrays out)
that never imports USD, USD reading and writing at the edges, and no import cycles between modules.

Read from the source (``ast``), not by importing: the lazy imports inside functions count too."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "usdface"

#: The numerical core: arrays in, arrays out, no USD types. ``transfer/pipeline.py`` is the implant's
#: orchestrator (it reads the avatar and writes the layer when given paths) and ``personalize/report.py``
#: and ``landmarks/plots.py`` write files: they are edges inside the packages and are not listed.
CORE = ["mesh.py", "motion.py", "model.py", "submesh.py", "bounded_lsq.py", "arkit.py", "namelist.py",
        "take_select.py", *(f"personalize/{n}" for n in ("align.py", "amplitude.py", "api.py", "contact.py",
                                                          "crossval.py", "dt.py", "ebfr.py", "evaluate.py",
                                                          "fit.py", "laplacian.py", "takefit.py", "weak.py",
                                                          "weights.py")),
        *(f"transfer/{n}" for n in ("correspond.py", "denoise.py", "eyelids.py", "face_map.py", "implant.py",
                                    "motion_field.py", "options.py", "partial_dt.py", "register.py",
                                    "report.py", "retarget.py", "scoring.py", "surface.py", "trust.py")),
        *(f"landmarks/{n}" for n in ("baselines.py", "candidates.py", "cover.py", "diagnostics.py",
                                     "evaluate.py", "layout.py", "multicover.py", "reconstruct.py",
                                     "sampling.py", "symmetry.py", "visibility.py"))]

#: Packages and modules that read or write USD, or face the user: the core may not import them.
EDGES = ("usdface.io", "usdface.api", "usdface.cli", "usdface.commands", "usdface.pipeline",
         "usdface.review", "usdface.render", "usdface.inspect", "usdface.schemas")
#: ... except the atomic file writer (a temporary file renamed into place; no USD), which the
#: correspondence cache (``transfer/correspond.py``, an ``.npz``) uses.
ALLOWED = ("usdface.io.atomic",)


def _module(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module(p): p for p in PACKAGE.rglob("*.py")}


def _imports(path: Path, modules, top_level_only: bool) -> set[str]:
    """The modules ``path`` imports (``from . import sub`` names the submodule, not its package); with
    ``top_level_only``, those imported when the module itself is imported (not inside functions)."""
    name = _module(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    if top_level_only:
        nodes = []
        stack = list(tree.body)
        while stack:
            node = stack.pop()
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                continue
            nodes.append(node)
            stack.extend(ast.iter_child_nodes(node))
    else:
        nodes = list(ast.walk(tree))
    found = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            subs = [f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in modules]
            found.update(subs if subs and len(subs) == len(node.names) else [target, *subs])
    return found - {name}


def test_the_numerical_core_never_imports_usd_or_the_edges():
    """No core module imports ``pxr`` (anywhere, lazy imports too) or an edge package (io, api, cli, ...):
    arrays in, arrays out, so the core runs and is tested without USD."""
    modules = _modules()
    offences = []
    for rel in CORE:
        path = PACKAGE / rel
        assert path.is_file(), f"CORE lists {rel}, which is not in usdface/ (update the list)"
        for target in _imports(path, modules, top_level_only=False):
            if target.split(".")[0] == "pxr" or (target.startswith(EDGES) and target not in ALLOWED):
                offences.append(f"usdface/{rel} imports {target}")
    assert not offences, "\n".join(offences)


def test_every_core_package_module_is_classified():
    """A new module in personalize/, transfer/ or landmarks/ is either core (listed) or a named edge: the
    core list cannot silently fall behind the source."""
    edges_inside = {"transfer/pipeline.py", "personalize/report.py", "landmarks/plots.py"}
    for package in ("personalize", "transfer", "landmarks"):
        for path in (PACKAGE / package).glob("*.py"):
            rel = f"{package}/{path.name}"
            assert path.name == "__init__.py" or rel in CORE or rel in edges_inside, rel


def test_no_import_cycles_between_modules():
    """The graph of module-level imports between usdface's modules has no cycle (Tarjan's strongly
    connected components, each of one module)."""
    modules = _modules()
    graph = {m: {t for t in _imports(p, modules, top_level_only=True) if t in modules}
             for m, p in modules.items()}
    index, low, stack, on, cycles, counter = {}, {}, [], set(), [], [0]

    def visit(v):
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not cycles, cycles
