"""Screen (2026-12-01): one controller that tries K students within the episode and commits to the best — zero-shot,
no episode but the scored one. Decision t < K·d is played by candidate t // d (d decisions each); then the candidate
whose own decisions moved the body furthest (the episode's reward over them, which a controller can integrate from
its sensed velocities) plays the rest. Every candidate's forward runs every step (a recurrent one keeps its memory);
the scored move is the whole episode's, trials included. Candidates in the order given (ranked on other bodies).
From the repository root:
    PYTHONPATH=. python lab/results/control_student/selection/trial_length/try_and_commit_screen.py BODIES.npy K D S...
"""
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from lab.heldout import read_bodies
from freeform.agents.controller_file import controller_for, read_controller
from freeform.agents.controllers import controller_step
from freeform.envs.control import ControlEnv
from freeform.sim import SimConfig

bodies, k, d, *sources = sys.argv[1:]
k, d = int(k), int(d)
first = read_controller(sources[0])
sim = first.sim or SimConfig()
grids = read_bodies(Path(bodies), len(sim.materials))
nets = [controller_for(s, grids).controller.eval() for s in sources[:k]]
box = tuple(nets[0].box)
control = replace(first.control, headings="any")
m = len(grids)
env = ControlEnv(grids, sim=sim, control=control, seed=0, box=box, first_env=np.arange(m))
obs, total = env.reset(), torch.zeros(m, dtype=torch.float64)
gain = torch.zeros(k, m, dtype=torch.float64)  # each candidate's move over its own trial decisions
states = [None] * k
choice = None
with torch.no_grad():
    for t in range(control.steps):
        means = []
        for i, n in enumerate(nets):
            outputs, states[i] = controller_step(n, obs, states[i])
            means.append(n.distribution.mode(outputs[:3]))
        if t < k * d:
            acting = torch.full((m,), t // d, dtype=torch.long)
        else:
            choice = gain.argmax(0) if choice is None else choice
            acting = choice
        action = torch.stack(means)[acting, torch.arange(m)]
        obs, reward, _, _ = env.step(action)
        total += reward.double()
        if t < k * d:
            gain[t // d] += reward.double()
print(f"K={k} d={d}: mean move {total.mean():.4f}")
np.save(f"/tmp/try_commit_{Path(bodies).stem}_{k}_{d}.npy", total.numpy())
