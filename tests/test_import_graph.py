"""The module import graph: no import cycles between shiftkit's modules (read with grimp, the graph
library import-linter uses), and the dependency contracts (pyproject's [tool.importlinter], run by
`scripts/lint-imports.sh`) break when a module, existing or new, imports upwards or sideways (the
engine and the trainers are independent of each other)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("datasets", "pipelines", "transforms", "policies", "envs", "cards", "app")


# The strongly connected components (Tarjan) of grimp's graph of direct imports, module level and
# function level alike: each one with more than one module is an import cycle.
CYCLES = """
import json, sys
import grimp
graph = grimp.build_graph("shiftkit")
index, low, stack, on, cycles = {}, {}, [], set(), []
sys.setrecursionlimit(100000)
def visit(v):
    index[v] = low[v] = len(index); stack.append(v); on.add(v)
    for w in graph.find_modules_directly_imported_by(v):
        if w not in index:
            visit(w); low[v] = min(low[v], low[w])
        elif w in on:
            low[v] = min(low[v], index[w])
    if low[v] == index[v]:
        component = []
        while not component or component[-1] != v:
            component.append(stack.pop()); on.discard(component[-1])
        if len(component) > 1:
            cycles.append(sorted(component))
for module in sorted(graph.modules):
    if module not in index:
        visit(module)
print(json.dumps(sorted(cycles)))
"""


def installed_layout(src: Path, dest: Path) -> Path:
    """`src`'s top-level packages laid out as the installed `shiftkit` package (sources only): the
    package-dir mapping hides them from a file walker, as in scripts/lint-imports.sh."""
    (dest / "shiftkit").mkdir(parents=True)
    (dest / "shiftkit" / "__init__.py").touch()
    for package in PACKAGES:
        shutil.copytree(src / package, dest / "shiftkit" / package, ignore=shutil.ignore_patterns("__pycache__"))
    return dest


def test_no_import_cycles(tmp_path):
    tree = installed_layout(ROOT, tmp_path / "tree")
    proc = subprocess.run(
        [sys.executable, "-c", CYCLES], env={"PYTHONPATH": str(tree)}, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    cycles = json.loads(proc.stdout)
    assert cycles == []


def _repo_copy(dest: Path) -> Path:
    for package in PACKAGES:
        shutil.copytree(ROOT / package, dest / package, ignore=shutil.ignore_patterns("__pycache__"))
    (dest / "scripts").mkdir()
    shutil.copy2(ROOT / "scripts" / "lint-imports.sh", dest / "scripts" / "lint-imports.sh")
    shutil.copy2(ROOT / "pyproject.toml", dest / "pyproject.toml")
    return dest


WRONG_WAYS = {
    # a dataset-layer module importing the engine above it
    "existing dataset module": ("datasets/jsonutil.py", "shiftkit.pipelines.runner"),
    # a new engine module importing a trainer beside it
    "new engine module": ("pipelines/fresh_engine_module.py", "shiftkit.policies.fire"),
    # a trainer module importing the engine beside it
    "existing policy module": ("policies/replay.py", "shiftkit.pipelines.runner"),
}


@pytest.mark.parametrize("mutation", ["none", *WRONG_WAYS])
def test_a_wrong_way_import_breaks_the_contracts(tmp_path, mutation):
    repo = _repo_copy(tmp_path / "repo")
    if mutation != "none":
        path, target = WRONG_WAYS[mutation]
        with open(repo / path, "a") as f:
            f.write(
                ('"""A module added later."""' if not (repo / path).exists() else "") + f"\nimport {target}  # noqa\n"
            )
    proc = subprocess.run(
        ["bash", str(repo / "scripts" / "lint-imports.sh"), sys.prefix], capture_output=True, text=True, timeout=300
    )
    if mutation == "none":
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    else:
        path, target = WRONG_WAYS[mutation]
        module = "shiftkit." + path.removesuffix(".py").replace("/", ".")
        assert proc.returncode != 0
        assert "layers: applications (CLI, collect, demo) > stages > policies | pipeline engine" in proc.stdout
        assert "> datasets > envs | cards BROKEN" in proc.stdout
        assert f"{module} -> {target}" in proc.stdout, proc.stdout[-3000:]
