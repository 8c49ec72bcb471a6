"""The layering of docs/architecture.md, checked on the source: which layer may import which, no import circles,
and a CLI that other packages extend through entry points."""
from __future__ import annotations

import ast
import functools
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tests.conftest import REPO

PACKAGES = ("gbuffer_export", "training", "blender_addon")


def layer_of(module: str) -> str:
    """core (numpy), bpy (gbuffer_export.blender), commands (the CLI), torch (training), torch-commands
    (training.commands: the torch layer's commands and generators), addon."""
    if module.startswith("gbuffer_export.blender"):
        return "bpy"
    if module.startswith("gbuffer_export.commands") or module == "gbuffer_export.cli":
        return "commands"
    if module.startswith("gbuffer_export"):
        return "core"
    if module.startswith("training.commands"):
        return "torch-commands"
    if module.startswith("training"):
        return "torch"
    return "addon"


#: layer -> the project layers and third-party top-level packages it must never import (at any depth of the code,
#: function-local imports included).
FORBIDDEN = {
    "core": ({"bpy", "torch", "commands", "torch-commands", "addon"}, {"bpy", "bmesh", "mathutils", "torch", "training"}),
    "bpy": ({"torch", "commands", "torch-commands", "addon"}, {"torch", "training"}),
    "commands": ({"torch", "torch-commands", "addon"}, {"torch", "training"}),
    "torch": ({"bpy", "commands", "torch-commands", "addon"}, {"bpy", "bmesh", "mathutils"}),
    "torch-commands": ({"bpy", "addon"}, {"bpy", "bmesh", "mathutils"}),
    "addon": (set(), set()),
}


def modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for p in (REPO / pkg).rglob("*.py"):
            parts = p.relative_to(REPO).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = p
    return out


@functools.lru_cache(maxsize=None)
def nodes(path: Path) -> tuple[ast.AST, ...]:
    """Every node of the module at ``path`` (``ast.walk`` order), parsed once for all the tests of this file."""
    return tuple(ast.walk(ast.parse(path.read_text())))


def imports(name: str, path: Path, known: dict[str, Path]) -> set[tuple[str, int]]:
    """(imported module, line) of every import statement: project modules resolved to the deepest known module,
    third-party ones to their top-level package."""
    pkg = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()

    def add(target: str, line: int) -> None:
        t = target
        while t and t not in known:
            t = t.rpartition(".")[0]
        out.add((t or target.split(".")[0], line))

    for node in nodes(path):
        if isinstance(node, ast.Import):
            for a in node.names:
                add(a.name, node.lineno)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")[:len(pkg.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            for a in node.names:
                full = f"{mod}.{a.name}"
                add(full if full in known else mod, node.lineno)
    out.discard((name, 0))
    return {(t, ln) for t, ln in out if t != name}


def test_no_module_imports_a_layer_above_its_own():
    known = modules()
    bad = []
    for name, path in known.items():
        layers, packages = FORBIDDEN[layer_of(name)]
        for target, line in imports(name, path, known):
            if target in known and layer_of(target) in layers:
                bad.append(f"{path.relative_to(REPO)}:{line} ({layer_of(name)}) imports {target} ({layer_of(target)})")
            elif target not in known and target.split(".")[0] in packages:
                bad.append(f"{path.relative_to(REPO)}:{line} ({layer_of(name)}) imports {target}")
    assert not bad, "layering violations (docs/architecture.md):\n" + "\n".join(sorted(bad))


