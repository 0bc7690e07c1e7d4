"""Teachers regularised towards a student (``control.prior``, freeform/agents/distill/prior.py): the reward gains the
prior's log-likelihood per acting entry, against scipy's normal density; the return logged is the task's; a teacher run
with a prior resumes bit for bit; bad settings are refused naming the field."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import straight_and_resumed
from scipy import stats
from test_control_run import ROD, bodies, tiny_control  # noqa: F401  (the fixture and the tiny run)

from freeform.agents.distill.prior import PriorReward
from freeform.agents.networks.controllers import build_controller
from freeform.checkpoint import load_checkpoint
from freeform.config import compose
from freeform.envs.control import ControlConfig, ControlEnv
from freeform.sim import SimConfig


def test_the_reward_gains_the_priors_log_density_per_acting_entry() -> None:
    grids = np.stack([ROD, np.pad(ROD[:2], ((0, 1), (0, 0), (0, 0)))])  # (3 voxels, 2 acting; 2 voxels, 1 acting)
    control = ControlConfig(burn_in=0.0, duration=0.05, residual=True)
    plain, env = (ControlEnv(grids, sim=SimConfig(precision="f64"), control=control) for _ in range(2))
    torch.manual_seed(0)
    prior = build_controller("context", env, 4, log_std=-0.7)
    wrapped = PriorReward(env, prior, coeff=0.3)
    obs, _ = wrapped.reset(), plain.reset()
    task = torch.zeros(2)
    for _ in range(env.control.steps):
        actions = torch.randn(2, env.action_dim)
        with torch.no_grad():
            mean, log_std, mask, _ = prior(obs)
        want = []
        for n in range(2):  # scipy's normal density over the entries that act, averaged
            acting = mask[n].bool()
            want.append(stats.norm.logpdf(actions[n][acting].numpy(), mean[n][acting].numpy(),
                                          np.exp(log_std[n][acting].numpy())).mean())
        obs, reward, _, info = wrapped.step(actions)
        _, own, done, _ = plain.step(actions)
        task += own
        # the return logged stays the task's: the env's own rewards, summed at the episode's end
        torch.testing.assert_close(info["task_reward"], task if done.all() else torch.zeros(2))
        np.testing.assert_allclose((reward - own).numpy(), 0.3 * np.array(want), rtol=1e-5, atol=1e-6)
        assert mask.sum(-1).tolist() == [2.0, 1.0]
    with pytest.raises(ValueError, match=r"control.prior_coeff must be > 0"):
        PriorReward(env, prior, coeff=0.0)


def test_a_teacher_run_with_a_prior_resumes_bit_for_bit(bodies: Path, tmp_path: Path) -> None:  # noqa: F811
    """A tiny control run is the prior of a two-teacher bank: two epochs straight equal one plus a resumed one (the
    restored env's observation is what the prior reads); a missing prior, one that reads other channels and a
    weight <= 0 are refused, naming the field."""
    from freeform.run.build import build
    from freeform.train import train

    student = ("control.controller=context", "control.headings=any", "seed=4")
    train(compose(*tiny_control(bodies, *student, "trainer.epochs=1")), tmp_path / "student")
    teach = (*student, "control.teachers=2", "agent.advantage_norm=group",
             f"control.prior={tmp_path / 'student'}", "control.prior_coeff=0.5")
    straight, split = straight_and_resumed(compose(*tiny_control(bodies, *teach)), tmp_path, epochs=2)
    a = load_checkpoint(straight / "checkpoints" / "last.pt")
    b = load_checkpoint(split / "checkpoints" / "last.pt")
    for key, tensor in a["ppo"]["policy"].items():
        assert torch.equal(tensor, b["ppo"]["policy"][key]), key
    _, learner = build(compose(*tiny_control(bodies, *teach)), torch.device("cpu"))
    assert isinstance(learner.env, PriorReward) and learner.env.coeff == 0.5
    with pytest.raises(ValueError, match=r"control.prior='nowhere': no such checkpoint, controller.pt"):
        build(compose(*tiny_control(bodies, *student, "control.prior=nowhere")), torch.device("cpu"))
    with pytest.raises(ValueError, match=r"control.prior='.*' reads 16 observation channels and this run's env "
                                         r"gives 17"):
        build(compose(*tiny_control(bodies, *teach, "control.residual=true")), torch.device("cpu"))
    with pytest.raises(ValueError, match=r"control.prior_coeff"):
        compose(*tiny_control(bodies, *teach, "control.prior_coeff=-1"))
