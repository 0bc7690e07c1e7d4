"""Distillation (``algo=distill``, ``freeform.agents.distill``): DAgger's labels are the teacher's on the
observations the student visited, a student learns its teacher's skill on a Gymnasium task, and the app's run
resumes bit for bit."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch
from helpers import straight_and_resumed
from test_control_run import bodies, tiny_control  # noqa: F401  (the fixture and the tiny run)

from freeform.agents import MLPActorCritic
from freeform.agents.distill import Distillation, DistillConfig, distill_loss
from freeform.agents.ppo import PPOConfig
from freeform.checkpoint import load_checkpoint
from freeform.config import compose
from freeform.distributions import Categorical, DiagGaussian
from freeform.envs import from_gymnasium


def balancer(obs: torch.Tensor, envs: torch.Tensor) -> tuple[torch.Tensor, None]:
    """CartPole's textbook rule as a near-deterministic categorical teacher: push towards where the pole falls
    (θ + 0.5·θ'); environment i's logits scaled by 1 + i (a teacher per index, all of them the same rule)."""
    s = (obs[:, 2] + 0.5 * obs[:, 3]) * 20.0 * (1.0 + envs.float())
    return torch.stack([-s, s], 1), None


def cartpoles(n: int) -> object:
    return from_gymnasium(gym.vector.SyncVectorEnv([lambda: gym.make("CartPole-v1")] * n), seed=0)


def test_the_labels_are_the_teachers_on_the_visited_observations() -> None:
    """After a round, every sample of the dataset is an observation the env returned during the rollout and its
    label is the teacher's distribution on it, for that sample's environment (the teacher differs per index)."""
    torch.manual_seed(0)
    env = cartpoles(4)
    student = MLPActorCritic.for_env(env, hidden=(16,))
    learner = Distillation(env, student, balancer, PPOConfig(rollout_steps=8, num_sgd_iter=1, sgd_minibatch_size=16),
                           DistillConfig(beta=0.5, buffer=2))
    learner.train_epoch()
    obs, labels, value = learner.dataset["obs"], learner.dataset["params"], learner.dataset["value"]
    assert obs.shape == (4, 8, 4) and labels[0].shape == (4, 8, 2) and torch.isnan(value).all()
    torch.testing.assert_close(obs.transpose(0, 1), learner.rollout.obs)  # the visited observations, in order
    for n in range(4):
        expected, _ = balancer(obs[n], torch.full((8,), n))
        torch.testing.assert_close(labels[0][n], expected)
    learner.train_epoch()
    learner.train_epoch()  # three rounds, two kept
    assert learner.dataset["obs"].shape == (4, 16, 4)
    torch.testing.assert_close(learner.dataset["obs"][:, 8:].transpose(0, 1), learner.rollout.obs)


class Recorded:
    """A VecEnv wrapper that keeps every action it is given (``[N]`` a step)."""

    def __init__(self, env: Any) -> None:
        self.env, self.given = env, []

    def __getattr__(self, name: str) -> Any:
        if name == "env":
            raise AttributeError(name)
        return getattr(self.env, name)

    def step(self, actions: torch.Tensor) -> Any:
        self.given.append(actions.clone())
        return self.env.step(actions)


@pytest.mark.parametrize("beta", [1.0, 0.0])
def test_with_beta_one_every_step_plays_the_teachers_action_and_with_zero_none(beta: float) -> None:
    """DAgger's mixture: at β = 1 every environment's every step is the teacher's mode on what it observed (the
    student's own sample never reaches the env), at β = 0 none is — the student samples, which the teacher's
    near-deterministic rule disagrees with on some steps."""
    torch.manual_seed(0)
    env = Recorded(cartpoles(4))
    student = MLPActorCritic.for_env(env, hidden=(8,))
    learner = Distillation(env, student, balancer, PPOConfig(rollout_steps=16, num_sgd_iter=1, sgd_minibatch_size=16),
                           DistillConfig(beta=beta, buffer=1))
    stats = learner.train_epoch()
    given = torch.stack(env.given).reshape(16, 4)  # [T, N]
    seen = learner.rollout.obs  # [T, N, 4]: what each step acted on
    teacher = torch.stack([balancer(seen[t], torch.arange(4))[0].argmax(1) for t in range(16)])
    if beta == 1.0:
        assert torch.equal(given.long(), teacher) and stats["teacher_steps"] == 1.0
    else:
        assert torch.equal(given.long(), learner.rollout.actions.reshape(16, 4).long()) and not torch.equal(given.long(), teacher)
        assert stats["teacher_steps"] == 0.0


def test_a_student_learns_to_balance_the_pole_from_its_teacher() -> None:
    """The teacher balances CartPole for the whole 500 steps; a fresh student gets near nothing (~20 steps). After
    eight DAgger rounds (β from 1 halving) the student alone, acting on its mode, balances >= 400 steps."""
    torch.manual_seed(0)
    env = cartpoles(8)
    student = MLPActorCritic.for_env(env, hidden=(32,))
    learner = Distillation(env, student, balancer,
                           PPOConfig(rollout_steps=64, num_sgd_iter=8, sgd_minibatch_size=128, lr=3e-3),
                           DistillConfig(loss="kl", beta=1.0, beta_decay=0.5, buffer=8))
    before = learner.evaluate(cartpoles(4), episodes=4)["eval_return"]
    stats = [learner.train_epoch() for _ in range(8)]
    after = learner.evaluate(cartpoles(4), episodes=4)["eval_return"]
    assert before < 100 and after >= 400, (before, after)
    assert stats[-1]["distill_kl"] < 0.2 * stats[0]["distill_kl"]
    assert stats[0]["teacher_steps"] == pytest.approx(1.0) and stats[-1]["teacher_steps"] < 0.05


def blind_cartpoles(n: int) -> object:
    """CartPole whose policy sees the cart's and the pole's positions alone; the velocities are the ``"critic"``
    group (``HideEntries``): the privileged teacher's."""
    from freeform.envs.partial import HideEntries

    return from_gymnasium(gym.vector.SyncVectorEnv(
        [lambda: HideEntries(gym.make("CartPole-v1"), [1, 3], critic=True)] * n), seed=0, dict_obs=True)


def privileged_balancer(obs: dict[str, torch.Tensor], envs: torch.Tensor) -> tuple[torch.Tensor, None]:
    """:func:`balancer` reading the pole's angle from ``"policy"`` and its angular velocity from ``"critic"``."""
    s = (obs["policy"][:, 1] + 0.5 * obs["critic"][:, 1]) * 20.0
    return torch.stack([-s, s], 1), None


@pytest.mark.slow
def test_a_recurrent_student_learns_what_only_its_privileged_teacher_sees() -> None:
    """The teacher reads the pole's angular velocity, the students its angle alone. Distilled alike (6 rounds), a
    feed-forward student cannot tell which way the pole swings and drops it (< 100 steps); a GRU student, trained
    over sequences of 16 steps, infers the swing from the angles it saw and balances several times longer. How much
    longer varies with the seed (500, 478, 154, 389 steps for seeds 0-3, the feed-forward one 41-53), and this run's
    figure has moved with what ran before it in the worker (308), so the bar is relative: >= 2.5x the feed-forward
    student's, and >= 120 steps."""
    from freeform.agents.networks.recurrent import RecurrentActorCritic

    returns = {}
    for kind in ("feed-forward", "gru"):
        torch.manual_seed(0)
        env = blind_cartpoles(8)
        student = (RecurrentActorCritic.for_env(env, hidden=(32,), rnn="gru", rnn_hidden=32) if kind == "gru"
                   else MLPActorCritic.for_env(env, hidden=(32,)))
        learner = Distillation(env, student, privileged_balancer,
                               PPOConfig(rollout_steps=64, num_sgd_iter=8, sgd_minibatch_size=128, lr=1e-2,
                                         sequence_length=16),
                               DistillConfig(loss="kl", beta=1.0, beta_decay=0.5, buffer=8))
        for _ in range(6):
            learner.train_epoch()
        returns[kind] = learner.evaluate(blind_cartpoles(4), episodes=4)["eval_return"]
    assert returns["feed-forward"] < 100 and returns["gru"] >= max(120.0, 2.5 * returns["feed-forward"]), returns


def test_a_recurrent_students_sequences_carry_its_memory_across_chunks() -> None:
    """The dataset starts mid-episode (3 rounds, 2 kept): the steps before an env's first episode start there do
    not count (the student's memory of them is unknown), and the rest do. Cut into chunks of 5 steps, each run
    from the state the student reaches over the chunks before it, the regression's loss is the one of each env's
    16 steps run as one sequence."""
    from freeform.agents.networks.recurrent import RecurrentActorCritic

    torch.manual_seed(0)
    env = blind_cartpoles(4)
    student = RecurrentActorCritic.for_env(env, hidden=(8,), rnn="lstm", rnn_hidden=8)
    learner = Distillation(env, student, privileged_balancer,
                           PPOConfig(rollout_steps=8, num_sgd_iter=1, sgd_minibatch_size=16, sequence_length=5),
                           DistillConfig(beta=0.5, buffer=2))
    for _ in range(3):
        learner.train_epoch()
    starts, valid = learner.dataset["starts"], learner.dataset["valid"]
    assert starts.shape == valid.shape == (4, 16)
    first = torch.where(starts.any(1), starts.float().argmax(1), 16)  # (16: no start in the dataset, none counts)
    expected = (torch.arange(16)[None] >= first[:, None]) & valid
    assert bool((first > 0).any()) and bool((first < 16).any()), first  # begun mid-episode; an episode begins
    with torch.no_grad():  # (a fresh head commands ≈ 0 whatever it remembers: made loud, so that memory shows)
        student.actor[-1].weight.mul_(300.0)

    def loss(length: int) -> torch.Tensor:
        learner.config.sequence_length = length
        seq = learner._sequences()
        sequences = seq.mask.shape[1]
        total, _ = learner._sequence_loss(seq, torch.arange(sequences), torch.zeros(seq.mask.numel(), dtype=torch.long),
                                          seq.counted.sum())
        return seq, total

    whole, one = loss(16)
    torch.testing.assert_close(whole.mask.T, expected)
    chunked, five = loss(5)
    assert chunked.mask.shape == (5, 4 * 4) and int(chunked.mask.sum()) == int(expected.sum())
    torch.testing.assert_close(five, one)


def test_the_loss_is_kl_or_the_means_squared_error() -> None:
    """By hand: one sample, a 2-D Gaussian; KL(N(0, 1) ‖ N(1, e)) per entry = log σ1 − log σ0 + (σ0² + Δ²)/(2σ1²)
    − 1/2; mse the means' squared error averaged over the entries; the value's squared error."""
    dist = DiagGaussian(2)
    teacher = (torch.zeros(1, 2), torch.zeros(1, 2))
    student = (torch.ones(1, 2), torch.ones(1, 2), torch.tensor([3.0]))
    kl_entry = 1.0 + (1.0 + 1.0) / (2 * np.e ** 2) - 0.5
    loss, stats = distill_loss(student, teacher, torch.tensor([1.0]), dist, "kl", 0.5)
    torch.testing.assert_close(stats, torch.tensor([2 * kl_entry, 2 * kl_entry, 1.0, 4.0]))
    torch.testing.assert_close(loss, torch.tensor(2 * kl_entry + 2.0))
    loss, stats = distill_loss(student, teacher, torch.tensor([float("nan")]), dist, "mse", 0.5)
    torch.testing.assert_close(loss, torch.tensor(1.0))
    with pytest.raises(ValueError, match="algo.loss=kl"):
        Distillation(cartpoles(2), MLPActorCritic.for_env(cartpoles(2)), balancer, PPOConfig(),
                     DistillConfig(loss="mse"))
    assert isinstance(MLPActorCritic.for_env(cartpoles(2)).distribution, Categorical)


TEACH = ("control.teachers=2", "control.controller=context", "agent.group_baseline=true", "control.headings=any",
         "agent.advantage_norm=group", "seed=4")
"""A tiny teacher run's overrides (two context teachers, each body's own baseline and advantages)."""


def distilled_straight_and_resumed(body_file: Path, tmp_path: Path, *student: str) -> tuple[Any, dict]:
    """Teachers trained one epoch through the app (:data:`TEACH`), then algo=distill from them (β 0.5, samples turned
    by the ground's symmetries) with ``student``'s overrides: two rounds straight and one plus a resumed one. Asserts
    the students and the aggregated datasets equal to the bit; returns the distillation's config and the straight
    run's checkpoint."""
    from freeform.train import train

    train(compose(*tiny_control(body_file, *TEACH, "trainer.epochs=1")), tmp_path / "teachers")
    distill = compose(*tiny_control(body_file, *TEACH, "algo=distill", f"algo.teacher={tmp_path / 'teachers'}",
                                    "algo.beta=0.5", "agent.num_sgd_iter=2", "algo.symmetry=ground", *student))
    straight_and_resumed(distill, tmp_path, epochs=2)
    a = load_checkpoint(tmp_path / "straight" / "checkpoints" / "last.pt")
    b = load_checkpoint(tmp_path / "split" / "checkpoints" / "last.pt")
    for key, tensor in a["ppo"]["policy"].items():
        assert torch.equal(tensor, b["ppo"]["policy"][key]), key
    for key, tensor in a["ppo"]["distill"]["per_env"].items():
        assert torch.equal(tensor, b["ppo"]["distill"]["per_env"][key]), key
    return distill, a


def test_a_distillation_run_of_the_app_resumes_bit_for_bit(bodies: Path, tmp_path: Path,  # noqa: F811
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """A teacher bank trained one epoch through the app, then algo=distill from it (each sample turned by the
    ground's symmetries: their draws resume too): two rounds straight equal one plus a resumed one (the student,
    the optimiser, the aggregated dataset — written packed, as a large run's is)."""
    from freeform import checkpoint

    monkeypatch.setattr(checkpoint, "PACK_MIN_ELEMENTS", 1024)  # (this tiny run's dataset packed like a large one's)

    distill, a = distilled_straight_and_resumed(bodies, tmp_path)
    assert a["policy_class"].endswith(":ContextConvController")
    assert a["ppo"]["distill"]["per_env"]["obs"].shape[:2] == (4, 8)  # 4 envs, 2 rounds of 4 steps
    raw = torch.load(tmp_path / "split" / "checkpoints" / "last.pt", weights_only=True)
    assert checkpoint.PACKED in raw["ppo"]["distill"]["per_env"]["obs"]
    # the optional PPO fine-tune starts from the student's weights (control.controller_init=<the distill run>)
    from freeform.run.build import build

    fine = compose(*tiny_control(bodies, "control.controller=context", "control.headings=any", "seed=4",
                                 f"control.controller_init={tmp_path / 'straight'}"))
    _, ppo = build(fine, torch.device("cpu"))
    assert all(torch.equal(v, a["ppo"]["policy"][k]) for k, v in ppo.policy.state_dict().items())
    # teachers re-started from the student (distillation's next round, as divide-and-conquer RL does): each
    # teacher of the new bank holds the student's weights
    again = compose(*tiny_control(bodies, *TEACH, f"control.controller_init={tmp_path / 'straight'}"))
    _, learner = build(again, torch.device("cpu"))
    for m in range(2):
        member = learner.policy.member_state(m)
        assert all(torch.equal(v, a["ppo"]["policy"][k]) for k, v in member.items())
    # a run whose episode differs from the teachers' is refused, naming the field and both values
    other = compose(*tiny_control(bodies, *TEACH, "algo=distill", f"algo.teacher={tmp_path / 'teachers'}",
                                  "control.duration=0.025"))
    with pytest.raises(ValueError, match=r"control\.duration: 0\.05 in the teacher run, 0\.025 here"):
        build(other, torch.device("cpu"))
    # ... and one of another simulator, naming the physics field; how it runs (the schedule) may differ
    lighter = compose(*tiny_control(bodies, *TEACH, "algo=distill", f"algo.teacher={tmp_path / 'teachers'}",
                                    "sim.gravity=-5.0", "sim.schedule=robots"))
    with pytest.raises(ValueError, match=r"its teachers were trained in another simulator than this run's: "
                                         r"sim\.gravity: -9\.81 in the teacher run, -5\.0 here \(give") as refused:
        build(lighter, torch.device("cpu"))
    assert "schedule" not in str(refused.value)
    # a turned body sits elsewhere in its padded box: a student that the padding changes is refused
    conv = compose(*tiny_control(bodies, *TEACH, "algo=distill", f"algo.teacher={tmp_path / 'teachers'}",
                                 "algo.symmetry=ground", "control.controller=conv"))
    with pytest.raises(ValueError, match=r"control.controller is 'conv'"):
        build(conv, torch.device("cpu"))
    from freeform.agents.networks.group_average import check_turnable

    def kinds(student: str, teacher: str) -> dict[str, str]:
        return {"control.controller": student, "the teacher run's controller": teacher}

    # a teacher run with fixed headings: the same rule
    with pytest.raises(ValueError, match=r"headings=fixed rewards \+x alone: use algo.symmetry=mirror"):
        check_turnable("algo.symmetry", "ground", "fixed", "world", kinds("context", "context"))
    check_turnable("algo.symmetry", "mirror", "fixed", "world", kinds("context", "attention"))
    with pytest.raises(ValueError, match=r"control.frame=heading every task is \+x"):  # (steering, turned to +x)
        check_turnable("algo.symmetry", "ground", "random", "heading", kinds("attention", "attention"))
    check_turnable("algo.symmetry", "mirror", "random", "heading", kinds("attention", "attention"))
    check_turnable("algo.symmetry", "ground", "any", "heading", kinds("attention", "attention"))  # (no heading)
    with pytest.raises(ValueError, match=r"algo.symmetry must be one of \['none', 'ground', 'mirror'\]"):
        compose(*tiny_control(bodies, *TEACH, "algo=distill", "algo.teacher=x", "algo.symmetry=turns"))
    # a student may sense more than its teachers did (control.response): they label what they read before it
    seeing = compose(*tiny_control(bodies, *TEACH, "algo=distill", f"algo.teacher={tmp_path / 'teachers'}",
                                   "control.response=true"))
    _, student = build(seeing, torch.device("cpu"))
    obs, envs = student.env.reset(), torch.arange(4)
    assert obs.shape[1] == student.teacher.bank.init_kwargs["controller"]["channels"] + 6
    from freeform.run.build import read_teacher_run

    bank = read_teacher_run(tmp_path / "teachers", "the teachers").bank.eval()
    for a, b in zip(student.teacher(obs, envs), bank({"teacher": envs % 2, "policy": obs[:, :-6]}), strict=True):
        torch.testing.assert_close(a, b)
    np.save(bodies, np.load(bodies)[::-1].copy())  # the same control.bodies, other grids: refused, naming them
    with pytest.raises(ValueError, match=r"its bodies are not this run's \(bodies \[0, 1\] differ"):
        build(distill, torch.device("cpu"))


def test_token_dropout_hides_voxels_from_the_student_and_resumes_bit_for_bit(bodies: Path,  # noqa: F811
                                                                             tmp_path: Path,
                                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """algo.token_dropout into an attention student: two rounds straight equal one plus a resumed one (its draws
    come from the shared generator, as the symmetry's); every regression forward hides about that fraction of its
    samples' cells and no forward outside it (acting, labelling: without gradients) hides any; a student without
    voxel tokens, a recurrent one and a probability out of [0, 1) are refused, naming the field."""
    from freeform.agents.networks.attention_controllers import VoxelAttentionController
    from freeform.run.build import build

    hidden: list[float] = []
    hiding = VoxelAttentionController.hiding

    def recorded(self: VoxelAttentionController, cells: torch.Tensor) -> Any:
        hidden.append(float(cells.float().mean()))
        return hiding(self, cells)

    monkeypatch.setattr(VoxelAttentionController, "hiding", recorded)
    forwards = []
    forward = VoxelAttentionController.forward
    monkeypatch.setattr(VoxelAttentionController, "forward",
                        lambda self, obs: forwards.append((self.hidden_cells is not None, torch.is_grad_enabled()))
                        or forward(self, obs))
    distill, a = distilled_straight_and_resumed(bodies, tmp_path, "control.controller=attention",
                                                "algo.token_dropout=0.5")
    assert a["policy_class"].endswith(":VoxelAttentionController") and distill.algo.token_dropout == 0.5
    hides = [h for h, _ in forwards]
    assert len(hidden) == sum(hides) > 0 and 0.45 < np.mean(hidden) < 0.55  # (the regression's forwards)
    assert sum(not g for _, g in forwards) > 0 and all(h == g for h, g in forwards)  # (acting, labelling: none)
    for student, why in (("control.controller=context", "has no tokens to hide"),
                         ("control.controller=attention_gru", "is recurrent")):
        refused = compose(*tiny_control(bodies, *TEACH, "algo=distill", f"algo.teacher={tmp_path / 'teachers'}",
                                        "algo.token_dropout=0.2", student))
        with pytest.raises(ValueError, match=rf"algo.token_dropout hides voxels .* {why}"):
            build(refused, torch.device("cpu"))
    with pytest.raises(ValueError, match=r"algo.token_dropout must be a probability in \[0, 1\)"):  # (composing)
        compose(*tiny_control(bodies, *TEACH, "algo=distill", "algo.teacher=x", "algo.token_dropout=1.0"))


def test_a_recurrent_students_distillation_run_resumes_bit_for_bit(bodies: Path, tmp_path: Path) -> None:  # noqa: F811
    """algo=distill into an attention_gru student (chunks of 3 steps in episodes of 4, so chunks begin mid-episode;
    samples turned by the ground's symmetries, a chunk as one; the first epoch's gait rendered, the student driving
    its body): two rounds straight equal one plus a resumed one — the student, and the dataset with its episode
    starts."""
    _, a = distilled_straight_and_resumed(bodies, tmp_path, "control.controller=attention_gru",
                                          "agent.sequence_length=3",
                                          "trainer.render_every=2")  # (epoch 0's gait render: the student drives)
    assert a["policy_class"].endswith(":RecurrentAttentionController")
    data = a["ppo"]["distill"]["per_env"]
    assert data["starts"].shape == (4, 8) and data["starts"][:, ::4].all() and not data["starts"][:, 1::4].any()


def test_a_selection_teaches_each_body_by_its_chosen_controller(bodies: Path, tmp_path: Path) -> None:  # noqa: F811
    """algo.teacher may name an ``lab.selection --try`` folder: environment i is labelled by the controller
    chosen for its body (i mod M), its outputs on that observation exactly; a round of DAgger runs on it. A run of
    another episode or simulator, other bodies or a recurrent controller among those tried is refused, naming the
    problem."""
    import csv

    from freeform.agents.controller_file import read_controller, save_controller
    from freeform.agents.networks.controllers import ContextConvController
    from freeform.run.build import build
    from lab.selection import try_controllers

    run = compose(*tiny_control(bodies, *TEACH, "algo=distill", f"algo.teacher={tmp_path / 'chosen'}"))
    plain = compose(*tiny_control(bodies, *TEACH))
    env, _ = build(plain, torch.device("cpu"))
    files = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        net = ContextConvController.for_env(env.env, hidden=4)
        files.append(save_controller(tmp_path / f"c{seed}" / "controller.pt", net, plain.control, plain.sim))
    try_controllers(files, bodies, tmp_path / "chosen")
    table = tmp_path / "chosen" / "bodies.csv"
    rows = list(csv.DictReader(open(table)))
    rows[0]["chosen"], rows[1]["chosen"] = "c1", "c0"  # (each body another controller: the mapping is what is tested)
    with open(table, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    _, learner = build(run, torch.device("cpu"))
    obs, envs = learner.env.reset(), torch.arange(4)
    labels = learner.teacher(obs, envs)
    nets = [read_controller(f).controller.eval() for f in files]
    with torch.no_grad():
        for i in range(4):
            want = nets[(1, 0)[i % 2]](obs[i:i + 1])
            for a, b in zip(labels, want, strict=True):
                torch.testing.assert_close(a[i:i + 1], b)
    learner.train_epoch()
    assert learner.dataset["obs"].shape[:2] == (4, 4)
    other = compose(*tiny_control(bodies, *TEACH, "algo=distill", f"algo.teacher={tmp_path / 'chosen'}",
                                  "control.duration=0.025"))
    with pytest.raises(ValueError, match=r"tried in another episode than this run's: control\.duration: 0\.05 in the "
                                         r"selection, 0\.025 here"):
        build(other, torch.device("cpu"))
    lighter = compose(*tiny_control(bodies, *TEACH, "algo=distill", f"algo.teacher={tmp_path / 'chosen'}",
                                    "sim.gravity=-5.0", "sim.schedule=robots"))
    with pytest.raises(ValueError, match=r"tried in another simulator than this run's: sim\.gravity: -9\.81 in the "
                                         r"selection, -5\.0 here \(give this run"):  # (the schedule: not named)
        build(lighter, torch.device("cpu"))
    swapped = tmp_path / "swapped.npy"
    np.save(swapped, np.load(bodies)[::-1].copy())
    elsewhere = compose(*tiny_control(swapped, *TEACH, "algo=distill", f"algo.teacher={tmp_path / 'chosen'}"))
    with pytest.raises(ValueError, match=r"its 2 bodies .* are not this run's 2"):
        build(elsewhere, torch.device("cpu"))
    from freeform.agents.networks.controllers import RecurrentContextController

    memory = save_controller(tmp_path / "gru" / "controller.pt", RecurrentContextController.for_env(env.env, hidden=4),
                             plain.control, plain.sim)
    try_controllers([files[0], memory], bodies, tmp_path / "chosen")
    with pytest.raises(ValueError, match=r"gru/controller.pt is recurrent"):
        build(run, torch.device("cpu"))
