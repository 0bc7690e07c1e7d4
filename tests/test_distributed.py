"""Data-parallel PPO on the CPU with ``gloo``: R = 2 ranks give the single process's run, up to summation order.

The 2-rank runs are real process groups: one spawned pair of ranks (``torch.multiprocessing``, a module fixture) runs
every case of the algorithm, each its own folder, and ``torchrun`` runs the training app; the truth they are held to is the 1-process run of the same config and seed,
which is the unchanged single-process algorithm. The environment count (5) does not divide by the ranks (3 + 2).
"""

from __future__ import annotations

import functools
import os
import shutil
import subprocess
import sys
import warnings
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from helpers import run_cli as cli  # tests/helpers.py
from helpers import scalars, tiny

from freeform.agents import PPO, MLPActorCritic, PPOConfig, RecurrentActorCritic, VoxelActorCritic
from freeform.agents.distributed import Collectives, DataParallel, env_slice
from freeform.envs import DesignEnv, EnvConfig
from freeform.records import read_record

pytestmark = pytest.mark.usefixtures("one_thread", "keep_global_rng")  # tests/conftest.py

NUM_ENVS, RHO, STEPS = 5, 6, 4
# Global batch 5 x 4 = 20 samples, minibatch 6: 3 minibatches per pass (2 samples dropped), shares vary by rank.
PPO_KW = dict(rollout_steps=STEPS, num_sgd_iter=3, sgd_minibatch_size=6, seed=3, lr=3e-3)
NOT_COMPARED = ("time_", "samples_per_second")  # wall-clock figures


# The cases: the paper's network and advantage standardisations; and the MLP over the flattened grids with both
# running normalisations (its critic runs once per rollout; the reward scaling gathers every rank's returns).
CASES = {
    "batch": dict(advantage_norm="batch"),
    "minibatch": dict(advantage_norm="minibatch"),
    "mlp_normalised": dict(advantage_norm="minibatch", obs_norm=True, reward_norm=True, grad_clip=0.5),
    # an LSTM: sequences of 3 steps (2 chunks per env, the second padded), 2 per minibatch, split by their env
    "recurrent": dict(advantage_norm="minibatch", sequence_length=3, grad_clip=0.5),
}
STUDENTS = ["feed-forward", "recurrent"]  # algo=distill's students
# Checkpoints whose state has a dimension equal to the local env count by chance: (local envs, hidden width).
NAMED_STATE_CASES = {"hidden width = local envs": (4, 4),
                     "generator state length = local envs": (torch.Generator().get_state().numel(), 8)}


def make_ppo(envs: tuple[int, int] = (0, NUM_ENVS), case: str = "batch") -> PPO:
    """Environments ``[lo, hi)`` of the run (the caller's rank slice); every rank builds the same policy."""
    torch.manual_seed(0)
    env = DesignEnv(envs[1] - envs[0], EnvConfig(resolution=RHO, steps=STEPS), materials=2)
    if case == "mlp_normalised":
        policy = MLPActorCritic(RHO**3, env.action_dim, hidden=(16,))
    elif case == "recurrent":
        policy = RecurrentActorCritic(RHO**3, env.action_dim, hidden=(8,), rnn_hidden=8)
    else:
        policy = VoxelActorCritic(resolution=RHO, materials=2, hidden=16)
    return PPO(env, policy, PPOConfig(**{**PPO_KW, **CASES[case]}))


def flat_params(ppo: PPO) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in ppo.policy.parameters()])


def comparable(stats: dict[str, float]) -> dict[str, float]:
    return {k: v for k, v in stats.items() if not k.startswith(NOT_COMPARED)}


def _ppo_case(rank: int, world: int, out_dir: Path, case: str) -> None:
    """One rank: two fresh epochs (checkpoint after the first), then one epoch resumed from the 1-process checkpoint."""
    envs = env_slice(NUM_ENVS, world, rank)
    ppo = make_ppo(envs, case)
    first = ppo.train_epoch()
    actions = ppo.dp.gather_envs(ppo.rollout.actions, dim=1)
    ppo.save(out_dir / "two_ranks_epoch1.pt")  # collective; rank 0 writes
    second = ppo.train_epoch()
    resumed = PPO.load(out_dir / "one_process_epoch1.pt", DesignEnv(envs[1] - envs[0], EnvConfig(resolution=RHO, steps=STEPS),
                                                                    materials=2))
    resumed_stats = resumed.train_epoch()
    torch.save(
        {
            "stats": [first, second],
            "actions": actions,
            "params": flat_params(ppo),
            "generator": ppo.generator.get_state(),
            "kl_coeff": ppo.kl_coeff,
            "global_step": ppo.global_step,
            "resumed_stats": resumed_stats,
            "resumed_params": flat_params(resumed),
        },
        out_dir / f"rank{rank}.pt",
    )


