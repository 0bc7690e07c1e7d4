"""The teacher bank (issue 56): M controllers with their own weights run as one batch give what each gives alone,
learn apart, and train through the app (``control.teachers``) with exact resume."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import straight_and_resumed
from test_control_run import bodies, tiny_control  # noqa: F401  (the fixture and the tiny run)

from freeform.agents.distill.teachers import TEACHER, TeacherBank, TeacherIndex
from freeform.agents.networks.controller_heads import ControlInputs
from freeform.agents.networks.controllers import CONTROLLERS, ContextConvController
from freeform.agents.ppo.losses import standardize, standardize_groups
from freeform.checkpoint import load_checkpoint
from freeform.config import compose
from freeform.envs.control import OBS_CHANNELS

BOX = (3, 2, 2)
INPUTS = ControlInputs(len(OBS_CHANNELS), BOX, OBS_CHANNELS.index("actuated"))


def observations(n: int, seed: int = 0) -> torch.Tensor:
    """``n`` observations of bodies in BOX: random channels, the filled and actuated cells random (>= 1 filled)."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(n, len(OBS_CHANNELS), *BOX, generator=g)
    filled = (torch.rand(n, *BOX, generator=g) < 0.6).float()
    filled[:, 0, 0, 0] = 1.0
    obs[:, OBS_CHANNELS.index("filled")] = filled
    obs[:, OBS_CHANNELS.index("actuated")] = filled * (torch.rand(n, *BOX, generator=g) < 0.5).float()
    return obs * filled[:, None]


def perturbed_bank(template: torch.nn.Module, teachers: int) -> TeacherBank:
    bank = TeacherBank.from_template(template, teachers)
    with torch.no_grad():
        for p in bank.stacked.values():
            p.add_(0.3 * torch.randn_like(p))
    return bank


@pytest.mark.parametrize("kind", ["context", "attention", "attention_hyper"])
def test_a_teacher_in_the_bank_gives_what_its_weights_give_alone(kind: str) -> None:
    """Batch invariance: 4 teachers with different weights, 13 samples in a shuffled order (teacher 2 has none),
    each sample's outputs equal its teacher's weights run alone on its samples (float rounding apart). The
    hypernetwork's generator is perturbed with the rest, so each sample's head is written by its own body."""
    torch.manual_seed(0)
    cls = CONTROLLERS[kind]
    template = cls(INPUTS, hidden=8, log_std=-1.0)
    bank = perturbed_bank(template, 4)
    teacher = torch.tensor([3, 0, 1, 1, 3, 3, 0, 0, 1, 3, 3, 0, 1])
    obs = observations(len(teacher))
    outs = bank({TEACHER: teacher, "policy": obs})
    assert len(outs) == 4 and outs[0].shape == (13, int(np.prod(BOX)))
    for m in (0, 1, 3):
        alone = bank.member(m)(obs[teacher == m])
        for a, b in zip(outs, alone, strict=True):
            torch.testing.assert_close(a[teacher == m], b, rtol=1e-5, atol=1e-5)
    if kind != "context":  # the bank's fixed token count and written-out attention end with its call
        assert bank.template.token_count is None and not any(b.written_out for b in bank.template.blocks)
    # and the members differ (the check above could not pass by every teacher being one)
    assert not torch.allclose(bank.member(0)(obs)[0], bank.member(1)(obs)[0])


def test_a_teachers_loss_moves_its_own_weights_only() -> None:
    torch.manual_seed(1)
    template = ContextConvController(INPUTS, hidden=4)
    bank = perturbed_bank(template, 3)
    teacher = torch.tensor([0, 1, 2, 1, 0, 2])
    mean, log_std, _, value = bank({TEACHER: teacher, "policy": observations(6)})
    ((mean[teacher == 1] ** 2).sum() + value[teacher == 1].sum()).backward()
    for name, p in bank.stacked.items():
        if p.grad is None:
            continue
        assert p.grad[0].abs().max() == 0 and p.grad[2].abs().max() == 0, name
    assert any(p.grad is not None and p.grad[1].abs().max() > 0 for p in bank.stacked.values())
    assert all(not p.requires_grad for p in bank.template.buffers())
    assert {n for n, _ in bank.named_parameters()} == {f"stacked.{k}" for k in bank.stacked}


