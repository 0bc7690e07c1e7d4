"""The paper's figures, one command each: ``python -m experiments.<name> <sweep dir | run dirs> --out <dir>``.

Each command reads the run directories that ``freeform-train`` wrote (``run_info.json``, the resolved Hydra
config, per-epoch design records, checkpoints) and writes its figure (PNG + PDF) and the numbers behind it (CSV),
with the provenance of the runs (freeform/torch/taichi versions, device, git commit) in the CSV header and caption.

| module | paper figure |
|---|---|
| ``volume``      | Fig. 2: volume reward across seeds + six example bodies |
| ``locomotion``  | Fig. 4 A-H: reward and the seven body metrics across seeds |
| ``critic``      | Fig. 5: trained vs untrained critic V(s_T) against the true reward, in- and out-of-domain |
| ``robustness``  | Fig. 6: reward of the final epoch's designs truncated after each design step t |
| ``hparams``     | Table I: the hyper-parameters actually used, from the runs' configs |
| ``policy_eval`` | (CPU demo) fresh designs of the untrained and the trained policy, scored by the run's task |

``experiments/reproduce.sh`` trains the paper's sweeps (5 seeds of paper_volume and paper_locomotion) on a GPU and
runs every command above; docs/experiments.md describes each.

Shared statistics and run reading live in ``experiments.common``. matplotlib is the ``experiments`` extra.
"""
