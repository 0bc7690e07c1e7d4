"""Screen (2026-12-02): is the choice among the 17 students in how the body moves rather than in its shape?

The shape gates (`../gate/gate_screen.py`) pick students no better than the best single one: what makes a student
work on a body is not in the body's shape features. A student with the response channels (`control.response`) sees,
from its first decision, each voxel's response to the open-loop gait walked in the burn-in (its velocity's Fourier
coefficients at the actuation frequency over the last actuation period). If the choice lies there, a student that
reads them could learn from teachers chosen by selection what a shape-reading one cannot. The test: the same gates
(k-nearest neighbours, ridge regression of each student's relative move), fitted on the same 256 training bodies and
their 17 students' moves (`../gate/gate_moves256.npy`, not tracked: restored as `../gate/gate_screen.py` says), on the response's body summaries added to the shape features
or alone; scored leave-one-out on the 256 and on the 93 held-out bodies and 32 fresh grown ones, never seen.

Response summaries of a body (over its filled cells, from the first observation at the students' episode settings:
1 s of open-loop burn-in, residual, ramped, 26 /s): each of the 6 response channels' mean (the centre of mass's
response: the gait's own net oscillation), its mean magnitude, and its covariance with the voxel's place along x
and along y (how the response's phase turns across the body: a wave's signature), 24 numbers.

From the repository root (about two minutes on 2 cores: 381 bodies' burn-ins):
    PYTHONPATH=. python lab/results/control_student/selection/response_gate/response_gate_screen.py
"""
import sys
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).parent
GATE = HERE.parent / "gate"
ROOT = HERE.parents[4]
sys.path.insert(0, str(GATE))
import gate_screen as shape  # noqa: E402  (its features, gates and scores)

from experiments.common import write_rows  # noqa: E402
from freeform.agents.controller_file import read_controller  # noqa: E402
from freeform.body import largest_component  # noqa: E402
from freeform.envs.control import ControlEnv  # noqa: E402
from freeform.envs.response import RESPONSE_CHANNELS  # noqa: E402

saved = read_controller(ROOT / "lab/results/control_student/controller.pt")
CONTROL = type(saved.control)(**{**vars(saved.control), "response": True})


def response_features(grids: np.ndarray) -> np.ndarray:
    """[M, 24] response summaries of bodies ``grids`` [M, ρ, ρ, ρ] (module docstring)."""
    env = ControlEnv(largest_component(torch.from_numpy(grids.astype(np.uint8))), sim=saved.sim, control=CONTROL)
    obs = env.reset().double()  # [M, C, Bx, By, Bz]
    ch = {name: obs[:, i] for i, name in enumerate(env.channels)}
    filled = ch["filled"] > 0
    n = filled.sum((1, 2, 3)).clamp(min=1)

    def mean(v: torch.Tensor) -> torch.Tensor:
        return (v * filled).sum((1, 2, 3)) / n

    out = []
    for name in RESPONSE_CHANNELS:
        r = ch[name]
        out += [mean(r), mean(r.abs()), mean(r * ch["rel_x"]) - mean(r) * mean(ch["rel_x"]),
                mean(r * ch["rel_y"]) - mean(r) * mean(ch["rel_y"])]
    return torch.stack(out, 1).numpy()


def standardise(train: np.ndarray, *others: np.ndarray) -> list[np.ndarray]:
    mu, sd = train.mean(0), train.std(0) + 1e-9
    return [(x - mu) / sd for x in (train, *others)]


train_grids = np.load(GATE / "gate_bodies256.npy")
train_moves = np.load(GATE / "gate_moves256.npy")[:, -1].astype(np.float64)  # [17, 256]: whole episodes
y_train = shape.relative(train_moves).T  # [256, 17]
NAMES = shape.students(HERE.parent / "bodies.csv")
sets = {"heldout93": (HERE.parent / "bodies.csv", [ROOT / f"lab/results/heldout_bodies/{s}.npy"
                                                    for s in ("design_unseen", "grown", "hand_built")]),
        "fresh_grown32": (HERE.parent / "fresh_grown32/bodies.csv", [HERE.parent / "fresh_grown32/grown_seed7.npy"])}
grids = {w: [np.load(f) for f in files] for w, (_, files) in sets.items()}
resp_train = response_features(train_grids)
resp = {w: np.concatenate([response_features(g) for g in gs]) for w, gs in grids.items()}
shp_train = np.array([shape.features(g) for g in train_grids])
shp = {w: np.array([shape.features(g) for g in np.concatenate(gs)]) for w, gs in grids.items()}

rows, lines = [], []
best_single = int(np.argmax(y_train.mean(0)))
lines.append(f"256 training bodies: mean student {train_moves.mean():.3f}, best single student "
             f"{train_moves.mean(1).max():.3f} (by relative move {train_moves[best_single].mean():.3f}), each body's "
             f"best of 17 {train_moves.max(0).mean():.3f}")
for label, (xt, xs) in {"response": (resp_train, resp),
                        "shape + response": (np.c_[shp_train, resp_train], {w: np.c_[shp[w], resp[w]] for w in sets}),
                        "shape": (shp_train, shp)}.items():
    x_train, *x_sets = standardise(xt, *(xs[w] for w in sets))
    for k in (7, 15, 31):
        picked = [shape.knn_pick(np.delete(x_train, i, 0), np.delete(y_train, i, 0), x_train[i:i + 1], k)[0]
                  for i in range(len(x_train))]
        lines.append(f"{label:>17}: leave one out, k-NN k = {k}: {train_moves[picked, np.arange(256)].mean():.3f}")
    lam = shape.ridge_loo_lambda(x_train, y_train, [1.0, 10.0, 100.0, 1000.0])
    picked = [np.argmax(np.r_[1.0, x_train[i]] @ shape.ridge(np.delete(x_train, i, 0), np.delete(y_train, i, 0), lam))
              for i in range(len(x_train))]
    lines.append(f"{label:>17}: leave one out, ridge λ = {lam:g}: {train_moves[picked, np.arange(256)].mean():.3f}")
    weights = shape.ridge(x_train, y_train, lam)
    for where, x in zip(sets, x_sets, strict=True):
        moves, body = shape.held_out(sets[where][0], NAMES)
        cols = np.arange(moves.shape[1])
        for what, pick in {"k-NN gate (k = 15)": shape.knn_pick(x_train, y_train, x, 15),
                           f"ridge gate (λ = {lam:g})": (np.c_[np.ones(len(x)), x] @ weights).argmax(1)}.items():
            rows.append({"features": label, "bodies": where, "gate": what, **shape.scored(moves[pick, cols], body)})
for where in sets:
    moves, body = shape.held_out(sets[where][0], NAMES)
    rows.append({"features": "none", "bodies": where, "gate": f"best on the training bodies ({NAMES[best_single]})",
                 **shape.scored(moves[best_single], body)})
    rows.append({"features": "none", "bodies": where, "gate": "oracle (best of 17, few-shot)",
                 **shape.scored(moves.max(0), body)})
write_rows(HERE / "response_gate_screen.csv", rows)
lines += [f"{r['bodies']:>14} {r['features']:>17} {r['gate']:<48} {r['fraction_of_per_body']:.3f} "
          f"x{r['over_hand_set_wave']:.2f} {r['beyond_own_gait']:.2f}" for r in rows]
(HERE / "response_gate_screen.txt").write_text("\n".join(lines) + "\n")
print("\n".join(lines))