def _worker(rank: int, world: int, init_file: str, out_dir: str) -> None:
    """One rank of every 2-rank case of this file, in one process group: a spawned process pays its interpreter's
    start (torch, freeform) once for all of them, and each case writes its results to its own folder."""
    torch.set_num_threads(1)
    # (a rank whose collectives fall out of step with the other's fails in minutes, not gloo's default 30)
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world,
                            timeout=timedelta(minutes=5))
    out = Path(out_dir)
    cases = [*(("ppo", c, functools.partial(_ppo_case, case=c)) for c in CASES),
             *(("distill", s, functools.partial(_distill_case, student=s)) for s in STUDENTS),
             *(("named", c, functools.partial(_named_state_case, local_envs=n, hidden=h))
               for c, (n, h) in NAMED_STATE_CASES.items())]
    try:
        for kind, case, run in cases:
            try:
                run(rank, world, out / kind / case)
            except Exception as exc:  # (every test of the fixture reports this: say which case failed)
                raise RuntimeError(f"2-rank case {kind}/{case} failed on rank {rank}") from exc
        dist.barrier()  # both ranks are done with gloo before either tears it down
    finally:
        dist.destroy_process_group()
    # Skip the interpreter's teardown: native thread pools (gloo's, Taichi's) destroyed at exit have aborted a
    # finished worker ("terminate called without an active exception") now and then. The results are on disk.
    os._exit(0)


@pytest.fixture(scope="module")
def two_ranks(tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[str, str], Any]:
    """The 1-process runs of the PPO and distillation cases (the PPO cases' first epoch checkpointed for the ranks
    to resume), then one spawned pair of gloo ranks running every case: ``{(kind, case): {folder, one: the 1-process results, ranks:
    [rank 0's, rank 1's]}}``, kind "ppo" | "distill" | "named" (whose results are the files in its folders)."""
    root = tmp_path_factory.mktemp("two_ranks")
    threads, rng = torch.get_num_threads(), torch.get_rng_state()
    torch.set_num_threads(1)
    try:
        singles: dict[tuple[str, str], Any] = {}
        for case in CASES:
            (root / "ppo" / case).mkdir(parents=True)
            single = make_ppo(case=case)
            first = single.train_epoch()
            actions = single.rollout.actions.clone()
            single.save(root / "ppo" / case / "one_process_epoch1.pt")
            second = single.train_epoch()
            singles["ppo", case] = dict(ppo=single, first=first, second=second, actions=actions)
        for student in STUDENTS:
            (root / "distill" / student).mkdir(parents=True)
            single = make_distillation(student=student)
            singles["distill", student] = dict(stats=[single.train_epoch() for _ in range(3)],
                                               params=flat_params(single))
        for case in NAMED_STATE_CASES:
            (root / "named" / case).mkdir(parents=True)
        mp.spawn(_worker, args=(2, str(root / "pg"), str(root)), nprocs=2, join=True)
    finally:
        torch.set_num_threads(threads)
        torch.set_rng_state(rng)
    return {key: dict(folder=root / key[0] / key[1], one=singles.get(key),
                      ranks=[torch.load(root / key[0] / key[1] / f"rank{r}.pt", weights_only=False) for r in range(2)]
                      if key[0] != "named" else None)
            for key in (*(("ppo", c) for c in CASES), *(("distill", s) for s in STUDENTS),
                        *(("named", c) for c in NAMED_STATE_CASES))}


