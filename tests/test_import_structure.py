"""The package reads top-down: no import circle (also none through imports inside functions), the bottom floors
import nothing from above, and every module imports alone, and the whole package in another order, in a fresh
process.

Static: an AST walk of geer_ns/**/*.py, every `import` statement wherever it stands (a late import inside a
function is still an edge: it only hides a circle until that function runs). Without a circle no import order
can meet a half-initialised geer module. Dynamic: one helper process imports the heavy third-party packages geer
uses (torch, nerfstudio's models, ...; stopping short of nerfstudio's plugin discovery, which imports geer
itself) and checks that no geer_ns module is loaded yet; then, for each module, it forks a child that imports
that module first and alone. A fork holds no geer_ns module, so each child meets geer's imports as a fresh
interpreter does, at a fraction of the cost of 50 interpreters each importing torch (95 s on 2 cores).
Meanwhile one plain fresh interpreter (nothing preloaded) imports the whole package in reverse order.
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "geer_ns"

# Floors that must not import from above: each may import geer_ns only from itself and the names listed.
BOTTOM_FLOORS = {
    "geer_ns.errors": (),
    "geer_ns.compat": (),
    "geer_ns.render": (),
    "geer_ns.cameras": (),
}


def _modules() -> dict[str, Path]:
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__main__":
            continue  # runs the CLI when imported
        if parts[-1] == "__init__":
            parts = parts[:-1]
        found[".".join(parts)] = path
    return found


def _targets(module: str, node: ast.AST, is_package: bool, modules: dict[str, Path]) -> set[str]:
    """The geer_ns modules an import statement loads (the longest known prefix of each name)."""
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
    else:
        base = node.module or ""
        if node.level:
            package = module.split(".") if is_package else module.split(".")[:-1]
            package = package[: len(package) - (node.level - 1)]
            base = ".".join(package + ([base] if base else []))
        names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names]
    out = set()
    for name in names:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        if name and name != module:
            out.add(name)
    return out


def import_graph() -> dict[str, set[str]]:
    """{module: geer_ns modules it imports anywhere in its source}."""
    modules = _modules()
    graph = {}
    for name, path in modules.items():
        edges: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf8"), str(path))):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                edges |= _targets(name, node, path.name == "__init__.py", modules)
        graph[name] = edges
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return cycles


def test_the_cycle_finder_finds_a_planted_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert import_cycles(graph) == [["a", "b", "c"]]
    assert import_cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_circle_in_the_package():
    graph = import_graph()
    assert "geer_ns.render.outputs" in graph and len(graph) > 40
    assert import_cycles(graph) == []


def test_bottom_floors_import_nothing_from_above():
    graph = import_graph()
    for floor, allowed in BOTTOM_FLOORS.items():
        for module, edges in graph.items():
            if module != floor and not module.startswith(floor + "."):
                continue
            above = {e for e in edges if e != floor and not e.startswith(floor + ".") and e not in allowed
                     and e != "geer_ns"}
            assert not above, f"{module} imports {sorted(above)} from above its floor ({floor})"


# Third-party packages preloaded before forking (nerfstudio.engine.trainer and the dataparser configs would
# discover plugins, that is import geer: not preloaded).
_PRELOAD = ("torch", "numpy", "cv2", "PIL.Image", "pycolmap", "plyfile", "tyro", "rich.progress", "torchvision.utils",
            "torchmetrics.image", "pytorch_msssim", "gsplat.strategy", "nerfstudio.cameras.cameras",
            "nerfstudio.utils.rich_utils", "nerfstudio.models.splatfacto",
            "nerfstudio.data.dataparsers.nerfstudio_dataparser")

_FORK_IMPORTS = r"""
import importlib, json, os, sys, traceback
preload, modules = json.loads(sys.argv[1]), json.loads(sys.argv[2])
for name in preload:
    importlib.import_module(name)
loaded = sorted(m for m in sys.modules if m == "geer_ns" or m.startswith("geer_ns."))
if loaded:
    sys.exit(f"preloading imported geer already: {loaded[:5]}")
failures = []
for name in modules:
    pid = os.fork()
    if pid == 0:
        code = 0
        try:
            importlib.import_module(name)
        except BaseException:
            print(f"importing {name} alone:", traceback.format_exc(), file=sys.stderr)
            code = 1
        sys.stderr.flush()
        os._exit(code)
    if os.waitpid(pid, 0)[1] != 0:
        failures.append(name)
print(json.dumps(failures))
"""


def test_every_module_imports_alone_and_in_any_order_in_a_fresh_process():
    names = sorted(_modules())
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    run = dict(stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env)
    forks = subprocess.Popen([sys.executable, "-c", _FORK_IMPORTS, json.dumps(_PRELOAD), json.dumps(names)], **run)
    # Meanwhile one plain interpreter, nothing preloaded, imports the whole package in reverse order.
    code = "import importlib\nfor n in %r: importlib.import_module(n)" % names[::-1]
    plain = subprocess.Popen([sys.executable, "-c", code], **run)
    out, err = forks.communicate(timeout=300)
    assert forks.returncode == 0, err[-4000:]
    assert json.loads(out.strip().splitlines()[-1]) == [], err[-4000:]
    _, plain_err = plain.communicate(timeout=300)
    assert plain.returncode == 0, plain_err[-4000:]
