"""Every benchmark and probe imports: ``make bench`` and the GPU check (``scripts/gpu_check.sh``) run them where a
broken import costs a lent device's minutes (``benchmarks.bench_update`` once imported a name ``bench_gpu`` no longer
had, found only by reading)."""

from __future__ import annotations

import ast
import importlib
import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("benchmarks", "experiments", "freeform")
MODULES = sorted(p.stem for p in (ROOT / "benchmarks").glob("*.py") if p.stem not in ("__init__", "__main__"))


def test_there_are_benchmarks_to_import() -> None:
    assert len(MODULES) >= 18  # (an empty glob would skip the parametrised test instead of failing it)


@pytest.mark.parametrize("name", MODULES)
def test_benchmark_module_imports(name: str) -> None:
    importlib.import_module(f"benchmarks.{name}")


def _defines(module: str, name: str) -> bool:
    """Whether ``from module import name`` finds ``name``: an attribute, or a submodule not yet imported."""
    return hasattr(importlib.import_module(module), name) or importlib.util.find_spec(f"{module}.{name}") is not None


def test_every_project_import_in_benchmarks_and_scripts_names_what_exists() -> None:
    """Imports inside functions too (they run only when a benchmark or a lent device's step reaches them), and the
    scripts', which run top to bottom on import."""
    checked = []
    for path in sorted([*(ROOT / "benchmarks").glob("*.py"), *(ROOT / "scripts").glob("*.py")]):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module.split(".")[0] in PACKAGES:
                missing = [a.name for a in node.names if not _defines(node.module, a.name)]
                assert not missing, f"{path.name}:{node.lineno} imports {missing} from {node.module}, which has none"
                checked += node.names
    assert len(checked) >= 50


def test_the_gpu_checks_control_section_runs_its_rehearsal(capsys) -> None:
    """``bench_gpu``'s closed-loop control section at the rehearsal's sizes (8 and 16 bodies): it calls the control
    benchmark's helpers, whose signatures changed once without it (issue 57's split), found by the rehearsal only."""
    from benchmarks.bench_gpu import control_section

    control_section("cpu", "cpu", rehearsal=True)
    out = capsys.readouterr().out
    assert "8 bodies: control steps/s" in out and "16 bodies: engine ms a period" in out
