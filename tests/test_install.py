"""freeform as a user installs it, not as the editable checkout runs it.

A wheel built from this checkout (offline, with this environment's setuptools) is installed into a fresh virtual
environment; from a directory outside the checkout its ``freeform-train`` trains one tiny epoch and its
``freeform-render`` draws the run's best body. The Hydra configs must come from the wheel (``freeform/conf``), not
from the checkout's ``conf/``. The fresh environment borrows the dependencies (torch, taichi, hydra ...) of the
environment running the tests through a ``.pth`` path line, so nothing is downloaded; a plain path line does not
run that directory's own ``.pth`` files, so the editable freeform installed there stays invisible.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import numpy as np
import pytest
from helpers import tiny  # tests/helpers.py

REPO = Path(__file__).resolve().parent.parent
SOURCES = ("pyproject.toml", "README.md", "freeform", "conf")
"""What a build of the wheel reads (pyproject.toml: readme, packages, package-dir)."""

TINY = tiny("agent.num_sgd_iter=1", "trainer.epochs=1", "trainer.checkpoint_every=0")


def _run(cmd: list[str | Path], cwd: Path | None = None) -> str:
    """Run ``cmd`` (no PYTHONPATH: only what is installed counts); its stdout, or a failure showing its output."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.update(PIP_DISABLE_PIP_VERSION_CHECK="1", PIP_NO_INPUT="1", OMP_NUM_THREADS="1")
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    if proc.returncode:
        pytest.fail(f"{' '.join(map(str, cmd))} exited with {proc.returncode}\n--- stdout\n{proc.stdout[-4000:]}"
                    f"\n--- stderr\n{proc.stderr[-4000:]}")
    return proc.stdout


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """``(wheel, source copy)``: the wheel is built from a copy of the checkout, because a build in the checkout
    leaves ``build/`` behind, whose stale files would go into later wheels (and it races other builds)."""
    root = tmp_path_factory.mktemp("wheel")
    src = root / "src"
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            src.mkdir(exist_ok=True)
            shutil.copy2(REPO / name, src / name)
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
          "--wheel-dir", root / "dist", src])
    (wheel,) = (root / "dist").glob("freeform-*.whl")
    return wheel, src


@pytest.fixture(scope="module")
def venv(built: tuple[Path, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh virtual environment with the wheel installed and this environment's packages visible after its own."""
    root = tmp_path_factory.mktemp("venv") / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", root])
    python = root / "bin" / "python"
    site = Path(_run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"]).strip())
    borrowed = dict.fromkeys(sysconfig.get_path(key) for key in ("purelib", "platlib"))  # ordered, no duplicates
    (site / "_freeform_test_deps.pth").write_text("".join(f"{path}\n" for path in borrowed))
    # This environment's pip installs into the fresh one (--python, pip >= 22.3): no ensurepip, no download.
    _run([sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--no-index", built[0]])
    return root


def test_wheel_holds_every_module_and_config(built: tuple[Path, Path]) -> None:
    wheel, src = built
    names = set(zipfile.ZipFile(wheel).namelist())
    modules = {p.relative_to(src).as_posix() for p in (src / "freeform").rglob("*.py")}
    configs = {"freeform/conf/" + p.relative_to(src / "conf").as_posix() for p in (src / "conf").rglob("*.yaml")}
    missing = sorted(modules - names)
    assert not missing, f"{missing} not in the wheel: add their package to [tool.setuptools] packages (pyproject.toml)"
    missing = sorted(configs - names)
    assert not missing, f"{missing} not in the wheel: conf/ must ship as freeform/conf (pyproject.toml package-dir)"
    from freeform import zoo

    shipped = {f"freeform/zoo/{name}/{part}" for name in zoo.names() for part in (zoo.CONTROLLER_FILE, zoo.CARD)}
    missing = sorted(shipped - names)
    assert not missing, f"{missing} not in the wheel: the zoo ships as package data (pyproject.toml package-data)"


@pytest.mark.slow
def test_installed_apps_train_and_render_outside_the_checkout(venv: Path, tmp_path: Path) -> None:
    python, bin_dir = venv / "bin" / "python", venv / "bin"
    site = Path(_run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"]).strip()).resolve()
    where = _run([python, "-c", "import freeform, freeform._conf_dir as c; print(freeform.__file__); print(c.conf_dir())"],
                 cwd=tmp_path).split()
    assert [Path(p).resolve() for p in where] == [site / "freeform" / "__init__.py", site / "freeform" / "conf"]

    run = tmp_path / "run"
    _run([bin_dir / "freeform-train", *TINY, f"hydra.run.dir={run}"], cwd=tmp_path)
    assert (run / "checkpoints" / "last.pt").is_file()
    assert list(run.glob("events.out.tfevents.*")), sorted(p.name for p in run.iterdir())
    assert (run / "records" / "epoch_000000.npz").is_file()
    # Hydra composed the wheel's configs, not the checkout's conf/.
    sources = (run / ".hydra" / "hydra.yaml").read_text()
    assert str(site / "freeform" / "conf") in sources and str(REPO / "conf") not in sources

    printed = _run([bin_dir / "freeform-render", run, "--size", "64"], cwd=tmp_path).splitlines()
    images = [Path(line) for line in printed if line.endswith(".png")]  # Taichi may print its banner first
    assert len(images) == 1, printed
    image = images[0]
    assert image.parent == run / "renders" / "epoch_000000"
    assert image.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # A controller for a body of one's own, from the zoo in the wheel (a student and the library's last member:
    # every member's file is checked above): fit by trials, then watched.
    body = np.zeros((4, 4, 4), np.uint8)
    body[0:3, 0:2, 0] = [[2, 2], [1, 1], [3, 3]]
    np.save(tmp_path / "my_body.npy", body)
    from freeform import zoo

    _run([bin_dir / "freeform-control", "fit", "my_body.npy", "--out", "fitted", "--adapt-epochs", "0",
          "--candidates", zoo.STUDENTS[0], zoo.LIBRARY[-1]], cwd=tmp_path)
    fitted = (tmp_path / "fitted" / "bodies.csv").read_text().splitlines()
    assert len(fitted) == 2 and fitted[0].startswith("body,chosen,mean_command,controller_file,seconds")
    assert fitted[0].endswith(f"trial_{zoo.STUDENTS[0]},trial_{zoo.LIBRARY[-1]}")
    _run([bin_dir / "freeform-control", "watch", "fitted/body0/controller.pt", "my_body.npy", "--out", "seen"],
         cwd=tmp_path)
    seen = json.loads((tmp_path / "seen" / "gait.json").read_text())
    assert seen["controller"].startswith(str(tmp_path)) and (tmp_path / "seen" / "gait.gif").is_file()
    assert seen["displacement"] == float(fitted[1].split(",")[2])

    # The dry run composes the same configs (freeform.launch), still from outside the checkout.
    report = _run([bin_dir / "freeform-train", "trainer.dry_run=true", *TINY], cwd=tmp_path)
    assert "job 0:" in report and "launch: freeform-train" in report
