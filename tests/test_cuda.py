"""The simulator on a GPU, against the CPU: what ``scripts/gpu_check.sh`` runs on a lent CUDA machine.

Marked ``cuda`` and left out of the default suite (``pyproject.toml``: ``-m "not cuda"``). ``pytest -m cuda`` runs
them on ``FREEFORM_CHECK_ARCH`` (default ``cuda``); ``FREEFORM_CHECK_ARCH=cpu`` is the rehearsal on a CPU machine
(the flat schedule on the CPU against the robots schedule: the same comparisons, smaller batches).

* the device's flat schedule against the CPU's robots schedule (its own process: one arch per process), fixed bodies,
  f32 and f64, both semantics, within the tolerances below: measured on an H100 (``gpu-measured.md``) for 0.5 s
  of 16 design bodies and two cubes — f64 < 1e-5 voxel, COM 1.3e-12 m; f32 ≤ 0.002 voxel, COM ≤ 1.1e-5 m — with
  room for the bodies and the shorter run here;
* the robots schedule as a thread block per robot (issue 44) against the CPU, and run twice: the same bits;
* a planted NaN diverges its robot only; a compute graph equals launches from Python bit for bit on the device;
  many ``simulate`` calls of random batch sizes in one process.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.cuda

ARCH = os.environ.get("FREEFORM_CHECK_ARCH", "cuda")
ROOT = Path(__file__).resolve().parents[1]
CASES = [(p, s) for p in ("f32", "f64") for s in ("voxelyze", "rl4design")]
ATOL_VOXELS = {"f32": 5e-3, "f64": 1e-4}  # displacement, voxel lengths
ATOL_COM_M = {"f32": 5e-5, "f64": 1e-10}


def _bodies() -> np.ndarray:
    """Eight design bodies of an untrained policy (ρ = 20) and two muscle cubes (10³ and 6³), uint8 ``[10, 20³]``."""
    sys.path.insert(0, str(ROOT))
    from benchmarks.bench_sim import random_design_bodies

    grids = np.zeros((10, 20, 20, 20), np.uint8)
    grids[:8] = random_design_bodies(8, seed=5).numpy()
    grids[8, :10, :10, :10], grids[9, :6, :6, :6] = 2, 3
    return grids


def _simulate(arch: str, schedule: str, precision: str, semantics: str):
    from freeform.sim import SimConfig, Simulator

    cfg = SimConfig(precision=precision, semantics=semantics, burn_in=0.1, duration=0.2)
    return Simulator(cfg, arch=arch, schedule=schedule).simulate(_bodies())


def _reference(out: str) -> None:
    """Subprocess: the CPU robots schedule on every case, saved to ``out``."""
    res = {}
    for precision, semantics in CASES:
        r = _simulate("cpu", "robots", precision, semantics)
        res[f"{precision}_{semantics}_displacement"] = r.displacement.numpy()
        res[f"{precision}_{semantics}_com_end"] = r.com_end.numpy()
    np.savez(out, **res)


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> dict[str, np.ndarray]:
    out = tmp_path_factory.mktemp("cpu") / "reference.npz"
    p = subprocess.run([sys.executable, __file__, str(out)], cwd=ROOT, capture_output=True, text=True, timeout=900,
                       env={**os.environ, "CUDA_VISIBLE_DEVICES": ""})
    assert p.returncode == 0, p.stderr[-3000:]
    with np.load(out) as data:
        return {k: data[k] for k in data.files}


@pytest.mark.parametrize("precision, semantics", CASES)
def test_device_matches_the_cpu(reference: dict[str, np.ndarray], precision: str, semantics: str) -> None:
    r = _simulate(ARCH, "flat", precision, semantics)
    assert not r.diverged.any() and not r.stalled.any()
    d, com = reference[f"{precision}_{semantics}_displacement"], reference[f"{precision}_{semantics}_com_end"]
    gap_d, gap_c = np.abs(r.displacement.numpy() - d).max(), np.abs(r.com_end.numpy() - com).max()
    print(f"{ARCH} vs cpu, {precision} {semantics}: displacement {gap_d:.2e} voxel, COM {gap_c:.2e} m")
    assert gap_d <= ATOL_VOXELS[precision] and gap_c <= ATOL_COM_M[precision]
    assert np.abs(d).max() > 0.05  # the bodies moved: the comparison is not of resting ones


@pytest.mark.parametrize("precision, semantics", [("f64", "voxelyze"), ("f32", "rl4design")])
def test_block_schedule_matches_the_cpu_and_repeats(reference: dict[str, np.ndarray], precision: str, semantics: str,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """schedule="robots" on the device: a thread block per robot (issue 44; B chosen per batch, the 10³
    cube's 2,700 links give B = 512), within the flat schedule's tolerances of the CPU, and a second run the same
    bits (no float atomics: the block's reductions are serial on lane 0). On the CPU rehearsal: the CPU's own
    robots schedule."""
    monkeypatch.setenv("FREEFORM_CUDA_ROBOTS", "1")
    runs = [_simulate(ARCH, "robots", precision, semantics) for _ in range(2)]
    r = runs[0]
    assert not r.diverged.any() and not r.stalled.any()
    d, com = reference[f"{precision}_{semantics}_displacement"], reference[f"{precision}_{semantics}_com_end"]
    gap_d, gap_c = np.abs(r.displacement.numpy() - d).max(), np.abs(r.com_end.numpy() - com).max()
    print(f"{ARCH} block vs cpu, {precision} {semantics}: displacement {gap_d:.2e} voxel, COM {gap_c:.2e} m")
    assert gap_d <= ATOL_VOXELS[precision] and gap_c <= ATOL_COM_M[precision]
    assert torch.equal(runs[0].com_end, runs[1].com_end) and torch.equal(runs[0].steps, runs[1].steps)


def test_planted_nan_diverges_its_robot_only() -> None:
    from freeform.sim import SimConfig, Simulator
    from freeform.sim.state import DIVERGED, RUNNING

    grids = _bodies()[:4]
    sim = Simulator(SimConfig(precision="f32", burn_in=0.05, duration=0.05), arch=ARCH, schedule="flat")
    clean = sim.engine(sim.layout(grids))
    clean.advance(200)
    clean_positions = clean.positions()  # (the next engine reuses this one's device arrays)
    layout = sim.layout(grids)
    layout.velocity[0, 0] = np.nan  # a voxel of robot 0
    planted = sim.engine(layout)
    planted.advance(200)
    status = planted.robot_status()
    assert status[0] == DIVERGED and (status[1:] == RUNNING).all()
    others = layout.voxel_robot != 0
    np.testing.assert_array_equal(planted.positions()[others], clean_positions[others])


def test_compute_graph_equals_launches_from_python_on_the_device() -> None:
    from freeform.sim import SimConfig, Simulator

    runs = [Simulator(SimConfig(precision="f32", burn_in=0.05, duration=0.1, graph_launches=k), arch=ARCH,
                      schedule="flat").simulate(_bodies()[:4]) for k in (0, 16)]
    assert torch.equal(runs[0].com_end, runs[1].com_end) and torch.equal(runs[0].displacement, runs[1].displacement)


def test_many_simulate_calls_of_random_batch_size() -> None:
    from freeform.sim import SimConfig, Simulator

    sys.path.insert(0, str(ROOT))
    from benchmarks.bench_sim import random_design_bodies

    largest = 512 if ARCH == "cuda" else 32
    bodies = random_design_bodies(largest, seed=1).numpy()
    sim = Simulator(SimConfig(precision="f32", burn_in=0.01, duration=0.01), arch=ARCH, schedule="flat")
    rng = np.random.default_rng(0)
    for _ in range(40 if ARCH == "cuda" else 10):
        b = int(rng.integers(1, largest + 1))
        r = sim.simulate(bodies[:b])
        assert r.displacement.shape == (b,) and torch.isfinite(r.displacement).all()


def _volume_ppo(cuda_graph: bool, **agent: object):
    """A small design-env PPO of the paper's network on the volume task (no simulation), on the device."""
    from freeform.config import compose
    from freeform.run.build import build

    overrides = [f"agent.{k}={v}" for k, v in agent.items()]
    cfg = compose("experiment=volume_cpu", "trainer.device=cuda", "env.num_envs=16", "env.steps=16",
                  "env.resolution=8", "agent.sgd_minibatch_size=64", "agent.num_sgd_iter=3",
                  f"agent.cuda_graph={str(cuda_graph).lower()}", *overrides)
    return build(cfg, torch.device("cuda"))[1]


cuda_only = pytest.mark.skipif(ARCH != "cuda", reason="CUDA graphs need a CUDA device (the rehearsal has none)")


@cuda_only
@pytest.mark.parametrize("agent", [{}, {"grad_clip": 0.5, "advantage_norm": "minibatch", "kl_coeff": 0.0},
                                   {"trunk": "gather"}])
def test_graphed_update_follows_the_eager_one(agent: dict) -> None:
    """One epoch of 12 Adam steps (3 eager warm-ups, the capture, 8 replays) on the same rollout: the same statistics
    and weights as the eager update, to float rounding (capturable Adam computes its bias correction on the device,
    in f32; measured on an H200: 7.7e-7 for the paper's settings, 2.7e-5 with clipping and per-minibatch
    advantages)."""
    agent = {"trunk": "fast", **agent}  # the form "auto" takes in a graph, eager too: one function, two schedules
    runs = []
    for graphed in (False, True):
        ppo = _volume_ppo(graphed, **agent)
        runs.append((ppo.train_epoch(), ppo.flat.value.detach().clone()))
    (eager_stats, eager_w), (graph_stats, graph_w) = runs
    gap = (eager_w - graph_w).abs().max().item()
    print(f"graphed vs eager update, {agent or 'paper'}: weights {gap:.2e}, total loss "
          f"{eager_stats['total_loss']:.6f} / {graph_stats['total_loss']:.6f}")
    assert 0.0 < (eager_w - _volume_ppo(False, **agent).flat.value).abs().max().item()  # the epoch moved the weights
    assert gap < 1e-4
    for key in ("total_loss", "policy_loss", "value_loss", "entropy"):
        assert graph_stats[key] == pytest.approx(eager_stats[key], rel=1e-4, abs=1e-6)


@cuda_only
@pytest.mark.parametrize("trunk", ["auto", "conv"])  # auto: the gather form, as deterministic algorithms are asked for
def test_graphed_update_resumes_bit_for_bit(trunk: str) -> None:
    """Two epochs straight = one epoch, the state through ``state_dict`` (the checkpoint's format), one more: the
    resumed PPO captures its graph anew, after the eager warm-up steps every update begins with. Under cuDNN's
    deterministic algorithms: its default ones may sum in a varying order (two straight runs are compared first)."""
    with torch.backends.cudnn.flags(enabled=True, benchmark=False, deterministic=True):
        def straight() -> torch.Tensor:
            ppo = _volume_ppo(True, trunk=trunk)
            ppo.train_epoch()
            ppo.train_epoch()
            return ppo.flat.value.detach().clone()

        reference = straight()
        assert torch.equal(reference, straight()), "two straight runs differ: a nondeterministic kernel, not resume"
        first = _volume_ppo(True, trunk=trunk)
        first.train_epoch()
        state = first.state_dict()
        assert isinstance(state["optimizer"]["param_groups"][0]["lr"], float)  # the eager format
        resumed = _volume_ppo(True, trunk=trunk)
        resumed.load_state_dict(state)
        resumed.train_epoch()
        assert torch.equal(reference, resumed.flat.value)
        eager = _volume_ppo(False, trunk=trunk)  # and an eager PPO loads the graphed one's state
        eager.load_state_dict(state)
        eager.train_epoch()
        assert (eager.flat.value - resumed.flat.value).abs().max().item() < 1e-4


if __name__ == "__main__":
    _reference(sys.argv[1])
