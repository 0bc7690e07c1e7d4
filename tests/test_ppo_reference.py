"""The feed-forward PPO path pinned to the bit: a few epochs on a design env (the paper's network, RLlib's
semantics), on Hopper-v5 (CleanRL's Box preset: observation and reward normalisation, minibatch advantages, PPO2
value clip) and on CartPole-v1 (the discrete preset) give the same weights as the code before the PPO package was
split (``tests/data/ppo_feedforward_reference.json``, written by ``python tests/test_ppo_reference.py --write`` at
58715e8: per run the weights' SHA-256, sum, norm and 64 evenly spaced values — a description of the weights, not a
checkpoint). Floating-point results can differ between CPUs (vector widths, MKL paths), so the file also holds a
fingerprint of this host's arithmetic: where it matches the writer's, the weights must be equal bit for bit (their
hash); on another host, within float32 rounding of a few epochs (sum, norm and the sampled values)."""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import pytest
import torch

from freeform.agents import PPO, MLPActorCritic, PPOConfig, VoxelActorCritic

pytestmark = pytest.mark.usefixtures("one_thread", "keep_global_rng")  # tests/conftest.py

REFERENCE = Path(__file__).parent / "data" / "ppo_feedforward_reference.json"


def host_fingerprint() -> str:
    """A hash of a few float32 computations whose last bits depend on the CPU's paths (matmul, conv, exp)."""
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(67, 129, generator=g), torch.randn(129, 33, generator=g)
    x, w = torch.randn(2, 3, 9, 9, 9, generator=g), torch.randn(1, 3, 3, 3, 3, generator=g)
    parts = (a @ b, torch.nn.functional.conv3d(x, w, padding=1), torch.tanh(a).exp(), torch.softmax(a, 1))
    return hashlib.sha256(b"".join(p.contiguous().numpy().tobytes() for p in parts)).hexdigest()


def flat(ppo: PPO) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in ppo.policy.parameters()]).clone()


def design_run() -> torch.Tensor:
    from freeform.envs import DesignEnv, EnvConfig, VolumeTask

    torch.manual_seed(3)
    env = DesignEnv(8, EnvConfig(resolution=8, steps=6),
                    materials=2, task=VolumeTask(), compute_metrics=False, seed=3)
    cfg = PPOConfig(rollout_steps=8, num_sgd_iter=3, sgd_minibatch_size=16, lr=1e-3, seed=3)  # episodes cut
    ppo = PPO(env, VoxelActorCritic(resolution=8, materials=2, hidden=16), cfg)
    ppo.learn(3)
    return flat(ppo)


def gym_run(task: str, preset: str) -> torch.Tensor:
    gym = pytest.importorskip("gymnasium")
    if task.startswith("Hopper"):
        pytest.importorskip("mujoco")
    from freeform.envs import from_gymnasium

    torch.manual_seed(4)
    vec = gym.make_vec(task, num_envs=2, vectorization_mode="sync",
                       vector_kwargs={"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP})
    env = from_gymnasium(vec, seed=4)
    cfg = getattr(PPOConfig, preset)(rollout_steps=64, sgd_minibatch_size=32, num_sgd_iter=2, seed=4)
    ppo = PPO(env, MLPActorCritic.for_env(env), cfg)
    ppo.learn(3)
    vec.close()
    return flat(ppo)


RUNS = {
    "design": design_run,
    "hopper": lambda: gym_run("Hopper-v5", "cleanrl"),
    "cartpole": lambda: gym_run("CartPole-v1", "cleanrl_discrete"),
}


def describe(weights: torch.Tensor) -> dict:
    """What the reference keeps of a run's flat float32 weights."""
    w = weights.float().contiguous()
    return {"shape": list(w.shape), "sha256": hashlib.sha256(w.numpy().tobytes()).hexdigest(),
            "sum": float(w.double().sum()), "norm": float(w.double().norm()),
            "sample": [float(x) for x in w[:: max(1, w.numel() // 64)][:64]]}


@pytest.mark.parametrize("name", list(RUNS))
def test_feedforward_weights_are_those_before_the_split(name: str) -> None:
    saved = json.loads(REFERENCE.read_text())
    got, want = describe(RUNS[name]()), saved["weights"][name]
    assert got["shape"] == want["shape"]
    if saved["host"] == host_fingerprint():
        assert got["sha256"] == want["sha256"], f"{name}: the weights differ from the pinned ones (sum {got['sum']} " \
                                                f"against {want['sum']})"
    else:  # another CPU: other last bits, amplified a little by a few Adam steps
        torch.testing.assert_close(torch.tensor(got["sample"]), torch.tensor(want["sample"]), rtol=1e-3, atol=1e-4)
        torch.testing.assert_close(torch.tensor([got["sum"], got["norm"]]), torch.tensor([want["sum"], want["norm"]]),
                                   rtol=1e-3, atol=1e-3)


if __name__ == "__main__" and "--write" in sys.argv:
    torch.set_num_threads(1)
    reference = {"host": host_fingerprint(), "weights": {name: describe(run()) for name, run in RUNS.items()}}
    REFERENCE.write_text(json.dumps(reference, indent=1))
    print({k: v["shape"] for k, v in reference["weights"].items()})
