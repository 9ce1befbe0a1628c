"""The architecture as a test: imports point clients -> service -> schemas, no cycles, and the pure layers
(service/core, service/plant and the pure drivers' computations) touch no clock, thread, socket, process,
environment, ctypes, zenoh or mcap.

The checker reads source with ``ast`` (nothing is imported or run), so it also sees imports inside functions.
Each rule is shown to fail on a planted violation in a temporary tree.
"""

from __future__ import annotations

import ast
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("schemas", "service", "clients")

# which of our packages each may import (a prefix match on the dotted module name)
ALLOWED = {
    "schemas": ("schemas",),
    "service": ("schemas", "service"),
    "clients": ("schemas", "service", "clients"),
}
# inside service: each layer and what it may import of service (schemas is always allowed there)
SERVICE_LAYERS = {
    "service.core": ("service.core", "service._kernel"),
    "service.plant": ("service.core.types", "service.plant", "service._kernel"),
    "service.forecast": ("service.core", "service.plant"),
    # the run metrics (settle, band, sharing ...) every driver, stand-in, report and bench reads: over the core's
    # mode names only
    "service.metrics": ("service.core.source",),
    "service.sim": ("service.core", "service.plant", "service.forecast", "service.metrics"),
    # the network wing: the pure layer, the offline network, the rig's model; its replay reads a log besides
    "service.network.layer_replay": ("service.network.layer", "service.logio", "service.plant"),
    "service.network": ("service.core", "service.plant", "service.forecast", "service.sim", "service.metrics",
                        "service.network"),
    "service.priority": (),
    # the recorder and reader: what a log holds (the core's records), the recorder process's priority
    "service.logio": ("service.logio", "service.core", "service.priority"),
    "service.replay": ("service.core", "service.logio"),
    # the runtime services (daemon, coordinator): the pure parts they drive, the logs, the process's priority; never
    # the offline drivers (service.sim, service.replay)
    "service.daemon": ("service.daemon", "service.core", "service.forecast", "service.logio", "service.network",
                       "service.plant", "service.priority", "service._kernel"),
}
PURE = ("service.core", "service.plant", "service.forecast", "service.metrics", "service.sim", "service.network")
IMPURE_MODULES = ("time", "datetime", "threading", "_thread", "concurrent", "asyncio", "socket", "ssl", "selectors",
                  "subprocess", "multiprocessing", "signal", "os", "ctypes", "zenoh", "mcap", "random", "secrets")


def _module_name(root: Path, path: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(root: Path, path: Path) -> list[tuple[int, str]]:
    """(line, absolute dotted module) of every import in the file, relative ones resolved."""
    name = _module_name(root, path)
    pkg = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")
                base = base[:len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            # "from service.core import control" names a module; "from x import name" names x
            out += [(node.lineno, f"{mod}.{a.name}") if (root / (mod.replace(".", "/")) / f"{a.name}.py").exists()
                    or (root / mod.replace(".", "/") / a.name / "__init__.py").exists() else (node.lineno, mod)
                    for a in node.names]
    return out


def _within(mod: str, prefixes) -> bool:
    return any(mod == p or mod.startswith(p + ".") for p in prefixes)


def _ours(mod: str) -> bool:
    return mod.split(".")[0] in PACKAGES


def violations(root: Path) -> list[str]:
    """Every broken rule in the tree at root, as 'file:line: what'."""
    out: list[str] = []
    graph: dict[str, set[str]] = {}
    files = sorted(p for pkg in PACKAGES if (root / pkg).is_dir() for p in (root / pkg).rglob("*.py"))
    modules = {_module_name(root, p) for p in files}
    for path in files:
        name = _module_name(root, path)
        rel = path.relative_to(root)
        top = name.split(".")[0]
        layer = next((lay for lay in SERVICE_LAYERS if _within(name, (lay,))), None)
        for line, mod in _imports(root, path):
            where = f"{rel}:{line}"
            if _ours(mod):
                if not _within(mod, ALLOWED[top]):
                    out.append(f"{where}: {top}/ imports {mod} (imports point clients -> service -> schemas)")
                elif top == "service" and not _within(mod, ("schemas",)):
                    if layer is None:
                        if name != "service":
                            out.append(f"{where}: {name} is in no service layer (add it to SERVICE_LAYERS)")
                    elif not _within(mod, SERVICE_LAYERS[layer]) and mod != "service":
                        out.append(f"{where}: {layer} imports {mod}, outside its layer's reach")
                target = mod
                while target and target not in modules:
                    target = target.rpartition(".")[0]
                if target and target != name:
                    graph.setdefault(name, set()).add(target)
            elif _within(name, PURE) and _within(mod, IMPURE_MODULES):
                out.append(f"{where}: pure {name} imports {mod} (no clock, thread, socket, process, environment, "
                           "ctypes, zenoh or mcap)")
    out += [f"import cycle: {' -> '.join(c)}" for c in _cycles(graph)]
    return out


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle per strongly connected component of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
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
                found.append(sorted(comp) + [sorted(comp)[0]])

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_tree_keeps_its_layers():
    assert violations(ROOT) == []


def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(textwrap.dedent(text))
    for pkg in ("schemas", "service", "clients", "service/core", "service/plant", "service/daemon"):
        init = tmp_path / pkg / "__init__.py"
        init.parent.mkdir(parents=True, exist_ok=True)
        init.touch()
    return tmp_path


@pytest.mark.parametrize(("files", "expected"), [
    ({"service/daemon/x.py": "from clients import cli\n"}, "service/ imports clients"),
    ({"schemas/m.py": "import service.core\n"}, "schemas/ imports service.core"),
    ({"service/core/law.py": "import time\n"}, "pure service.core.law imports time"),
    ({"service/plant/p.py": "def f():\n    import os\n    return os.environ\n"}, "pure service.plant.p imports os"),
    ({"service/core/law.py": "import zenoh\n"}, "pure service.core.law imports zenoh"),
    ({"service/core/law.py": "from service.daemon import bus\n"}, "service.core imports service.daemon"),
    ({"service/logio/w.py": "from service.daemon import bus\n"}, "service.logio imports service.daemon"),
    ({"service/daemon/d.py": "from service import sim\n", "service/sim.py": ""}, "service.daemon imports service.sim"),
    ({"service/network/layer.py": "from service.daemon import bus\n"}, "service.network imports service.daemon"),
    ({"service/network/layer.py": "import zenoh\n"}, "pure service.network.layer imports zenoh"),
    ({"service/core/a.py": "from . import b\n", "service/core/b.py": "from service.core import a\n"},
     "import cycle: service.core.a -> service.core.b -> service.core.a"),
])
def test_a_planted_violation_is_found(tmp_path, files, expected):
    found = violations(_tree(tmp_path, files))
    assert any(expected in v for v in found), found


def test_a_clean_planted_tree_passes(tmp_path):
    """The checker accepts what the rules allow (so the failures above are the rules, not noise)."""
    tree = _tree(tmp_path, {"service/core/law.py": "import math\nfrom schemas import m\n", "schemas/m.py": "",
                            "clients/c.py": "from service.core import law\nimport time\n",
                            "service/daemon/d.py": "import threading\nfrom service.core import law\n"})
    assert violations(tree) == []
