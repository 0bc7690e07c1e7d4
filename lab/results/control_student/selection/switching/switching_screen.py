"""Screen (2026-12-05): how far a controller that switches among the committed students *decision by decision*
could go — an upper reach for any learned switch (a gate over experts that reads the state, not the shape alone),
before building one. At each of the episode's decisions the env is branched (``ControlEnv.snapshot``): every
candidate's stroke is played from the same state, and the one that moved the body furthest over that decision is
kept (a greedy one-decision lookahead, an oracle: it sees each candidate's outcome before choosing). Zero-shot
apart from the oracle's foresight; the try-and-commit bound (``../trial_length/in_episode_bound.py``) commits to
one candidate, this one may change its mind at every decision.

From the repository root (16 feed-forward students and the hand-set wave; ≈ 17 episodes' simulation):
    PYTHONPATH=. python lab/results/control_student/selection/switching/switching_screen.py BODIES.npy OUT.npy \
        REFERENCE_BODIES.csv S...
writes OUT.npy: float64 ``[2 + candidates, M]`` — each body's greedy-switching move, how many decisions changed
candidate, then every candidate's move over the whole episode alone (the same env and bodies, for pairing) — and
beside it OUT.csv: the README's table, against REFERENCE_BODIES.csv (a held-out table of the same bodies with
per-body control: its ``per_body_mean_command`` and ``open_loop`` columns).
"""
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from experiments.common import paired_band, write_rows
from lab.heldout import hand_set_wave, read_bodies
from lab.paired import read_table
from freeform.agents.controller_file import controller_for, read_controller
from freeform.agents.controllers import controller_step
from freeform.envs.control import ControlEnv
from freeform.sim import SimConfig

bodies, out, reference, *sources = sys.argv[1:]
rows = read_table(Path(reference), "REFERENCE_BODIES.csv", "lab.control --evaluate --per-body")
per_body = np.array([float(r["per_body_mean_command"]) for r in rows])
own_gait = np.array([float(r["open_loop"]) for r in rows])
first = read_controller(sources[0])
sim = first.sim or SimConfig()
grids = read_bodies(Path(bodies), len(sim.materials))
nets = [controller_for(s, grids).controller.eval() for s in sources]
control = replace(first.control, headings="any")
m = len(grids)
env = ControlEnv(grids, sim=sim, control=control, seed=0, box=tuple(nets[0].box), first_env=np.arange(m))
nets.append(hand_set_wave(env, nets[0], None))
k = len(nets)


def mode(net: torch.nn.Module, obs: torch.Tensor) -> torch.Tensor:
    """``net``'s mean command on ``obs``: ``[M, action_dim]``."""
    return net.distribution.mode(controller_step(net, obs, None)[0][:3])


with torch.no_grad():
    # each candidate alone, for pairing (one episode each, in this env)
    alone = np.zeros((k, m))
    for c in range(k):
        obs = env.reset(episode=0)
        for _ in range(control.steps):
            obs, reward, _, _ = env.step(mode(nets[c], obs))
            alone[c] += reward.double().numpy()
    obs, total = env.reset(episode=0), np.zeros(m)
    last, switches = None, np.zeros(m)
    for t in range(control.steps):
        snap, actions = env.snapshot(), torch.stack([mode(n, obs) for n in nets])
        moves = np.zeros((k, m))
        for c in range(k):
            env.restore(snap)
            moves[c] = env.step(actions[c])[1].double().numpy()
        choice = moves.argmax(0)
        env.restore(snap)
        obs, reward, _, _ = env.step(actions[torch.from_numpy(choice), torch.arange(m)])
        assert np.array_equal(reward.double().numpy(), moves[choice, np.arange(m)])  # (the branch replays exactly)
        total += reward.double().numpy()
        switches += 0 if last is None else (choice != last)
        last = choice
        print(f"decision {t + 1}: greedy {total.mean():.4f}", flush=True)
if len(rows) != m:
    raise ValueError(f"{reference}: {len(rows)} bodies, not the {m} played")
wave = alone[-1]


def row(what: str, moves: np.ndarray) -> dict:
    return {"controller": what, "mean_command": moves.mean(), "fraction_of_per_body": moves.mean() / per_body.mean(),
            "over_wave": moves.mean() / wave.mean(), "beyond_own_gait": np.mean(moves > own_gait)}


difference, band = paired_band(total - alone.max(0))
write_rows(Path(out).with_suffix(".csv"), [
    row("one student (the students' mean)", alone[:-1].mean(0)),
    row("the best candidate for the whole episode (by hindsight)", alone.max(0)),
    row(f"switching greedily at every decision ({switches.mean():.1f} switches)", total),
    {"controller": f"switching - the best candidate, paired: {difference:+.3f} +- {band:.3f} (99 %)"}])
print(f"greedy switching {total.mean():.4f}; best alone per body {alone.max(0).mean():.4f}; paired "
      f"{difference:+.3f} ± {band:.3f}; mean candidate {alone[:-1].mean():.4f}; hand-set wave {wave.mean():.4f}")
np.save(out, np.concatenate([total[None], switches[None], alone]))
