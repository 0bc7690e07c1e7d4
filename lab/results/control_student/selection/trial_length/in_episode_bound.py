"""Screen (2026-12-02): how far could ANY controller that tries the 17 students inside the scored 2 s episode go?

A bound, not a controller. From `moves_93.npy` (each student's move after each of its 8 decisions, one mean-command
episode a body) a decision's move is its increment there. A controller that plays E candidates one decision each
(in the order ranked on `../fresh_grown32/`, so the 93 do not rank them) and then commits is scored, in this table
model, by the trials' increments plus the committed candidate's increments over the decisions left — as if a
candidate played at decision t moves the body as it does at t in its own episode. The model predicts the real
try-and-commit screen (`try_and_commit.csv`, switches simulated) to 0.3 point at K = 2 and 3 and overstates it at
K = 4 (79.9 against 77.3 %): switching costs, which the model leaves out, so its figures are upper bounds there.

Rows: the rule that commits to the best trial; the same trials with a perfect choice (the candidate whose
remaining decisions move the body furthest); and an omniscient stopper that, body by body, knows how many trials to
play and whom to keep. No chooser that tries these candidates in this order, one decision each, and then commits —
learned or hand-set — beats that row; one that knew a body's best candidate without trying it would be a gate on the
body (`../gate_cv.py`: a k-NN gate on its shape found little).
From the repository root (seconds):
    PYTHONPATH=. python lab/results/control_student/selection/trial_length/in_episode_bound.py
"""
import csv
from pathlib import Path

import numpy as np

from experiments.common import write_rows

HERE = Path(__file__).parent
RANKED = ["reptile2", "reptile3_fresh_bodies", "reptile1", "student64_gen3_seed1", "student64_gen4_hyper",
          "student64_gen4_gru", "reptile1_seed1", "student64_gen3_soup", "student64_gen3",
          "student64_iterated_seed1", "reptile3", "student64_gen4", "student256_gen4", "student64_iterated",
          "student64_gen4_seed1", "student256", "student64"]  # by mean command on ../fresh_grown32/bodies.csv

rows = list(csv.DictReader(open(HERE.parent / "bodies.csv")))
names = [c[len("mean_command_"):] for c in rows[0] if c.startswith("mean_command_")]
after = np.load(HERE / "moves_93.npy").astype(np.float64)  # [17 students, 8 decisions, 93 bodies], cumulative
steps, count = after.shape[1], after.shape[2]
step_move = np.diff(after, axis=1, prepend=0.0)  # [17, 8, 93]: each decision's increment
body = {k: np.array([float(r[k]) for r in rows]) for k in ("per_body_mean_command", "hand_set_wave", "open_loop")}
order = np.array([names.index(n) for n in RANKED])


def scored(moved: np.ndarray) -> dict:
    return {"fraction_of_per_body": moved.mean() / body["per_body_mean_command"].mean(),
            "over_hand_set_wave": moved.mean() / body["hand_set_wave"].mean(),
            "beyond_own_gait": float(np.mean(moved > body["open_loop"]))}


def trials_then(e: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """E one-decision trials: (their summed increments [93], each trial's increment [E, 93], each tried
    candidate's increments over the decisions left [E, 93])."""
    tried = order[:e]
    trial = step_move[tried, np.arange(e)]  # [E, 93]
    rest = after[tried, -1] - after[tried, e - 1]
    return trial.sum(0), trial, rest


out, best_e = [], []
for e in range(1, steps + 1):
    trial_sum, trial, rest = trials_then(e)
    rule = trial_sum + rest[trial.argmax(0), np.arange(count)]
    perfect = trial_sum + rest.max(0)
    best_e.append(perfect)
    out += [{"trials": e, "choice": "best trial", **scored(rule)}, {"trials": e, "choice": "perfect", **scored(perfect)}]
out.append({"trials": "per body", "choice": "omniscient stopper", **scored(np.max(best_e, axis=0))})
clairvoyant = after[:, -1].max(0)
out.append({"trials": 0, "choice": "best of 17 from the start (few-shot selection)", **scored(clairvoyant)})
write_rows(HERE / "in_episode_bound.csv", out)
for r in out:
    print(f"{r['trials']!s:>9} {r['choice']:<48} {r['fraction_of_per_body']:.3f}  x{r['over_hand_set_wave']:.2f}  "
          f"{r['beyond_own_gait']:.2f}")
