"""A trial gate (freeform.agents.networks.gated.TrialGate): plays each expert for its window, then the one whose window
earned most — checked on hand-made rewards, and on a real episode against the same choice made by hand step by step."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_control_cli import SHORT, tiny_bodies

from freeform.agents.controller_file import read_controller, save_controller
from freeform.agents.networks.controller_heads import ControlInputs
from freeform.agents.networks.controllers import ContextConvController, build_controller, controller_step
from freeform.agents.networks.gated import TrialGate
from freeform.control.play import play
from freeform.envs.control import OBS_CHANNELS, ControlEnv
from freeform.sim import SimConfig


def _experts(k: int, box=(2, 2, 1)) -> list[ContextConvController]:
    nets = []
    for seed in range(k):
        torch.manual_seed(seed)
        net = ContextConvController(ControlInputs(len(OBS_CHANNELS), box, OBS_CHANNELS.index("actuated")), hidden=4,
                                    log_std=-1.0)
        with torch.no_grad():
            net.actor.bias.fill_(0.3 * (seed - 1))  # (experts whose commands differ clearly)
        nets.append(net.eval())
    return nets


def test_a_gate_commits_to_the_expert_whose_window_earned_most() -> None:
    experts = _experts(3)
    gate = TrialGate.from_controllers(experts, trial=2)
    obs = torch.randn(4, len(OBS_CHANNELS), 2, 2, 1)
    obs[:, OBS_CHANNELS.index("actuated")] = 1.0
    # each row's reward per decision while trying: row 0 favours expert 1, row 1 expert 2, row 2 expert 0 (a loss
    # elsewhere), row 3 earns nothing anywhere (a tie: the first)
    earned = {0: [0.1, 0.9, 0.2], 1: [0.0, 0.1, 0.5], 2: [0.3, -1.0, -0.2], 3: [0.0, 0.0, 0.0]}
    winner = [1, 2, 0, 0]
    state = None
    for t in range(10):
        outputs, state = controller_step(gate, obs, state)
        expected = [t // 2 if t < 6 else winner[r] for r in range(4)]
        for r, k in enumerate(expected):
            mine = experts[k](obs[r:r + 1])
            for a, b in zip(outputs, mine, strict=True):
                torch.testing.assert_close(a[r:r + 1], b)
        reward = torch.tensor([earned[r][t // 2] / 2 if t < 6 else 5.0 for r in range(4)])
        state = gate.observe(state, reward)  # (after the trials: earned, and no longer counted)
    np.testing.assert_allclose(state[0][:, 2:].numpy(), [[0.1, 0.9, 0.2], [0.0, 0.1, 0.5], [0.3, -1.0, -0.2],
                                                        [0.0, 0.0, 0.0]], atol=1e-6)
    np.testing.assert_array_equal(gate.chosen(state).numpy(), winner)
    # a row whose episode starts is tried again from expert 0
    *_, fresh = gate(obs[None], state, torch.tensor([[True, False, False, False]]))
    np.testing.assert_array_equal(gate.chosen(fresh).numpy(), [0, 2, 0, 0])
    assert fresh[0][0, 0] == 1 and fresh[0][1, 0] == 11


def test_a_gate_plays_a_real_episode_as_its_choice_made_by_hand(tmp_path) -> None:
    """On real bodies: play() of the gate equals an episode stepped by hand, expert 0 for a decision, expert 1 for
    the next, then whichever of them earned more there, row by row — and the file saved and read back plays alike."""
    experts = _experts(2)
    gate = TrialGate.from_controllers(experts, trial=1)
    grids = tiny_bodies()

    def env() -> ControlEnv:
        return ControlEnv(grids, sim=SimConfig(), control=SHORT, seed=0, box=(2, 2, 1))

    played = play(env(), [("gate", gate.eval(), False, False)], SHORT.steps, seed=0).returns[0]
    by_hand, first = env(), None
    obs, total, earned = by_hand.reset(), np.zeros(3), np.zeros((2, 3))
    for t in range(SHORT.steps):
        if t < 2:
            k = torch.full((3,), t)
        else:
            k = torch.as_tensor(earned.argmax(0)) if first is None else first
            first = k
        means = torch.stack([e.distribution.mode(tuple(e(obs))[:3]) for e in experts])  # [K, N, A]
        obs, reward, _, _ = by_hand.step(means[k, torch.arange(3)])
        if t < 2:
            earned[t] = reward.numpy()
        total += reward.numpy()
    assert not np.allclose(earned[0], earned[1])  # (the experts differ on these bodies: the choice matters)
    np.testing.assert_array_equal(played, total)

    path = save_controller(tmp_path / "controller.pt", gate, SHORT, SimConfig())
    saved = read_controller(path)
    assert saved.kind == "gated" and saved.controller.trial == 1
    wider = read_controller(path, box=(3, 2, 2))  # (its experts fit any box: so does the gate)
    assert wider.controller.box == (3, 2, 2) and all(tuple(e.box) == (3, 2, 2) for e in wider.controller.experts)
    again = play(env(), [("gate", saved.controller.eval(), False, False)], SHORT.steps, seed=0).returns[0]
    np.testing.assert_array_equal(again, played)


def test_a_gate_is_refused_where_it_cannot_play() -> None:
    with pytest.raises(ValueError, match="at least one expert"):
        TrialGate([], trial=1)
    with pytest.raises(ValueError, match="whole number of decisions"):
        TrialGate.from_controllers(_experts(1), trial=0)
    with pytest.raises(ValueError, match="made of trained controllers"):
        build_controller("gated", object())
    with pytest.raises(ValueError, match="one action distribution, one box"):
        TrialGate.from_controllers([*_experts(1), *_experts(1, box=(3, 1, 1))], trial=1)


def test_freeform_control_gate_writes_one_controller_that_evaluate_plays(tmp_path, capsys) -> None:
    from test_control_cli import refused, rows

    from freeform.control.cli import main

    bodies = tmp_path / "bodies.npy"
    np.save(bodies, tiny_bodies())
    out = tmp_path / "g.pt"
    main(["gate", "student", "wave", "--trial", "0.25", "--out", str(out)])
    assert "tries student, wave for 0.25 s each" in capsys.readouterr().out
    saved = read_controller(out)
    assert saved.kind == "gated" and saved.controller.trial == 1 and len(saved.controller.experts) == 2
    main(["evaluate", str(out), str(bodies), "--out", str(tmp_path / "eval"), "--episodes", "1"])
    assert len(rows(tmp_path / "eval" / "bodies.csv")) == 3
    refused(["gate", "student", "wave", "--trial", "0.25", "--out", str(out)], capsys, "exists")
    refused(["gate", "student", "wave", "pool256", "student_gen3", "--trial", "0.5", "--out", str(tmp_path / "h.pt")],
            capsys, "leave none of the episode's 8")
    assert not (tmp_path / "h.pt").exists()
