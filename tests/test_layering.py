"""Layering: import-linter contracts of pyproject.toml, and hardware code free of simulation code.

``drivers/`` and ``sim_backends/`` are mapped into the ``setmem_hil`` namespace by setuptools'
``package-dir``; import-linter (grimp) finds subpackages by walking the package's folder, so the
test lays the three source trees out as one package in a temporary folder and lints that copy
(the same files, not a re-implementation of the rules).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _lint_imports() -> Path | None:
    exe = Path(sys.executable).with_name("lint-imports")
    return exe if exe.exists() else (Path(p) if (p := shutil.which("lint-imports")) else None)


def test_import_linter_contracts_hold(tmp_path):
    exe = _lint_imports()
    if exe is None:
        pytest.skip("import-linter is not installed (pip install -e '.[test]')")
    tree = tmp_path / "src"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(REPO / "setmem_hil", tree / "setmem_hil", ignore=ignore)
    shutil.copytree(REPO / "drivers", tree / "setmem_hil" / "drivers", ignore=ignore)
    shutil.copytree(REPO / "sim_backends", tree / "setmem_hil" / "sim_backends", ignore=ignore)
    shutil.copy(REPO / "pyproject.toml", tree / "pyproject.toml")
    env = dict(os.environ, PYTHONPATH=str(tree))
    run = subprocess.run([str(exe), "--config", "pyproject.toml"], cwd=tree, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "0 broken" in run.stdout and "2 kept" in run.stdout, run.stdout


def test_hardware_code_never_names_simulation_code():
    offenders = [f"{p.relative_to(REPO)}:{n}" for p in sorted((REPO / "drivers").rglob("*")) if p.is_file() and p.suffix in {".py", ".md", ".toml"}
                 for n, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1) if "sim_backends" in line]
    assert offenders == []


def test_nothing_imports_the_tests():
    offenders = []
    for folder in ("setmem_hil", "drivers", "sim_backends", "benchmarks"):
        for p in (REPO / folder).rglob("*.py"):
            for n, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1):
                words = line.split()
                if words[:1] in (["import"], ["from"]) and len(words) > 1 and words[1].split(".")[0] in {"tests", "conftest", "_campaign_helpers"}:
                    offenders.append(f"{p.relative_to(REPO)}:{n}")
    assert offenders == []
