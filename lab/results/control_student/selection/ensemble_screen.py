"""Screen (2026-12-01): the mean command of an ensemble of students (their means averaged) against each member on one
held-out set; prints the members' episode spread (0: a mean-command episode repeats). From the repository root:
PYTHONPATH=. python lab/results/control_student/selection/ensemble_screen.py BODIES.npy OUT.npy STUDENT...
"""
import sys, json
from dataclasses import replace
from pathlib import Path
import numpy as np, torch, torch.nn as nn
from freeform.agents.controller_file import controller_for, read_controller
from freeform.envs.control import ControlEnv
from freeform.sim import SimConfig
from lab.heldout import read_bodies, play

class Ensemble(nn.Module):
    def __init__(self, members):
        super().__init__()
        self.members = nn.ModuleList(members)
        self.distribution = members[0].distribution
    def forward(self, obs):
        outs = [m(obs) for m in self.members]
        mean = torch.stack([o[0] for o in outs]).mean(0)
        return (mean, outs[0][1], outs[0][2], torch.stack([o[3] for o in outs]).mean(0))

bodies, out, *sources = sys.argv[1:]
first = read_controller(sources[0])
sim = first.sim or SimConfig()
grids = read_bodies(Path(bodies), len(sim.materials))
nets = [controller_for(s, grids).controller.eval() for s in sources]
boxes = {tuple(n.box) for n in nets}
assert len(boxes) == 1, boxes
box = boxes.pop()
control = replace(first.control, headings="any")
groups = [("ensemble", Ensemble(nets), False, False)] + [(f"m{i}", n, False, False) for i, n in enumerate(nets)]
m, n = len(grids), 2
env = ControlEnv(grids.repeat_interleave(n, 0).repeat(len(groups), 1, 1, 1), sim=sim, control=control, seed=0,
                 box=box, first_env=np.tile(np.arange(m * n), len(groups)))
with torch.no_grad():
    returns = play(env, groups, control.steps, 0).returns
full = returns.reshape(len(groups), m, n); print("episode spread", float(np.abs(full[..., 0] - full[..., 1]).max())); per = full.mean(2)
np.save(out, per)
print(json.dumps({g[0]: float(per[i].mean()) for i, g in enumerate(groups)}))
