"""The simulator's two backends, Taichi 1.7.4 and its maintained fork quadrants (``freeform.sim.runtime``).

The two cannot both be initialised in one process, so each backend runs in a subprocess (this file run as a script)
on the same bodies, and the test compares what they return:

* with fast-math off (``FREEFORM_FAST_MATH=0``) they must agree **bit for bit**: the same kernels, the same order of
  operations, IEEE arithmetic (LLVM 15 in Taichi, LLVM 22 in quadrants; neither contracts a·b + c into an FMA on
  this CPU path);
* with fast-math on (both backends' default, what runs in practice) LLVM may reassociate sums and products
  differently in each compiler, so the states differ at rounding level from the first steps; friction's
  stick/slip switches and the strain hysteresis can amplify that over a long run. Over 0.5 s of six design bodies
  the tolerances below hold with a wide margin (measured: see docs/physics-running.md, "Backends").

The backend switch's own rules (the environment variable, a clear error for a second backend or a missing one)
are checked here too, in subprocesses, so that this process never fixes a backend.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

HAS_QUADRANTS = importlib.util.find_spec("quadrants") is not None
needs_quadrants = pytest.mark.skipif(not HAS_QUADRANTS, reason="quadrants is not installed (the `quadrants` extra)")

ROOT = Path(__file__).resolve().parents[1]
# What the two backends must agree on with fast-math on, 0.5 s (4243 steps) of six design bodies, against the largest
# difference measured (docs/physics-running.md, "Backends"): f32 displacement 9.1e-6 voxel lengths (of ~0.4-1.5), centre of
# mass 1.4e-7 m — ~100x margin; f64 displacements equal (f32 outputs), centre of mass 1.2e-16 m (1 ulp) — the
# margin allows the growth of a rounding difference over longer or livelier runs (schedules: 1e-15 after 0.7 s).
ATOL_DISPLACEMENT = {"f32": 1e-3, "f64": 1e-6}  # voxel lengths
ATOL_COM_M = {"f32": 1e-5, "f64": 1e-12}  # metres
# (both precisions and both schedules, each once: a case is a compile of its own, the file's cost)
CASES = (("f32", "robots"), ("f64", "flat"))
# With fast-math the practical case alone (f32, what runs): bit-for-bit agreement on both cases without it already
# says the kernels are the same; what fast-math adds is each compiler's reassociation, which f64 hides (f32 outputs).
FAST_MATH_CASES = CASES[:1]


def _bodies() -> np.ndarray:
    """Six bodies of an untrained design policy (the benchmark's, ``DesignEnv`` at ρ = 20), as uint8 grids."""
    sys.path.insert(0, str(ROOT))
    from benchmarks.bench_sim import random_design_bodies

    return random_design_bodies(6, seed=3).numpy()


def _simulate(out: str, cases: list[str]) -> None:
    """Subprocess: simulate ``cases`` (``precision_schedule``) on this process's backend and save the results to
    ``out`` (npz)."""
    from freeform.sim import SimConfig, Simulator, runtime

    grids = _bodies()
    res: dict[str, np.ndarray] = {}
    for precision, schedule in (case.split("_") for case in cases):
        cfg = SimConfig(precision=precision, burn_in=0.1, duration=0.4)
        r = Simulator(cfg, arch="cpu", schedule=schedule).simulate(grids)
        key = f"{precision}_{schedule}"
        res[f"{key}_displacement"] = r.displacement.numpy()
        res[f"{key}_max_voxel"] = r.max_voxel_displacement.numpy()
        res[f"{key}_com_end"] = r.com_end.numpy()
        res[f"{key}_steps"] = r.steps.numpy()
        res[f"{key}_diverged"] = r.diverged.numpy()
    np.savez(out, backend=runtime.describe(), **res)


def _run(code: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    """Run ``python <code...>`` from the repository root with ``env`` added; it must succeed."""
    p = subprocess.run([sys.executable, *code], env={**os.environ, **env}, cwd=ROOT, capture_output=True,
                       text=True, timeout=600)
    assert p.returncode == 0, f"{code} failed:\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}"
    return p


def _results(tmp_path: Path, backend: str, fast_math: str, cases=CASES) -> dict[str, np.ndarray]:
    out = tmp_path / f"{backend}_{fast_math}.npz"
    _run([__file__, str(out), *(f"{p}_{s}" for p, s in cases)], {"FREEFORM_BACKEND": backend, "FREEFORM_FAST_MATH": fast_math})
    with np.load(out) as z:
        return {k: z[k] for k in z.files}


@needs_quadrants
@pytest.mark.slow
def test_backends_agree_bit_for_bit_without_fast_math(tmp_path):
    a, b = _results(tmp_path, "taichi", "0"), _results(tmp_path, "quadrants", "0")
    assert {k[: -len("_steps")] for k in a if k.endswith("_steps")} == {f"{p}_{s}" for p, s in CASES}
    assert str(a["backend"]).startswith("taichi ") and str(b["backend"]).startswith("quadrants ")
    for key in a:
        if key != "backend":
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


@needs_quadrants
@pytest.mark.slow
def test_backends_agree_within_tolerance_with_fast_math(tmp_path):
    a, b = (_results(tmp_path, backend, "1", FAST_MATH_CASES) for backend in ("taichi", "quadrants"))
    for precision, schedule in FAST_MATH_CASES:
        key = f"{precision}_{schedule}"
        # every robot takes the same steps (fixed protocol, healthy bodies) and none diverges on either backend
        np.testing.assert_array_equal(a[f"{key}_steps"], b[f"{key}_steps"], err_msg=key)
        assert not a[f"{key}_diverged"].any() and not b[f"{key}_diverged"].any(), key
        assert (a[f"{key}_displacement"] > 0.05).all(), "the bodies should move (a comparison of zeros proves nothing)"
        for what in ("displacement", "max_voxel"):
            np.testing.assert_allclose(b[f"{key}_{what}"], a[f"{key}_{what}"], rtol=0,
                                       atol=ATOL_DISPLACEMENT[precision], err_msg=f"{key} {what}")
        np.testing.assert_allclose(b[f"{key}_com_end"], a[f"{key}_com_end"], rtol=0, atol=ATOL_COM_M[precision],
                                   err_msg=f"{key} com_end")


_SWITCH = """
import os, sys
from freeform.sim import SimConfig, Simulator, runtime
import freeform.sim
assert runtime.backend() is None and 'taichi' not in sys.modules and 'quadrants' not in sys.modules, 'import fixed it'
cfg = SimConfig(burn_in=0.0, duration=0.002, backend=sys.argv[1] if sys.argv[1] != '-' else None)
import numpy as np
Simulator(cfg, arch='cpu').simulate(np.ones((1, 2, 1, 1), np.uint8))
print('first', runtime.describe())
other = 'quadrants' if runtime.backend() == 'taichi' else 'taichi'
try:
    Simulator(SimConfig(burn_in=0.0, duration=0.002, backend=other), arch='cpu').simulate(np.ones((1, 2, 1, 1), np.uint8))
except RuntimeError as e:
    print('second', e)
Simulator(SimConfig(burn_in=0.0, duration=0.002), arch='cpu').simulate(np.ones((1, 2, 1, 1), np.uint8))
print('default', runtime.backend())
"""


@needs_quadrants
@pytest.mark.parametrize("backend, env, expect", [("-", {}, "taichi"), ("-", {"FREEFORM_BACKEND": "quadrants"}, "quadrants"),
                                                  ("quadrants", {"FREEFORM_BACKEND": "taichi"}, "quadrants")])
def test_backend_is_chosen_once_per_process(backend, env, expect):
    """SimConfig.backend wins over FREEFORM_BACKEND, which wins over the default (taichi); importing freeform fixes
    nothing; a second backend in the same process is refused naming both; a later Simulator that names none uses the
    one in use."""
    env = {"FREEFORM_BACKEND": "", **env}
    out = _run(["-c", _SWITCH, backend], env).stdout
    assert f"first {expect} " in out
    other = "quadrants" if expect == "taichi" else "taichi"
    assert f"second freeform.sim: backend '{other}' requested, but '{expect}' is already initialised on 'cpu'" in out
    assert "cannot both run in one process" in out
    assert f"default {expect}" in out


def test_missing_backend_names_the_extra():
    """A process asking for quadrants where it is not installed is told which extra to install (simulated by
    hiding the module), and an unknown name is a ValueError naming the choices."""
    hide = ("import sys; sys.modules['quadrants'] = None\n"
            "from freeform.sim import runtime\n"
            "try:\n    runtime.use('quadrants')\nexcept ImportError as e:\n    print('ERR', e)\n"
            "try:\n    runtime.requested('jax')\nexcept ValueError as e:\n    print('VAL', e)\n")
    out = _run(["-c", hide], {}).stdout
    assert "ERR freeform.sim: backend 'quadrants' is not installed" in out
    assert "pip install 'freeform[quadrants]'" in out
    assert "VAL backend must be one of ('taichi', 'quadrants'), got 'jax'" in out


def test_config_validates_backend():
    from freeform.sim import SimConfig

    with pytest.raises(ValueError, match=r"sim\.backend"):
        SimConfig(backend="jax").validate("sim")


def test_provenance_names_the_backend(tmp_path, monkeypatch):
    """run_info.json and the figure footers name the backend and its version; a run from before the switch
    (no sim_backend) ran on Taichi, whose version it records."""
    import json

    import torch

    from experiments import common
    from freeform.config import TrainConfig
    from freeform.train import run_info

    monkeypatch.setenv("FREEFORM_BACKEND", "taichi")
    assert run_info(TrainConfig(), torch.device("cpu"))["sim_backend"].startswith("taichi 1.7.")
    runs = []
    for i, extra in enumerate(({"sim_backend": "quadrants 1.3.3"}, {})):
        run = tmp_path / str(i)
        run.mkdir()
        info = {"freeform": "0.1.0", "torch": "2.13", "taichi": "1.7.4", "device": "cpu", "git_commit": "abc", **extra}
        (run / common.RUN_INFO).write_text(json.dumps(info))
        runs.append(run)
    prov = common.provenance(runs)
    assert prov["sim_backend"] == "quadrants 1.3.3 | taichi 1.7.4"
    assert "sim quadrants 1.3.3 | taichi 1.7.4, device cpu" in common.provenance_caption(prov)


if __name__ == "__main__":
    _simulate(sys.argv[1], sys.argv[2:])