def test_the_bank_refuses_an_observation_without_teachers_or_out_of_range() -> None:
    template = ContextConvController(INPUTS, hidden=4)
    bank = TeacherBank.from_template(template, 2)
    with pytest.raises(ValueError, match="teacher"):
        bank(observations(2))
    with pytest.raises(ValueError, match=r"0 … 1"):
        bank({TEACHER: torch.tensor([0, 2]), "policy": observations(2)})


def test_standardize_groups_is_standardize_within_each_group() -> None:
    g = torch.Generator().manual_seed(0)
    x = torch.randn(5, 6, generator=g) * torch.tensor([1.0, 10.0, 1.0, 10.0, 100.0, 100.0])
    groups = torch.tensor([0, 1, 0, 1, 2, 2])
    out = standardize_groups(x, groups)
    for k in range(3):
        cols = (groups == k).nonzero().flatten()
        torch.testing.assert_close(out[:, cols].reshape(-1), standardize(x[:, cols].reshape(-1)))


class _Counter:
    """A two-environment VecEnv whose observation is the step count (and the last episode's at its end)."""

    num_envs, observation_shape, action_dim, device = 2, (1,), 1, torch.device("cpu")

    def reset(self, seed: int | None = None) -> torch.Tensor:
        self.t = 0
        return torch.zeros(2, 1)

    def step(self, actions: torch.Tensor):  # noqa: ANN201
        self.t += 1
        done = torch.full((2,), self.t % 2 == 0)
        return torch.full((2, 1), float(self.t)), torch.ones(2), done, {"final_obs": torch.full((2, 1), -1.0)}


def test_teacher_index_adds_the_group_to_observations_and_final_observations() -> None:
    env = TeacherIndex(_Counter(), torch.tensor([1, 0]))
    assert env.observation_shape == {TEACHER: (), "policy": (1,)} and env.reward_groups.tolist() == [1, 0]
    obs = env.reset()
    assert obs[TEACHER].tolist() == [1, 0] and obs["policy"].shape == (2, 1)
    obs, _, _, info = env.step(torch.zeros(2, 1))
    assert info["final_obs"][TEACHER].tolist() == [1, 0] and info["final_obs"]["policy"].tolist() == [[-1.0]] * 2
    with pytest.raises(ValueError, match="one teacher per environment"):
        TeacherIndex(_Counter(), torch.tensor([0, 1, 2]))


def test_the_app_trains_a_bank_of_teachers_and_resumes_it_bit_for_bit(bodies: Path, tmp_path: Path) -> None:  # noqa: F811
    """control.teachers=2 on the two tiny bodies (4 environments: body i mod 2, two copies each, leave-one-out
    baseline, advantages standardised per body): two epochs equal one plus a resumed one; the checkpoint names the
    bank, and the two teachers, started alike, have learnt apart."""
    overrides = ("control.teachers=2", "control.controller=context", "seed=2", "agent.group_baseline=true",
                 "agent.advantage_norm=group", "control.headings=any")
    straight_and_resumed(compose(*tiny_control(bodies, *overrides)), tmp_path, epochs=2)
    a = load_checkpoint(tmp_path / "straight" / "checkpoints" / "last.pt")
    b = load_checkpoint(tmp_path / "split" / "checkpoints" / "last.pt")
    assert a["policy_class"].endswith(":TeacherBank") and a["policy_kwargs"]["teachers"] == 2
    for key, tensor in a["ppo"]["policy"].items():
        assert torch.equal(tensor, b["ppo"]["policy"][key]), key
    actor = a["ppo"]["policy"]["stacked.actor__weight"]
    assert not torch.equal(actor[0], actor[1])


