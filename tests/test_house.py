"""The house (issue 46): no import circle, the command list without importing the commands, and
commands that import only what they need (checked by what is imported, never by a clock: the
figures are in ``benchmarks/cli_startup.py``)."""

from __future__ import annotations

import argparse
import ast
import importlib
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SOURCES = {"setmem_hil": REPO / "setmem_hil", "setmem_hil.drivers": REPO / "drivers", "setmem_hil.sim_backends": REPO / "sim_backends"}


def module_files() -> dict[str, Path]:
    modules = {}
    for prefix, root in SOURCES.items():
        for path in root.rglob("*.py"):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join([prefix, *parts])] = path
    return modules


def imports_of(path: Path, modules: dict[str, Path]) -> set[str]:
    """Every project module ``path`` imports, at module level or inside a function."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        for name in names:
            name = name.replace("sim_backends", "setmem_hil.sim_backends", 1) if name.startswith("sim_backends") else name
            name = name.replace("drivers", "setmem_hil.drivers", 1) if name.startswith("drivers") else name
            if name in modules:
                found.add(name)
    return found


def test_no_import_circle_in_the_package():
    # a package's __init__ only hands names on (lazily): it is the package's face, not a room
    modules = {m: p for m, p in module_files().items() if p.name != "__init__.py"}
    graph = {m: imports_of(p, modules) - {m} for m, p in modules.items()}
    index, low, stack, on_stack, circles, counter = {}, {}, [], set(), [], [0]

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
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
                circles.append(sorted(component))

    sys.setrecursionlimit(10000)
    for v in graph:
        if v not in index:
            visit(v)
    assert circles == []


def test_the_command_list_names_every_command_with_its_modules_own_help():
    from setmem_hil.cli.commands import COMMANDS

    folder = REPO / "setmem_hil" / "cli" / "commands"
    assert sorted(m for m, _ in COMMANDS.values()) == sorted(p.stem for p in folder.glob("*.py") if not p.stem.startswith("_"))
    for name, (module, summary) in COMMANDS.items():
        parser = argparse.ArgumentParser()
        subparsers = parser.add_subparsers()
        importlib.import_module(f"setmem_hil.cli.commands.{module}").register(subparsers)
        assert list(subparsers.choices) == [name]
        assert subparsers._choices_actions[0].help == summary, name


def _loaded_after(argv: list[str]) -> set[str]:
    code = ("import sys\nfrom setmem_hil.cli.main import main\n"
            f"try:\n    main({argv!r})\nexcept SystemExit:\n    pass\n"
            "print(' '.join(sorted(sys.modules)), file=sys.stderr)")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    return set(run.stderr.split())


def test_help_and_version_load_no_numerics_and_a_command_loads_only_its_own_module():
    for argv in (["--help"], ["--version"]):
        loaded = _loaded_after(argv)
        assert "numpy" not in loaded and not any(m.startswith("setmem_hil.cli.commands.") for m in loaded), argv
    loaded = _loaded_after(["sweep", "--help"])
    assert "setmem_hil.cli.commands.sweep" in loaded and "setmem_hil.cli.commands.run" not in loaded
    assert "scipy" not in loaded and "dask" not in loaded


def test_run_check_loads_neither_the_loop_nor_the_backends():
    loaded = _loaded_after(["run", "--check", str(REPO / "setmem_hil" / "procedures" / "beam_6_3_2.toml")])
    assert "setmem_hil.campaign.preflight" in loaded  # it did check
    assert not {"setmem_hil.campaign.runner", "setmem_hil.robust.analysis", "setmem_hil.experiment_factory", "control"} & loaded


def _lines_without_docstring(node) -> int:
    first = min([node.lineno, *(d.lineno for d in node.decorator_list)])
    n = node.end_lineno - first + 1
    head = node.body[0] if node.body else None
    if isinstance(head, ast.Expr) and isinstance(head.value, ast.Constant) and isinstance(head.value.value, str):
        n -= head.end_lineno - head.lineno + 1
    return n


def test_no_function_in_the_package_is_longer_than_80_lines_without_its_docstring():
    long = []
    for path in sorted((REPO / "setmem_hil").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and _lines_without_docstring(node) > 80:
                long.append(f"{path.relative_to(REPO)}:{node.name} ({_lines_without_docstring(node)} lines)")
    assert long == []


def test_the_session_module_is_under_200_lines():
    assert len((REPO / "setmem_hil" / "campaign" / "session.py").read_text(encoding="utf-8").splitlines()) < 200
