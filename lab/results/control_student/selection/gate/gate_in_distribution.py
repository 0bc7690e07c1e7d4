"""The gate screen's gates inside the training bodies' own distribution: leave one training body out (seconds).
    PYTHONPATH=. python lab/results/control_student/selection/gate/gate_in_distribution.py"""
import runpy
from pathlib import Path

import numpy as np

g = runpy.run_path(str(Path(__file__).parent / "gate_screen.py"), run_name="gate")
x, y, moves = g["x_train"], g["y_train"], g["train_moves"]
n = len(x)
print(f"256 training bodies, mean move: mean student {moves.mean():.3f}, best single student "
      f"{moves.mean(1).max():.3f}, each body's best of 17 {moves.max(0).mean():.3f}")
for k in (3, 7, 15, 31):
    pick = [g["knn_pick"](np.delete(x, i, 0), np.delete(y, i, 0), x[i:i + 1], k)[0] for i in range(n)]
    print(f"leave one out, k-NN k = {k}: {moves[pick, np.arange(n)].mean():.3f}")
for lam in (1.0, 10.0, 100.0, 1000.0):
    pick = [np.argmax(np.r_[1.0, x[i]] @ g["ridge"](np.delete(x, i, 0), np.delete(y, i, 0), lam)) for i in range(n)]
    print(f"leave one out, ridge λ = {lam:g}: {moves[pick, np.arange(n)].mean():.3f}")
