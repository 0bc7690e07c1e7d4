"""Screen (2026-12-02): a gate on the body's shape, fitted on bodies of other kinds, choosing among the 17 students.

Zero-shot if it works: the gate reads the body (no trial), names a student, and that student drives the body. Fitted
on 256 training-like bodies (`lab.training_bodies --kind primitives,blobs,limbed,cppn --n 256 --seed 11`,
none of the held-out kinds), where every student's mean command was played once
(`gate_moves256.npy`: `[17, 8 decisions, 256]`, as `python -m lab.selection --try` writes `moves.npy`; not
tracked: `git show 4b5e8bf:lab/results/control_student/selection/gate/gate_moves256.npy > gate_moves256.npy`); scored on the 93 held-out bodies from the
committed tables (`../bodies.csv`: the students' mean commands there, per-body control, the hand-set wave, own gaits)
and on the 32 fresh grown bodies (`../fresh_grown32/bodies.csv`), neither of which the gate saw.

Targets: a student's move on a body over the students' mean move there (the body's scale divided out). Gates: the
best student on the training bodies (the baseline a gate must beat), k-nearest neighbours on the shape features,
and ridge regression of each student's relative move on the features (λ by leave-one-out on the training bodies).
From the repository root (seconds):
    PYTHONPATH=. python lab/results/control_student/selection/gate/gate_screen.py
"""
import csv
from pathlib import Path

import numpy as np

from experiments.common import write_rows

HERE = Path(__file__).parent
ROOT = HERE.parents[4]


def features(grid: np.ndarray) -> np.ndarray:
    """Shape and muscle layout of one body (uint8 [X, Y, Z], 0 empty, 1 passive, 2 and 3 the two muscle groups in
    anti-phase): size, box, materials, height, footprint, fill; each muscle group's centre and spread relative to the
    body's (the hand-set wave runs along x, so where the groups lie along x matters to a gait)."""
    filled = grid > 0
    at = np.argwhere(filled).astype(np.float64)
    lo, hi = at.min(0), at.max(0) + 1
    dims, n = hi - lo, len(at)
    centre = at.mean(0)
    share = np.bincount(grid[filled], minlength=4)[1:] / n
    out = [n, *dims, *share, centre[2] - lo[2], np.mean(at[:, 2] == lo[2]), dims[0] / max(dims[1], 1),
           n / np.prod(dims), *at.std(0)]
    for group in (2, 3):
        cells = np.argwhere(grid == group).astype(np.float64)
        out += [*(cells.mean(0) - centre), *cells.std(0)] if len(cells) else [0.0] * 6
    return np.array(out, dtype=np.float64)


def relative(moves: np.ndarray) -> np.ndarray:
    """[C, M] moves → each over the body's mean over the C students."""
    return moves / np.maximum(moves.mean(0, keepdims=True), 1e-9)


def ridge(x: np.ndarray, y: np.ndarray, lam: float) -> np.ndarray:
    """Weights [F + 1, C] of y [M, C] on x [M, F] (with an intercept, not penalised)."""
    a = np.c_[np.ones(len(x)), x]
    penalty = lam * np.eye(a.shape[1])
    penalty[0, 0] = 0.0
    return np.linalg.solve(a.T @ a + penalty, a.T @ y)


def ridge_loo_lambda(x: np.ndarray, y: np.ndarray, lams: list[float]) -> float:
    """λ whose leave-one-out choices on the training bodies move them furthest (relative moves)."""
    scores = []
    for lam in lams:
        picked = [np.argmax(np.r_[1.0, x[i]] @ ridge(np.delete(x, i, 0), np.delete(y, i, 0), lam))
                  for i in range(len(x))]
        scores.append(np.mean(y[np.arange(len(x)), picked]))
    return lams[int(np.argmax(scores))]


def knn_pick(x_train: np.ndarray, y_train: np.ndarray, x: np.ndarray, k: int) -> np.ndarray:
    d = ((x[:, None] - x_train[None]) ** 2).sum(-1)
    near = np.argsort(d, 1)[:, :k]
    return y_train[near].mean(1).argmax(1)


def students(path: Path) -> list[str]:
    """A selection table's students, in its columns' order."""
    return [c[len("mean_command_"):] for c in next(csv.DictReader(open(path))) if c.startswith("mean_command_")]


def held_out(path: Path, names: list[str]) -> tuple[np.ndarray, dict]:
    """The students' mean commands [C, M] in ``names``' order, and the bodies' reference columns."""
    rows = list(csv.DictReader(open(path)))
    moves = np.array([[float(r[f"mean_command_{n}"]) for r in rows] for n in names])
    body = {k: np.array([float(r[k]) for r in rows]) for k in ("per_body_mean_command", "hand_set_wave", "open_loop")
            if k in rows[0]}
    return moves, body


def scored(chosen: np.ndarray, body: dict) -> dict:
    return {"fraction_of_per_body": chosen.sum() / body["per_body_mean_command"].sum(),
            "over_hand_set_wave": chosen.mean() / body["hand_set_wave"].mean(),
            "beyond_own_gait": float(np.mean(chosen > body["open_loop"]))}


def main() -> None:
    """The screen: fit the gates, score them, write ``gate_screen.csv``."""
    train_grids = np.load(HERE / "gate_bodies256.npy")
    train_moves = np.load(HERE / "gate_moves256.npy")[:, -1].astype(np.float64)  # [17, 256]: whole episodes
    x_train = np.array([features(g) for g in train_grids])
    mu, sd = x_train.mean(0), x_train.std(0) + 1e-9
    x_train = (x_train - mu) / sd
    y_train = relative(train_moves).T  # [256, 17]
    lam = ridge_loo_lambda(x_train, y_train, [1.0, 10.0, 100.0, 1000.0])
    weights = ridge(x_train, y_train, lam)
    best_single = int(np.argmax(y_train.mean(0)))
    NAMES = students(HERE.parent / "bodies.csv")  # (the order the 17 were played in on the training bodies)

    out = []
    sets = {"heldout93": (HERE.parent / "bodies.csv", [ROOT / f"lab/results/heldout_bodies/{s}.npy"
                                                        for s in ("design_unseen", "grown", "hand_built")]),
            "fresh_grown32": (HERE.parent / "fresh_grown32/bodies.csv", [HERE.parent / "fresh_grown32/grown_seed7.npy"])}
    for where, (table, grid_files) in sets.items():
        moves, body = held_out(table, NAMES)
        grids = np.concatenate([np.load(f) for f in grid_files])
        x = (np.array([features(g) for g in grids]) - mu) / sd
        cols = np.arange(moves.shape[1])
        picks = {"mean student": None, f"best on the training bodies ({NAMES[best_single]})": np.full(len(cols), best_single),
                 "k-NN gate (k = 7)": knn_pick(x_train, y_train, x, 7), f"ridge gate (λ = {lam:g})":
                 (np.c_[np.ones(len(x)), x] @ weights).argmax(1), "oracle (best of 17, few-shot)": moves.argmax(0)}
        for what, pick in picks.items():
            chosen = moves.mean(0) if pick is None else moves[pick, cols]
            out.append({"bodies": where, "gate": what, **scored(chosen, body)})
    write_rows(HERE / "gate_screen.csv", out)
    for r in out:
        print(f"{r['bodies']:>14} {r['gate']:<52} {r['fraction_of_per_body']:.3f} x{r['over_hand_set_wave']:.2f} "
              f"{r['beyond_own_gait']:.2f}")


if __name__ == "__main__":
    main()
