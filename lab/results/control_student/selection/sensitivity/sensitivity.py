"""Screen (2026-12-02): are the students' body-by-body differences a lottery or a property of student and body?

The committed student played at wave gain 0.95 and 1.05 (a 5 % change of what it learnt, `--wave-gain G`) against
itself at gain 1 on the same host (`../../heldout93/student64_gen3_host2_bodies.csv`), body by body, as fractions of
per-body control; beside it, how much the 17 students differ on a body beyond what the body and the student explain
(the two-way table's interaction, from `../bodies.csv`). If a small change to one student moved bodies as much as
another student does, the best of 17 would be the best of 17 draws of noise; it moves them a tenth as much
(median; a sixth by the standard deviation, which a few bodies carry).
From the repository root (seconds):
    python lab/results/control_student/selection/sensitivity/sensitivity.py
"""
import csv
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent


def column(path: Path, name: str) -> np.ndarray:
    return np.array([float(r[name]) for r in csv.DictReader(open(path))])


per_body = column(HERE.parent.parent / "heldout93/student64_gen3_bodies.csv", "per_body_mean_command")
base = column(HERE.parent.parent / "heldout93/student64_gen3_host2_bodies.csv", "mean_command")
rows = [("gain", "fraction_of_per_body", "per_body_change_sd", "per_body_change_median_abs", "correlation")]
for gain in ("0.95", "1.05"):
    moved = column(HERE / f"gain{gain}_bodies.csv", "mean_command")
    change = (moved - base) / per_body
    rows.append((gain, moved.mean() / per_body.mean(), change.std(), np.median(np.abs(change)),
                 np.corrcoef(moved, base)[0, 1]))
table = list(csv.DictReader(open(HERE.parent / "bodies.csv")))
students = np.array([[float(r[c]) for r in table] for c in table[0] if c.startswith("mean_command_")])
fraction = students / per_body  # [17, 93]
interaction = fraction - fraction.mean(0) - fraction.mean(1, keepdims=True) + fraction.mean()
rows.append(("17 students: interaction", students.mean() / per_body.mean(), interaction.std(), np.median(np.abs(interaction)),
             np.corrcoef(students)[np.triu_indices(len(students), 1)].mean()))
with open(HERE / "sensitivity.csv", "w", newline="") as f:
    csv.writer(f).writerows(rows)
for r in rows[1:]:
    print(f"{r[0]:>26}: {r[1]:.3f} of per-body control, change sd {r[2]:.3f}, median |change| {r[3]:.3f}, "
          f"corr {r[4]:.4f}")
