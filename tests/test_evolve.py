"""The evolutionary baselines (``freeform.evolve``): each improves a toy fitness, deterministically for a seed;
each runs through ``freeform-train algo=...`` with PPO's run layout; each resumes bit for bit on the CPU; bad
settings fail naming the key.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import run_cli as cli  # tests/helpers.py
from helpers import scalars, straight_and_resumed, tiny

from freeform.body import largest_component
from freeform.checkpoint import load_checkpoint
from freeform.envs import DesignEnv, EnvConfig
from freeform.evolve import CMAES, Evolution, GridGA, SequenceGA, design_grids
from freeform.evolve.grid_ga import touching
from freeform.records import iter_records, read_record

EVOLUTION = ("ga", "cmaes", "grid_ga")


class TargetGrid:
    """Toy task: minus the number of cells that differ from a target grid (0 = the target itself)."""

    def __init__(self, target: torch.Tensor) -> None:
        self.target = target

    def reward(self, final_grids: torch.Tensor) -> torch.Tensor:
        return -(final_grids != self.target).reshape(len(final_grids), -1).sum(dim=1).to(torch.float32)


def _target_env(num_envs: int = 16) -> DesignEnv:
    target = torch.zeros((6, 6, 6), dtype=torch.uint8)
    target[1:5, 1:4, 0:2] = 1  # a 4 x 3 x 2 slab, 24 voxels: one body, reachable by set/clear mutations
    return DesignEnv(num_envs, EnvConfig(resolution=6, steps=6), materials=2, task=TargetGrid(target))


def _evolve(make, generations: int) -> list[float]:
    """Best fitness of each generation of ``make(env)``'s optimiser on the target-grid task."""
    env = _target_env()
    evolution = Evolution(env, make(env), "toy")
    return [evolution.train_epoch()["episode_reward_max"] for _ in range(generations)]


@pytest.mark.parametrize("kind", ["ga", "grid_ga"])
def test_genetic_algorithms_approach_a_target_grid_deterministically(kind: str) -> None:
    def make(env: DesignEnv, seed: int = 0):
        if kind == "ga":
            return SequenceGA(16, 6, env.action_dim, elite=2, tournament=3, crossover=0.5, mutation_rate=0.2, seed=seed)
        return GridGA(16, (6, env.action_dim), 2, lambda a: design_grids(env, a), elite=2, mutation_voxels=2, seed=seed)

    best = _evolve(make, 25)
    assert best == _evolve(make, 25)  # the same seed, the same search, number for number
    assert best != _evolve(lambda env: make(env, seed=1), 25)
    assert all(b >= a for a, b in zip(best, best[1:], strict=False))  # elitism: the best is never lost
    assert best[-1] >= best[0] + 6, best  # at least six cells closer to the target than generation 0's best


@pytest.mark.parametrize("variant", ["sep", "full"])
def test_cmaes_minimises_a_sphere_deterministically(variant: str) -> None:
    centre = torch.linspace(-1.5, 1.5, 3 * 4, dtype=torch.float64).reshape(3, 4)

    def run(seed: int) -> tuple[list[float], torch.Tensor]:
        cma = CMAES(8, 3, 4, sigma=1.0, variant=variant, seed=seed)
        history = []
        for _ in range(60):
            x = cma.ask().to(torch.float64)
            fitness = -((x - centre) ** 2).sum(dim=(1, 2))
            cma.tell(fitness)
            history.append(float(fitness.max()))
        return history, cma.mean

    history, mean = run(0)
    again, mean_again = run(0)
    assert history == again and torch.equal(mean, mean_again)
    assert run(1)[0] != history
    start = float((centre**2).sum())  # the distance² of the initial mean 0
    assert float(((mean - centre) ** 2).sum()) < 1e-3 * start
    assert history[-1] > -1e-2 * start