def test_no_import_circles():
    known = modules()
    graph = {n: {t for t, _ in imports(n, p, known) if t in known and t != n} for n, p in known.items()}
    # a package's __init__ importing its own submodules is not a circle
    for n in graph:
        graph[n] = {t for t in graph[n] if not (t.startswith(n + ".") or n.startswith(t + ".") and
                                                 known[t].name == "__init__.py")}
    index, low, stack, on, cycles = {}, {}, [], set(), []
    counter = [0]
    sys.setrecursionlimit(10000)

    def strong(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                strong(w)
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
            strong(v)
    assert not cycles, f"import circles: {cycles}"


def test_help_lists_every_command_from_the_entry_points():
    from importlib import metadata
    names = {ep.name for ep in metadata.entry_points(group="blendsr.commands")}
    if not names:
        pytest.skip("blendsr's metadata is not installed (pip install -e .)")
    proc = subprocess.run([sys.executable, "-m", "gbuffer_export.cli", "--help"], capture_output=True, text=True,
                          cwd=REPO, timeout=60)
    assert proc.returncode == 0
    for cmd in ("render", "dataset", "validate", "lut", "bench", "demo", "train", "evaluate", "upscale", "export"):
        assert f"\n    {cmd} " in proc.stdout, cmd


def test_a_package_adds_a_command_without_touching_the_core(tmp_path):
    """A distribution on sys.path with an entry in 'blendsr.commands' appears in 'blendsr --help' and runs."""
    (tmp_path / "hello_cmd.py").write_text(textwrap.dedent('''
        def register(sub):
            p = sub.add_parser("hello", help="say hello (a plug-in command)")
            p.add_argument("--name", default="world")
            p.set_defaults(func=lambda args: print(f"hello {args.name}") or 0)
    '''))
    dist = tmp_path / "hello_cmd-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: hello-cmd\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[blendsr.commands]\nhello = hello_cmd\n")
    import os
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(REPO)]))
    proc = subprocess.run([sys.executable, "-m", "gbuffer_export.cli", "--help"], capture_output=True, text=True,
                          cwd=REPO, env=env, timeout=60)
    assert "say hello (a plug-in command)" in proc.stdout
    proc = subprocess.run([sys.executable, "-m", "gbuffer_export.cli", "hello", "--name", "BlendSR"],
                          capture_output=True, text=True, cwd=REPO, env=env, timeout=60)
    assert proc.returncode == 0 and proc.stdout.strip() == "hello BlendSR"


def _package_graph(pkg: str, known: dict[str, Path]) -> dict[str, set[str]]:
    """Inside package ``pkg``: its own modules one node each, each direct subpackage one node (``name/``); an edge
    for every import between two nodes."""
    def node(mod: str) -> str:
        head = pkg + "." + mod[len(pkg) + 1:].split(".")[0]
        return head + "/" if head in known and known[head].name == "__init__.py" else mod
    graph: dict[str, set[str]] = {}
    for name, path in known.items():
        if not name.startswith(pkg + "."):
            continue
        a = node(name)
        for target, _ in imports(name, path, known):
            if target.startswith(pkg + ".") and target in known and node(target) != a:
                graph.setdefault(a, set()).add(node(target))
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a list of nodes, or None."""
    state: dict[str, int] = {}
    path: list[str] = []

    def visit(v):
        state[v] = 1
        path.append(v)
        for w in sorted(graph.get(v, ())):
            if state.get(w) == 1:
                return path[path.index(w):] + [w]
            if w not in state and (found := visit(w)):
                return found
        state[v] = 2
        path.pop()
        return None

    for v in sorted(graph):
        if v not in state and (found := visit(v)):
            return found
    return None


def test_no_module_imports_one_above_it_in_its_package():
    """Inside every package the subpackages and modules form layers: a module never imports one that (through
    others) imports it back, counting a subpackage as one node (models/ must not import the training configuration
    that imports the models; the kernels must not import the models that call them)."""
    known = modules()
    bad = []
    for pkg in sorted(n for n, p in known.items() if p.name == "__init__.py"):
        cycle = _cycle(_package_graph(pkg, known))
        if cycle:
            bad.append(f"{pkg}: " + " -> ".join(cycle))
    assert not bad, "imports that go up inside a package:\n" + "\n".join(bad)


#: Library modules that parse arguments because they are the entry points of child processes the library itself
#: starts (their arguments are written by the library, not typed by a user).
CHILD_ENTRY_POINTS = {"gbuffer_export.blender.dataset_job", "gbuffer_export.blender.import_job",
                      "gbuffer_export.blender.furnace"}


def test_only_commands_parse_arguments():
    """An argument parser is built only in the command rooms (``gbuffer_export/commands``, ``training/commands``),
    the CLI's entry and the add-on's scripts; a library module that needs a command line has its command there."""
    bad = []
    for name, path in modules().items():
        if layer_of(name) in ("commands", "torch-commands", "addon") or name in CHILD_ENTRY_POINTS:
            continue
        for node in nodes(path):
            if isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) in (
                    "ArgumentParser", "parse_args", "parse_known_args"):
                bad.append(f"{path.relative_to(REPO)}:{node.lineno}")
    assert not bad, "argument parsing outside the commands: " + ", ".join(bad)


def test_the_rooms_of_training():
    """training/ keeps at most 25 modules at its root; the commands and inference have rooms of their own."""
    root = [p for p in (REPO / "training").glob("*.py") if p.name != "__init__.py"]
    assert len(root) <= 25, f"{len(root)} modules at training/'s root: {sorted(p.name for p in root)}"
    for room in ("commands", "inference", "models", "kernels"):
        assert (REPO / "training" / room / "__init__.py").is_file()