def test_a_banks_copies_of_a_body_share_its_heading(bodies: Path) -> None:  # noqa: F811
    """Steering (control_steering_cpu: random headings) with a bank of 2 teachers on 4 environments, built as the app
    builds it on two ranks' halves: environments 0 and 2 drive body 0 and walk one heading, 1 and 3 another, so the
    leave-one-out baseline among a body's copies compares what the noise did along one heading."""
    from freeform.run.build import control_env

    cfg = compose(*tiny_control(bodies, "control.teachers=2"))
    env = control_env(cfg, torch.device("cpu"), (0, 4), seed=0)
    env.reset()
    heading = env.env.heading
    assert heading[0] == heading[2] and heading[1] == heading[3] and heading[0] != heading[1]
    halves = [control_env(cfg, torch.device("cpu"), envs, seed=0) for envs in ((0, 2), (2, 4))]
    for half in halves:
        half.reset()
    assert np.array_equal(np.concatenate([h.env.heading for h in halves]), heading)  # (any split into ranks)
    evaluation = control_env(cfg, torch.device("cpu"), (0, 4), seed=0, shared_headings=False)
    evaluation.reset()  # (an evaluation's episodes: each environment its own draw, as before banks shared them)
    assert len(set(evaluation.env.heading.tolist())) == 4


@pytest.mark.parametrize("override, message", [
    ("control.teachers=3", "env.num_envs"),
    ("control.bodies=population", "control.teachers"),
])
def test_a_bad_bank_is_refused_naming_the_key(bodies: Path, override: str, message: str) -> None:  # noqa: F811
    with pytest.raises(ValueError, match=message):
        compose(*tiny_control(bodies, "control.teachers=2", override))


def test_a_bank_of_controllers_with_a_privileged_critic_reads_both_groups() -> None:
    """Teachers may read privileged observations: a bank of PrivilegedCritics (an 8-wide critic MLP, kept) gives
    each sample its teacher's value from the "policy" and "critic" groups, as the member alone does."""
    from freeform.agents.networks.controllers import PrivilegedCritic

    torch.manual_seed(3)
    template = PrivilegedCritic("context", ContextConvController(INPUTS, hidden=4).init_kwargs, critic_dim=5, hidden=8)
    bank = perturbed_bank(template, 2)
    assert bank.member(0).critic_head[0].out_features == 8
    teacher = torch.tensor([1, 0, 1])
    obs = {"policy": observations(3), "critic": torch.randn(3, 5)}
    outs = bank({TEACHER: teacher, **obs})
    for m in (0, 1):
        alone = bank.member(m)({k: v[teacher == m] for k, v in obs.items()})
        torch.testing.assert_close(outs[-1][teacher == m], alone[-1], rtol=1e-5, atol=1e-5)


EVALUATED = ("control.teachers=2", "control.controller=context", "seed=3", "agent.group_baseline=true",
             "agent.advantage_norm=group", "agent.eval_every=1", "agent.eval_episodes=4",
             "agent.eval_same_episodes=true", "trainer.plateau_on=eval_return", "trainer.plateau_window=1",
             "trainer.epochs=6")
"""A steering bank (random headings) evaluated every epoch along the same 4 headings, stopped by that curve."""