def test_grid_ga_starts_from_the_designs_of_the_sequence_ga() -> None:
    """With the same seed, generation 0 of both GAs is the same N(0, I) designs: they start level."""
    env = _target_env(8)
    ga = SequenceGA(8, 6, env.action_dim, seed=3)
    grid = GridGA(8, (6, env.action_dim), 2, lambda a: design_grids(env, a), seed=3)
    assert torch.equal(design_grids(env, ga.ask()), grid.ask())


def test_touching_is_the_six_neighbour_dilation() -> None:
    """``touching`` = scipy's binary dilation with the 6-neighbour cross, nothing beyond the grid."""
    from scipy import ndimage

    occupied = torch.rand((5, 6, 6, 6), generator=torch.Generator().manual_seed(0)) < 0.1
    cross = ndimage.generate_binary_structure(3, 1)
    expected = np.stack([ndimage.binary_dilation(o, structure=cross) for o in occupied.numpy()])
    assert np.array_equal(touching(occupied).numpy(), expected)


@pytest.mark.parametrize("materials", [2, 4])
def test_grid_ga_child_is_its_parents_body_with_mutation_voxels_cells_changed_next_to_it(materials: int) -> None:
    """Each child differs from one parent's largest component in exactly ``mutation_voxels`` cells, all on the body
    or touching it; the elites are the best grids unchanged."""
    gen = torch.Generator().manual_seed(1)
    grids = torch.zeros((8, 6, 6, 6), dtype=torch.uint8)
    for i in range(8):  # bodies of different shapes, each with a stray voxel that the child must lose
        grids[i, 1:4, 1:3, 0 : 1 + i % 3] = torch.randint(1, materials, (3, 2, 1 + i % 3), generator=gen).to(torch.uint8)
        grids[i, 5, 5, 5] = 1
        grids[i, 1, 1, 0] = 1 + i % (materials - 1)
        grids[i, 3, 2 + i % 2, 5] = 1
    m, elite = 3, 2
    ga = GridGA(8, (1, 5), materials, lambda a: grids, elite=elite, mutation_voxels=m, seed=0)
    fitness = torch.arange(8, dtype=torch.float32)
    ga.tell(fitness)
    children = ga.ask()
    assert torch.equal(children[:elite], grids[[7, 6]])
    bodies = largest_component(grids)
    near = touching(bodies != 0)
    for child in children[elite:]:
        differs = child.unsqueeze(0) != bodies  # against every parent's body
        parent = int(differs.reshape(8, -1).sum(1).argmin())
        assert int(differs[parent].sum()) == m
        assert bool(near[parent][differs[parent]].all())
        assert int(child.max()) < materials


# ---------------------------------------------------------------------------------------------- through the app

TINY = tiny("env.num_envs=6")
STEPS_PER_EPOCH = 6 * 5


