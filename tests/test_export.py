"""``PPO.export``: the ONNX file, run by onnxruntime, gives what ``ppo.act(obs, deterministic=True)`` gives — with
observation normalisation folded in, for Box and discrete actions and the voxel network — and what cannot be
exported is refused with the reason."""

from __future__ import annotations

import sys
from typing import Any

import numpy as np
import pytest
import torch

from freeform.agents import PPO, MLPActorCritic, PPOConfig, VoxelActorCritic

ort = pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")
gym = pytest.importorskip("gymnasium")
from freeform.envs import from_gymnasium  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread", "keep_global_rng")  # tests/conftest.py


def gym_ppo(task: str, cfg: PPOConfig, num_envs: int = 2) -> PPO:
    torch.manual_seed(0)
    vec = gym.make_vec(task, num_envs=num_envs, vectorization_mode="sync",
                       vector_kwargs={"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP})
    env = from_gymnasium(vec, seed=0)
    return PPO(env, MLPActorCritic.for_env(env), cfg)


def run_onnx(path: Any, **inputs: torch.Tensor) -> list[np.ndarray]:
    session = ort.InferenceSession(str(path))
    return session.run(None, {k: v.numpy() for k, v in inputs.items()})


def test_exported_gaussian_policy_with_obs_norm_equals_act(tmp_path: Any) -> None:
    ppo = gym_ppo("Pendulum-v1", PPOConfig.cleanrl(rollout_steps=32, sgd_minibatch_size=16, num_sgd_iter=1))
    ppo.learn(2)  # trained weights and observation statistics away from their initial values
    assert ppo.obs_rms is not None and ppo.obs_rms.mean.abs().max() > 0
    obs = torch.randn(5, 3, generator=torch.Generator().manual_seed(1)) * 3  # another batch size than training's
    (actions,) = run_onnx(ppo.export(tmp_path / "pendulum.onnx"), obs=obs)
    want = ppo.act(obs, deterministic=True)
    assert actions.shape == (5, 1) and actions.dtype == np.float32
    np.testing.assert_allclose(actions, want.numpy(), rtol=1e-5, atol=1e-6)


def test_exported_discrete_policy_returns_the_same_indices(tmp_path: Any) -> None:
    ppo = gym_ppo("CartPole-v1", PPOConfig.cleanrl_discrete(rollout_steps=32, sgd_minibatch_size=32, num_sgd_iter=1))
    ppo.learn(1)
    obs = torch.randn(64, 4, generator=torch.Generator().manual_seed(2))
    (actions,) = run_onnx(ppo.export(tmp_path / "cartpole.onnx"), obs=obs)
    assert actions.dtype == np.int64
    np.testing.assert_array_equal(actions, ppo.act(obs, deterministic=True).numpy())


def test_exported_voxel_policy_reads_uint8_grids(tmp_path: Any) -> None:
    from freeform.envs import DesignEnv, EnvConfig, VolumeTask

    torch.manual_seed(0)
    env = DesignEnv(4, EnvConfig(resolution=6, steps=4),
                    materials=3, task=VolumeTask(), compute_metrics=False, seed=0)
    ppo = PPO(env, VoxelActorCritic(resolution=6, materials=3, hidden=8),
              PPOConfig(rollout_steps=4, num_sgd_iter=1, sgd_minibatch_size=8))
    ppo.learn(1)
    grids = torch.randint(0, 3, (3, 6, 6, 6), dtype=torch.uint8, generator=torch.Generator().manual_seed(3))
    (actions,) = run_onnx(ppo.export(tmp_path / "voxel.onnx"), obs=grids)  # the sparse CPU trunk's twin, Conv3d
    np.testing.assert_allclose(actions, ppo.act(grids, deterministic=True).numpy(), rtol=1e-5, atol=1e-5)


class DataDependent(MLPActorCritic):
    """A network whose Python branches on its input's values: nothing torch.export can trace."""

    def action_params(self, obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return super().action_params(obs if bool(obs.sum() > 0) else -obs)


def test_what_cannot_be_exported_is_refused_with_the_reason(tmp_path: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    ppo = gym_ppo("CartPole-v1", PPOConfig.cleanrl_discrete(rollout_steps=8, sgd_minibatch_size=8, num_sgd_iter=1), 1)
    ppo.policy = DataDependent(4, distribution=ppo.distribution)
    with pytest.raises(ValueError, match="cannot export DataDependent to ONNX"):
        ppo.export(tmp_path / "host.onnx")
    monkeypatch.setitem(sys.modules, "onnxscript", None)  # the export extra not installed
    with pytest.raises(ImportError, match=r"freeform\[export\]"):
        ppo.export(tmp_path / "none.onnx")