def test_a_steering_bank_stops_on_its_evaluated_curve_which_is_each_bodys_own_controller(bodies: Path,  # noqa: F811
                                                                                       tmp_path: Path) -> None:
    """``trainer.plateau_on=eval_return``. With a learning rate of 1e-12 the teachers do not move: the evaluated
    curve is flat and the run stops after two evaluations (epoch 2 of 6), though by its noisy training return it
    would have gone on (checked for this seed); one epoch and a resume stop there too (the first point comes back
    from the checkpoint). Each evaluated point is each body's own teacher, by its mean command, along the
    evaluation's draws (body b's copy c draws c·M + b, seed + 1): ``own_moves`` of the epoch's checkpoint on a fresh
    env, a path that shares nothing with PPO's evaluation but the env."""
    from freeform.agents.distill import bank_from_checkpoint
    from freeform.checkpoint import numbered_name
    from freeform.control.evaluate import episode_draws
    from freeform.control.play import own_moves
    from freeform.envs.control import ControlEnv
    from freeform.run.trainer import plateaued
    from freeform.train import train

    cfg = compose(*tiny_control(bodies, *EVALUATED, "agent.lr=1e-12"))
    result = train(cfg, tmp_path / "flat")
    saved = load_checkpoint(tmp_path / "flat" / "checkpoints" / "last.pt")
    assert (result.epochs, result.converged) == (2, 2) and [e for e, _ in saved["eval_curve"]] == [1, 2]
    assert not plateaued(saved["return_curve"], 1, cfg.trainer.plateau_gain)  # (the training return rose > 2 %)
    first = compose(*tiny_control(bodies, *EVALUATED, "agent.lr=1e-12", "trainer.epochs=1"))
    train(first, tmp_path / "split")
    assert (train(cfg, tmp_path / "split").epochs, load_checkpoint(tmp_path / "split" / "checkpoints" / "last.pt")[
        "eval_curve"]) == (2, saved["eval_curve"])
    grids = torch.from_numpy(np.load(bodies)).to(torch.uint8)
    for epoch, value in saved["eval_curve"]:
        bank = bank_from_checkpoint(load_checkpoint(tmp_path / "flat" / "checkpoints" / numbered_name(epoch)), "")
        env = ControlEnv(grids.repeat_interleave(2, 0), sim=cfg.sim, control=cfg.control.episode(), seed=cfg.seed + 1,
                         first_env=episode_draws(2, 2))
        assert value == pytest.approx(float(own_moves(bank, env, episodes=2).mean()), rel=1e-6)


def test_an_evaluation_changes_no_training_and_a_run_may_take_one_up_when_resumed(bodies: Path,  # noqa: F811
                                                                                   tmp_path: Path) -> None:
    """The same bank trained 2 epochs with and without its evaluation: the same weights, to the bit (the evaluation
    draws from none of the training's generators). So a resumed run may start one (``REPORTING_KEYS``): the run
    without it, continued for a third epoch with it, evaluates epoch 3. Named on the command line, any of the
    evaluation's keys or ``trainer.plateau_on`` brings all three of the current config (a rule taken up on resume
    reads the preset's evaluation); any other key is still refused."""
    from freeform.run.resume import resume_config
    from freeform.train import train

    evaluated = compose(*tiny_control(bodies, *EVALUATED, "trainer.plateau_window=0", "trainer.epochs=2"))
    plain = compose(*tiny_control(bodies, *EVALUATED[:5], "trainer.epochs=2"))
    train(evaluated, tmp_path / "evaluated")
    train(plain, tmp_path / "plain")
    a, b = (load_checkpoint(tmp_path / run / "checkpoints" / "last.pt") for run in ("evaluated", "plain"))
    assert len(a["eval_curve"]) == 2 and b["eval_curve"] == []
    for key, tensor in a["ppo"]["policy"].items():
        assert torch.equal(tensor, b["ppo"]["policy"][key]), key
    later = compose(*tiny_control(bodies, *EVALUATED, "trainer.epochs=3", "trainer.plateau_window=0"))
    assert resume_config(plain, later, ["agent.eval_every=1", "trainer.epochs=3"]).agent.eval_every == 1
    taken = resume_config(plain, later, ["trainer.plateau_on=eval_return", "trainer.plateau_window=2"])
    assert (taken.agent.eval_every, taken.agent.eval_episodes, taken.agent.eval_same_episodes) == (1, 4, True)
    assert resume_config(plain, later, ["trainer.epochs=3"]).agent.eval_every == 0  # (not named: the checkpoint's)
    with pytest.raises(ValueError, match="agent.lr: cannot change"):
        resume_config(plain, compose(*tiny_control(bodies, *EVALUATED[:5], "agent.lr=1e-2")), ["agent.lr=1e-2"])
    train(later, tmp_path / "plain")  # (Python's resume: the current config's trainer and evaluation)
    assert [e for e, _ in load_checkpoint(tmp_path / "plain" / "checkpoints" / "last.pt")["eval_curve"]] == [3]