@pytest.mark.slow  # (the two_ranks fixture: one spawn for all)
@pytest.mark.parametrize("case", list(CASES))
def test_two_gloo_ranks_match_one_process(two_ranks: dict[tuple[str, str], Any], case: str) -> None:
    one, ranks = two_ranks["ppo", case]["one"], two_ranks["ppo", case]["ranks"]
    single, first, second, actions = one["ppo"], one["first"], one["second"], one["actions"]

    # Identical weights, β and sampling generator on both ranks (the same all-reduced gradients, the same draws).
    assert torch.equal(ranks[0]["params"], ranks[1]["params"])
    assert ranks[0]["kl_coeff"] == ranks[1]["kl_coeff"] == single.kl_coeff
    # The generator drew exactly what the single process drew: the global noise, the global permutations.
    assert torch.equal(ranks[0]["generator"], single.generator.get_state())
    assert ranks[0]["global_step"] == single.global_step == 2 * NUM_ENVS * STEPS

    # The first epoch's global statistics, and the second's (after one data-parallel update), equal the single run's.
    for got, want in zip(ranks[0]["stats"], [first, second], strict=True):
        got, want = comparable(got), comparable(want)
        assert got.keys() == want.keys()
        for key in want:
            assert got[key] == pytest.approx(want[key], rel=1e-4, abs=1e-6, nan_ok=True), key
    assert ranks[1]["stats"][0]["episode_reward_mean"] == pytest.approx(first["episode_reward_mean"])
    # Env n got the same action whatever the rank count (the policy's float order differs by batch size only).
    torch.testing.assert_close(ranks[0]["actions"], actions, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(ranks[0]["params"], flat_params(single), rtol=1e-4, atol=1e-5)

    # Resume across rank counts: 2 ranks continuing the 1-process checkpoint = the 1-process run's second epoch ...
    for key, want in comparable(second).items():
        assert ranks[0]["resumed_stats"][key] == pytest.approx(want, rel=1e-4, abs=1e-6, nan_ok=True), key
    torch.testing.assert_close(ranks[0]["resumed_params"], flat_params(single), rtol=1e-4, atol=1e-5)
    # ... and 1 process continuing the 2-rank checkpoint too.
    back = PPO.load(two_ranks["ppo", case]["folder"] / "two_ranks_epoch1.pt",
                    DesignEnv(NUM_ENVS, EnvConfig(resolution=RHO, steps=STEPS), materials=2))
    assert back.global_step == NUM_ENVS * STEPS
    stats = back.train_epoch()
    for key, want in comparable(second).items():
        assert stats[key] == pytest.approx(want, rel=1e-4, abs=1e-6, nan_ok=True), key
    torch.testing.assert_close(flat_params(back), flat_params(single), rtol=1e-4, atol=1e-5)


def make_distillation(envs: tuple[int, int] = (0, NUM_ENVS), student: str = "feed-forward") -> Any:
    """DAgger from a fixed network (the same teacher for every env) into a student, on environments ``[lo, hi)``;
    the recurrent student's sequences of 3 steps begin mid-episode (episodes of 4), so its state pass runs too."""
    from freeform.agents.distill import Distillation, DistillConfig

    torch.manual_seed(7)
    teacher_net = VoxelActorCritic(resolution=RHO, materials=2, hidden=8).eval()

    def teacher(obs: torch.Tensor, _envs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        with torch.no_grad():
            return tuple(teacher_net(obs))

    torch.manual_seed(0)
    env = DesignEnv(envs[1] - envs[0], EnvConfig(resolution=RHO, steps=STEPS), materials=2)
    policy = (RecurrentActorCritic(RHO**3, env.action_dim, hidden=(8,), rnn_hidden=8) if student == "recurrent"
              else VoxelActorCritic(resolution=RHO, materials=2, hidden=16))
    return Distillation(env, policy, teacher, PPOConfig(**{**PPO_KW, "sequence_length": 3}),
                        DistillConfig(beta=0.5, buffer=2), first_env=envs[0], total_envs=NUM_ENVS)


def _distill_case(rank: int, world: int, out_dir: Path, student: str) -> None:
    """One rank of :func:`make_distillation`: three rounds (the third drops the first from the dataset)."""
    learner = make_distillation(env_slice(NUM_ENVS, world, rank), student)
    stats = [learner.train_epoch() for _ in range(3)]
    torch.save({"stats": stats, "params": flat_params(learner)}, out_dir / f"rank{rank}.pt")


@pytest.mark.slow  # (the two_ranks fixture: one spawn for all)
@pytest.mark.parametrize("student", STUDENTS)
def test_two_gloo_ranks_distil_as_one_process(two_ranks: dict[tuple[str, str], Any], student: str) -> None:
    """algo=distill data-parallel: the teachers' mixing draws, the aggregated dataset's minibatches (samples, or a
    recurrent student's sequences, split between ranks by their env) and the summed gradients give the single
    process's student and statistics after three rounds, up to summation order."""
    single, ranks = two_ranks["distill", student]["one"], two_ranks["distill", student]["ranks"]
    want = single["stats"]
    assert torch.equal(ranks[0]["params"], ranks[1]["params"])
    torch.testing.assert_close(ranks[0]["params"], single["params"], rtol=1e-4, atol=1e-5)
    for got, expected in zip(ranks[0]["stats"], want, strict=True):
        got, expected = comparable(got), comparable(expected)
        assert got.keys() == expected.keys()
        for key in expected:
            assert got[key] == pytest.approx(expected[key], rel=1e-4, abs=1e-6, nan_ok=True), key


# ---------------------------------------------------------------------------------------------------------------
# The split rules, by hand.
# ---------------------------------------------------------------------------------------------------------------


def test_env_slices_are_contiguous_and_balanced() -> None:
    assert [env_slice(5, 2, r) for r in range(2)] == [(0, 3), (3, 5)]
    assert [env_slice(10, 3, r) for r in range(3)] == [(0, 4), (4, 7), (7, 10)]
    assert [env_slice(8, 4, r) for r in range(4)] == [(0, 2), (2, 4), (4, 6), (6, 8)]
    with pytest.raises(ValueError, match="num_envs"):
        env_slice(2, 3, 0)
    with pytest.raises(ValueError, match="rank"):
        env_slice(4, 2, 2)


@pytest.mark.parametrize("kind", ["normal", "uniform"])
@pytest.mark.parametrize("like_shape", [(4, None, 5), (None, 5)], ids=["rollout [T, n, A]", "step [n, A]"])
def test_each_rank_keeps_its_envs_of_the_single_process_noise(like_shape: tuple, kind: str) -> None:
    """Ranks holding 3 and 2 of N = 5 envs: their noise (a Gaussian's normal draws, or the uniform ones of the
    discrete distributions), joined along the env dimension, is the single process's draw, and every rank's
    generator ends where the single process's does."""
    def draw(dp: Collectives, local: int) -> tuple[torch.Tensor, torch.Tensor]:
        g = torch.Generator().manual_seed(7)
        shape = tuple(local if d is None else d for d in like_shape)
        return dp.env_noise(torch.empty(shape), g, kind), g.get_state()

    single, single_state = draw(Collectives.single(5), 5)
    parts = [draw(DataParallel(rank=r, world_size=2, counts=(3, 2)), n) for r, n in ((0, 3), (1, 2))]
    torch.testing.assert_close(torch.cat([p for p, _ in parts], dim=-2), single, rtol=0, atol=0)
    assert all(torch.equal(state, single_state) for _, state in parts)
    if kind == "uniform":
        assert (single >= 0).all() and (single < 1).all()
    with pytest.raises(ValueError, match="dimension -2"):
        DataParallel(rank=0, world_size=2, counts=(3, 2)).env_noise(torch.empty(3, 2, 5), torch.Generator())
    with pytest.raises(ValueError, match="noise kind"):
        Collectives.single(5).env_noise(torch.empty(5, 2), torch.Generator(), "poisson")


def test_local_indices_pick_this_ranks_samples_in_minibatch_order() -> None:
    # N = 5 envs over ranks holding 3 and 2; global sample g = t*5 + n; rank 1 holds n = 3, 4 -> local t*2 + n-3.
    dp = DataParallel(rank=1, world_size=2, counts=(3, 2))
    idx = torch.tensor([4, 0, 8, 13, 3, 19, 5])  # (t, n) = (0,4) (0,0) (1,3) (2,3) (0,3) (3,4) (1,0)
    mask, local = dp.local_indices(idx)
    assert mask.tolist() == [True, False, True, True, True, True, False]
    assert local.tolist() == [1, 2, 4, 0, 7]
    rank0 = DataParallel(rank=0, world_size=2, counts=(3, 2))
    mask0, local0 = rank0.local_indices(idx)
    assert (mask0 ^ mask).all()  # every sample belongs to exactly one rank
    assert local0.tolist() == [0, 3]  # (0,0) -> 0, (1,0) -> 3


def test_shard_state_slices_only_what_is_named_per_env() -> None:
    """Per-environment state is named (under ``per_env``), never guessed from a shape: a weight matrix or an RNG
    state whose first dimension equals the env count is left whole."""
    dp = DataParallel(rank=1, world_size=2, counts=(3, 2))
    state = {
        "per_env": {"obs": torch.arange(5 * 2).reshape(5, 2)},
        "policy": {"w": torch.arange(5 * 3).reshape(5, 3)},  # 5 rows, like the global env count: not per env
        "generator": torch.zeros(5, dtype=torch.uint8),
        "env": {"per_env": {"grids": torch.arange(5)}, "t": 3, "config": {"resolution": 6}},
    }
    local = dp.shard_state(state)
    assert local["per_env"]["obs"].tolist() == [[6, 7], [8, 9]]
    assert torch.equal(local["policy"]["w"], state["policy"]["w"])
    assert torch.equal(local["generator"], state["generator"])
    assert local["env"]["per_env"]["grids"].tolist() == [3, 4]
    assert local["env"]["config"] == {"resolution": 6} and local["env"]["t"] == 3
    with pytest.raises(ValueError, match=r"per_env\.obs.*global env count 5"):
        dp.shard_state({"per_env": {"obs": torch.zeros(4, 2)}})
    # The single-process collectives are the identity.
    single = Collectives.single(5)
    assert single.shard_state(state) == state and single.gather_state(state) == state


class ToyEnv:
    """Points on a line pushed by the action: obs = position [N, 2], reward = −|position|, episodes of 3 steps.
    Its state names its per-environment part (``per_env``)."""

    def __init__(self, num_envs: int) -> None:
        self.num_envs, self.observation_shape, self.action_dim, self.device = num_envs, (2,), 2, torch.device("cpu")
        self.pos, self.t = torch.zeros(num_envs, 2), 0

    def reset(self, seed: int | None = None) -> torch.Tensor:
        self.pos, self.t = torch.zeros(self.num_envs, 2), 0
        return self.pos.clone()

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        self.pos = self.pos + 0.1 * actions.clamp(-1, 1)
        self.t += 1
        reward = -self.pos.norm(dim=1)
        done = torch.full((self.num_envs,), self.t % 3 == 0)
        return self.pos.clone(), reward, done, {}

    def state_dict(self) -> dict[str, Any]:
        return {"per_env": {"pos": self.pos.clone()}, "t": self.t}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.pos, self.t = state["per_env"]["pos"].clone(), int(state["t"])


def _named_state_case(rank: int, world: int, out_dir: Path, local_envs: int, hidden: int) -> None:
    torch.manual_seed(0)
    cfg = PPOConfig(rollout_steps=2, num_sgd_iter=2, sgd_minibatch_size=min(4096, local_envs), seed=1, lr=1e-2)
    ppo = PPO(ToyEnv(local_envs), MLPActorCritic(2, 2, hidden=(hidden, hidden)), cfg)
    ppo.train_epoch()
    ppo.save(out_dir / "two_ranks.pt")  # collective; rank 0 writes
    if rank == 0:
        torch.save({"policy": ppo.policy.state_dict(), "optimizer": ppo.optimizer.state_dict(),
                    "generator": ppo.generator.get_state()}, out_dir / "rank0.pt")


@pytest.mark.slow  # (the two_ranks fixture: one spawn for all)
@pytest.mark.parametrize("case", list(NAMED_STATE_CASES))
def test_two_rank_checkpoint_loads_in_one_process_with_rank0s_exact_state(two_ranks: dict[tuple[str, str], Any], case: str) -> None:
    """The data-loss bug: deciding per-environment state by shape stacked the two ranks' identical weights (and
    Adam moments, or the generator state) when a dimension happened to equal the local env count."""
    folder, (local_envs, _) = two_ranks["named", case]["folder"], NAMED_STATE_CASES[case]
    rank0 = torch.load(folder / "rank0.pt", weights_only=True)
    loaded = PPO.load(folder / "two_ranks.pt", ToyEnv(2 * local_envs))
    assert loaded.num_envs == 2 * local_envs and loaded.env.pos.shape == (2 * local_envs, 2)
    for name, tensor in rank0["policy"].items():
        assert torch.equal(loaded.policy.state_dict()[name], tensor), name
    want, got = rank0["optimizer"]["state"], loaded.optimizer.state_dict()["state"]
    assert want.keys() == got.keys()
    for key in want:
        for name in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(got[key][name], want[key][name]), (key, name)
    assert torch.equal(loaded.generator.get_state(), rank0["generator"])


# ---------------------------------------------------------------------------------------------------------------
# The training app under torchrun: rank 0 writes, the records are the global batch's, resume with another R.
# ---------------------------------------------------------------------------------------------------------------

TINY = tiny(f"env.num_envs={NUM_ENVS}", f"env.steps={STEPS}", "agent.sgd_minibatch_size=6", "trainer.print_every=1")


def finished_then_aborted(output: str, run: Path) -> bool:
    """Whether a failed torchrun run failed only at its end: a rank's C++ runtime aborted (SIGABRT, "terminate
    called without an active exception") after rank 0 had written its last checkpoint and logged "done"."""
    return ("terminate called without an active exception" in output and "(SIGABRT)" in output
            and "done: 1 epochs" in output and (run / "checkpoints" / "epoch_000001.pt").is_file())


@pytest.mark.slow
def test_torchrun_two_ranks_write_once_and_resume_with_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    torchrun = Path(sys.executable).parent / "torchrun"
    if not torchrun.exists():
        pytest.skip("torchrun is not installed beside this python")
    two = tmp_path / "two"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONFAULTHANDLER": "1"}  # (an abort prints where it happened)
    for attempt in range(2):
        out = subprocess.run(
            [str(torchrun), "--standalone", "--nproc_per_node=2", "-m", "freeform.train", *TINY, "trainer.epochs=1",
             f"hydra.run.dir={two}"],
            capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path,
        )
        if attempt == 0 and out.returncode != 0 and finished_then_aborted(out.stdout + out.stderr, two):
            # Seen once in CI and once in ~180 local runs: a secondary rank aborts in gloo's teardown after the run
            # completed (every checkpoint written, rank 0 past shutdown). Kept visible, run once more from scratch.
            warnings.warn("torchrun: a rank aborted at teardown after a completed run (retried once): "
                          + (out.stdout + out.stderr)[-3000:], stacklevel=1)
            shutil.rmtree(two)
            continue
        break
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    one = tmp_path / "one"
    cli(monkeypatch, *TINY, "trainer.epochs=2", f"hydra.run.dir={one}")

    # Rank 0 alone wrote: one event file, one summary line per epoch in the log, a world size in run_info.
    assert len(list(two.glob("events.out.tfevents.*"))) == 1
    assert (two / "train.log").read_text().count("epoch 1 |") == 1
    assert '"world_size": 2' in (two / "run_info.json").read_text()
    assert sorted(p.name for p in (two / "checkpoints").iterdir()) == ["epoch_000000.pt", "epoch_000001.pt", "last.pt"]

    # The record holds all 5 environments' episodes, the same designs as the single process's.
    r2, r1 = read_record(two / "records" / "epoch_000000.npz"), read_record(one / "records" / "epoch_000000.npz")
    assert r2.actions.shape == r1.actions.shape == (NUM_ENVS, STEPS, 3 + 2)
    np.testing.assert_allclose(r2.actions, r1.actions, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(r2.final_grids, r1.final_grids)
    np.testing.assert_array_equal(r2.rewards, r1.rewards)
    s2, s1 = scalars(two), scalars(one)
    step = NUM_ENVS * STEPS
    for tag in ("charts/episode_reward_mean", "losses/policy_loss", "losses/approx_kl", "losses/explained_variance",
                "body/volume"):
        assert dict(s2[tag])[step] == pytest.approx(dict(s1[tag])[step], rel=1e-4, abs=1e-6), tag

    # Resume the 2-rank run in one process: its second epoch is the single run's second epoch.
    cli(monkeypatch, f"trainer.resume={two}", "trainer.epochs=2", "trainer.threads=1")
    a, b = read_record(two / "records" / "epoch_000001.npz"), read_record(one / "records" / "epoch_000001.npz")
    np.testing.assert_allclose(a.actions, b.actions, rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(a.final_grids, b.final_grids)
    ca = torch.load(two / "checkpoints" / "last.pt", weights_only=True)
    cb = torch.load(one / "checkpoints" / "last.pt", weights_only=True)
    for name, tensor in cb["ppo"]["policy"].items():
        torch.testing.assert_close(ca["ppo"]["policy"][name], tensor, rtol=1e-4, atol=1e-5)
    assert torch.equal(ca["ppo"]["generator"], cb["ppo"]["generator"])
