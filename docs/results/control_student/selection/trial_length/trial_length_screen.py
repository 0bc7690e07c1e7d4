"""Screen (2026-12-01): how early in an episode does a trial tell which student suits a body? Every student plays
every body of one held-out set by its mean command for one 2 s episode (one env, a group a student); the move after
each decision is kept, and choosing by the move after t decisions is scored by the chosen student's full episode.
From the repository root:
    PYTHONPATH=. python docs/results/control_student/selection/trial_length/trial_length_screen.py BODIES.npy OUT.npy S...
OUT.npy: the cumulative move [students, decisions, bodies]."""
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from experiments.heldout import read_bodies
from freeform.agents.controller_file import controller_for, read_controller
from freeform.agents.controllers import controller_step
from freeform.envs.control import ControlEnv
from freeform.sim import SimConfig

bodies, out, *sources = sys.argv[1:]
first = read_controller(sources[0])
sim = first.sim or SimConfig()
grids = read_bodies(Path(bodies), len(sim.materials))
nets = [controller_for(s, grids).controller.eval() for s in sources]
box = tuple(nets[0].box)
assert all(tuple(n.box) == box for n in nets)
control = replace(first.control, headings="any")
m, c = len(grids), len(nets)
env = ControlEnv(grids.repeat(c, 1, 1, 1), sim=sim, control=control, seed=0, box=box, first_env=np.tile(np.arange(m), c))
obs, total, moves = env.reset(), torch.zeros(env.num_envs, dtype=torch.float64), []
states = [None] * c  # (a recurrent student's memory, carried through the episode)
with torch.no_grad():
    for _ in range(control.steps):
        actions = []
        for i, (n, part) in enumerate(zip(nets, obs.chunk(c))):
            outputs, states[i] = controller_step(n, part, states[i])
            actions.append(n.distribution.mode(outputs[:3]))
        obs, reward, _, _ = env.step(torch.cat(actions))
        total += reward.double()
        moves.append(total.clone().reshape(c, m).numpy())
np.save(out, np.stack(moves, 1))
print("decisions", control.steps, "final mean per student", np.round(moves[-1].mean(1), 3))