@pytest.mark.parametrize("algo", EVOLUTION)
def test_every_baseline_runs_through_the_training_app(algo: str, tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    run = tmp_path / algo
    cli(monkeypatch, *TINY, f"algo={algo}", "trainer.epochs=3", f"hydra.run.dir={run}")
    tags = scalars(run)
    steps = [STEPS_PER_EPOCH * (e + 1) for e in range(3)]
    for tag in ("charts/episode_reward_mean", "charts/episode_reward_max", "charts/best_reward",
                "charts/designs_scored", "perf/time_rollout", "body/volume", "body/lcc_ratio"):
        assert [s for s, _ in tags[tag]] == steps, tag
    assert [v for _, v in tags["charts/designs_scored"]] == [6.0, 12.0, 18.0]
    best = [v for _, v in tags["charts/best_reward"]]
    assert best == list(np.maximum.accumulate([v for _, v in tags["charts/episode_reward_max"]]))
    records = list(iter_records(run))
    assert [r.epoch for r in records] == [0, 1, 2]
    for rec, (_, mean) in zip(records, tags["charts/episode_reward_mean"], strict=True):
        assert rec.rewards.shape == (6,) and rec.rewards.mean() == pytest.approx(mean)
        np.testing.assert_array_equal(rec.rewards, rec.metrics["volume"])  # volume task: reward = body volume
        assert rec.actions.shape == ((6, 0, 5) if algo == "grid_ga" else (6, 5, 5))
        assert np.isnan(rec.values).all()  # no critic
    if algo != "grid_ga":  # the recorded actions design the recorded grids (the robustness replay's promise)
        env = DesignEnv(6, EnvConfig(resolution=6, steps=5), materials=2)
        grids = design_grids(env, torch.from_numpy(records[-1].actions))
        np.testing.assert_array_equal(grids.numpy(), records[-1].final_grids)
    ckpt = load_checkpoint(run / "checkpoints" / "last.pt")  # weights_only: tensors and numbers only
    assert ckpt["algo"] == algo and ckpt["config"]["algo"]["name"] == algo and ckpt["epoch"] == 3


@pytest.mark.parametrize("algo", EVOLUTION)
def test_two_generations_equal_one_plus_resume_one_bit_for_bit(algo: str, tmp_path: Path) -> None:
    from freeform.config import compose

    straight_and_resumed(compose(*TINY, f"algo={algo}", "seed=5"), tmp_path, epochs=3)

    a = load_checkpoint(tmp_path / "straight" / "checkpoints" / "last.pt")["evolution"]
    b = load_checkpoint(tmp_path / "split" / "checkpoints" / "last.pt")["evolution"]

    def same(x, y, where: str = "evolution") -> None:
        if isinstance(x, torch.Tensor):
            assert torch.equal(x, y), where
        elif isinstance(x, dict):
            assert x.keys() == y.keys(), where
            for k in x:
                same(x[k], y[k], f"{where}.{k}")
        elif isinstance(x, (list, tuple)):
            for i, (u, v) in enumerate(zip(x, y, strict=True)):
                same(u, v, f"{where}[{i}]")
        else:
            assert x == y or (x != x and y != y), where

    same(a, b)
    for name in ("epoch_000001.npz", "epoch_000002.npz"):
        ra, rb = (read_record(tmp_path / d / "records" / name) for d in ("straight", "split"))
        np.testing.assert_array_equal(ra.actions, rb.actions)
        np.testing.assert_array_equal(ra.final_grids, rb.final_grids)
        np.testing.assert_array_equal(ra.rewards, rb.rewards)


def test_bad_algo_config_fails_naming_the_key(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    bad = {
        "algo.name=nes": r"algo\.name must be one of \['ppo', 'ga', 'cmaes', 'grid_ga', 'distill'\], got 'nes'",
        "algo.mutation_rate=1.5": r"algo\.mutation_rate must be a probability in \[0, 1\], got 1\.5",
        "algo.elite=6": r"algo\.elite must be an integer in \[0, env\.num_envs - 1 = 5\], got 6",
        "algo.tournament=0": r"algo\.tournament must be an integer >= 1, got 0",
        "algo.variant=diag": r"algo\.variant must be one of \['sep', 'full'\], got 'diag'",
        "algo.sigma=0": r"algo\.sigma must be > 0, got 0",
        "env.dense_every=2": r"env\.dense_every must be 0 with algo\.name=ga",
    }
    for i, (override, message) in enumerate(bad.items()):
        with pytest.raises(SystemExit, match=message):
            cli(monkeypatch, *TINY, "algo=ga", override, f"hydra.run.dir={tmp_path / str(i)}")
    with pytest.raises(SystemExit):
        cli(monkeypatch, *TINY, "algo=ga", "algo.mutation=0.1", f"hydra.run.dir={tmp_path / 'x'}")
    assert "algo.mutation" in capsys.readouterr().err  # an unknown key: Hydra names it
    # A run's algorithm cannot change when it is resumed.
    run = tmp_path / "ga"
    cli(monkeypatch, *TINY, "algo=ga", "trainer.epochs=1", f"hydra.run.dir={run}")
    with pytest.raises(SystemExit, match=r"algo: cannot change algo\.name"):
        cli(monkeypatch, f"trainer.resume={run}", "algo=cmaes", "trainer.epochs=2")
