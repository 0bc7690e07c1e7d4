"""Every benchmark and probe imports: ``make bench`` and the GPU check (``scripts/gpu_check.sh``) run them where a
broken import costs a lent device's minutes (``benchmarks.bench_update`` once imported a name ``bench_gpu`` no longer
had, found only by reading)."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("benchmarks", "experiments", "freeform")
MODULES = sorted(p.stem for p in (ROOT / "benchmarks").glob("*.py") if p.stem not in ("__init__", "__main__"))


@pytest.mark.parametrize("name", MODULES)
def test_benchmark_module_imports(name: str) -> None:
    importlib.import_module(f"benchmarks.{name}")


def test_scripts_import_only_names_their_modules_define() -> None:
    """The scripts run top to bottom on import, so their ``from <package> import`` lines (this project's packages) are checked by name."""
    for script in sorted((ROOT / "scripts").glob("*.py")):
        for node in ast.walk(ast.parse(script.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] in PACKAGES:
                module = importlib.import_module(node.module)
                missing = [a.name for a in node.names if not hasattr(module, a.name)]
                assert not missing, f"{script.name} imports {missing} from {node.module}, which has no such name"
