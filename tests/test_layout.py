"""The layout the architecture promises (docs/architecture.md), checked on the source itself."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PRODUCTION = ("service", "slam", "loops", "graph", "perception", "rl", "sources", "evaluation", "bench")
CORE = ("slam", "loops")
ALLOWED = {  # package -> the packages of ours it may import
    "graph": set(),
    "perception": {"graph"},
    "loops": {"graph", "perception"},
    "rl": {"graph", "perception", "sources"},
    "sources": {"graph", "perception"},
    "evaluation": {"graph", "perception", "sources"},
    "slam": {"graph", "perception", "loops", "rl"},
    "service": set(PRODUCTION) - {"service", "bench"},
    "bench": set(PRODUCTION) - {"bench"},
}
COMMANDS = {"service/cli.py", "rl/commands.py"}  # command-line modules: they also register and print benchmarks


def _modules(packages) -> list[Path]:
    return sorted(p for pkg in packages for p in (ROOT / pkg).rglob("*.py"))


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


def test_no_production_module_is_over_400_lines():
    long = {str(p.relative_to(ROOT)): n for p in _modules(PRODUCTION) if (n := len(p.read_text().splitlines())) > 400}
    assert not long, long


def test_no_function_of_the_slam_core_is_over_60_lines():
    long = []
    for path in _modules(CORE):
        for node in ast.walk(ast.parse(path.read_text())):
            if (
                isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
                and node.end_lineno is not None
                and node.end_lineno - node.lineno + 1 > 60
            ):
                long.append(f"{path.relative_to(ROOT)}:{node.name}")
    assert not long, long


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_dependencies_flow_one_way(package):
    ours = set(PRODUCTION)
    wrong = {
        f"{p.relative_to(ROOT)} imports {name}"
        for p in _modules([package])
        for name in _imports(p) & ours - {package} - ALLOWED[package]
        if not (name == "bench" and str(p.relative_to(ROOT)) in COMMANDS)
    }
    assert not wrong, sorted(wrong)


def test_the_slam_core_imports_without_zenoh_or_threads_of_its_own():
    code = (
        "import sys, threading; before = threading.active_count(); import slam.core, slam.build, slam.snapshot; "
        "assert 'zenoh' not in sys.modules, 'zenoh imported'; assert threading.active_count() == before"
    )
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
