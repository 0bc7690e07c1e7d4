"""Dense design rewards: the improvement of the task's score of the partial body every k steps; an episode's
rewards sum to the sparse terminal reward."""

from __future__ import annotations

import pytest
import torch

from freeform.body import largest_component
from freeform.envs import DesignEnv, EnvConfig, VolumeTask
from freeform.envs.dense import DenseDesignReward


def volume(grids: torch.Tensor) -> torch.Tensor:
    return (largest_component(grids) != 0).flatten(1).sum(1).float()


@pytest.mark.parametrize("every", [1, 3])
def test_dense_rewards_are_score_improvements_and_sum_to_the_terminal_reward(every):
    env = DesignEnv(4, EnvConfig(resolution=6, steps=7), materials=2, task=VolumeTask(), seed=0)
    dense = DenseDesignReward(env, every=every)
    obs = dense.reset(seed=0)
    gen = torch.Generator().manual_seed(1)
    for _ in range(2):  # two episodes: the state resets between them
        total, last = torch.zeros(4), torch.zeros(4)
        for t in range(1, 8):
            obs, r, done, info = dense.step(torch.randn(4, dense.action_dim, generator=gen))
            total += r
            if t < 7:
                assert not done.any()
                if t % every == 0:
                    torch.testing.assert_close(r, volume(obs) - last)
                    last = volume(obs)
                else:
                    assert (r == 0).all()
        assert done.all()
        torch.testing.assert_close(total, info["task_reward"])  # telescoping: the sparse return
        torch.testing.assert_close(info["task_reward"], volume(info["final_grids"]))
        assert (info["task_reward"] > 0).all()


def test_dense_reward_rejects_a_bad_interval():
    env = DesignEnv(1, EnvConfig(resolution=4, steps=2), materials=2, task=VolumeTask())
    with pytest.raises(ValueError, match="every"):
        DenseDesignReward(env, every=0)
