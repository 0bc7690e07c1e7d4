"""Paper Table I — the hyper-parameters actually used, read from the runs' own configs.

    python -m experiments.hparams runs/paper_volume/<sweep> runs/paper_locomotion/<sweep> --out figures/hparams

Each run's config comes from its checkpoint (what it trained with), else from ``.hydra/config.yaml``. Runs are
grouped by experiment name (one column each); a value that differs within a group lists every value. Writes
``hparams.csv``, ``hparams.md`` (markdown) and ``hparams.tex`` (a LaTeX tabular in the paper's layout).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from experiments import common

Row = tuple[str, Callable[[dict[str, Any]], Any] | None]


def _mlp(c: dict[str, Any]) -> str:
    h = c["agent"]["hidden"]
    return f"({h}, {h})"


def _cnn(c: dict[str, Any]) -> str:
    k = c["task"]["materials"]
    return f"(3x3x3, {k}->1) (5x5x5 stride 2, 1->1)"


def _batch(c: dict[str, Any]) -> int:
    return c["env"]["num_envs"] * (c["agent"].get("rollout_steps") or c["env"]["steps"])


def _vf_clip(c: dict[str, Any]) -> str:
    v = c["agent"]["vf_clip_param"]
    return f"Disabled (by setting to {v:g})" if v >= 1e5 else f"{v:g}"


def _gae(c: dict[str, Any]) -> str:
    lam = c["agent"]["gae_lambda"]
    return "Disabled" if lam == 1 else f"lambda = {lam:g}"


def _sim(key: str) -> Callable[[dict[str, Any]], Any]:
    return lambda c: c.get("sim", {}).get(key, "-") if c["task"]["name"] == "locomotion" else "-"


ROWS: tuple[Row, ...] = (
    # The paper's Table I, in its order and wording
    ("CNN Size", _cnn),
    ("Actor MLP Size", _mlp),
    ("Critic MLP Size", _mlp),
    ("PPO Learning Rate", lambda c: f"{c['agent']['lr']:g}"),
    ("PPO Batch Size", _batch),
    ("PPO SGD Minibatch Size", lambda c: c["agent"]["sgd_minibatch_size"]),
    ("PPO SGD iter per Minibatch", lambda c: c["agent"]["num_sgd_iter"]),
    ("PPO Training Epochs", lambda c: c["trainer"]["epochs"]),
    ("PPO Discount Factor", lambda c: f"{c['agent']['gamma']:g}"),
    ("PPO Critic Parameter Clipping", _vf_clip),
    ("PPO GAE", _gae),
    # What the table leaves implicit
    ("Environments N", lambda c: c["env"]["num_envs"]),
    ("Design steps T", lambda c: c["env"]["steps"]),
    ("Grid resolution", lambda c: c["env"]["resolution"]),
    ("Materials k (incl. empty)", lambda c: c["task"]["materials"]),
    ("PPO clip", lambda c: f"{c['agent']['clip_param']:g}"),
    ("KL coeff (initial) / target", lambda c: f"{c['agent']['kl_coeff']:g} / {c['agent']['kl_target']:g}"),
    ("Entropy coeff", lambda c: f"{c['agent']['entropy_coeff']:g}"),
    ("Task", lambda c: c["task"]["name"]),
    ("Simulator semantics", _sim("semantics")),
    ("Burn-in / evaluation (s)", lambda c: (f"{c['sim']['burn_in']:g} / {c['sim']['duration']:g}"
                                            if c["task"]["name"] == "locomotion" else "-")),
    ("Locomotion reward", _sim("reward")),
    ("Seeds", None),  # filled per group
)


def table(runs: Sequence[Path]) -> tuple[list[str], list[str], list[list[str]]]:
    """``(group names, row names, cells[row][group])`` for the runs, grouped by experiment name."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for run in runs:
        cfg = common.run_config(run)
        groups.setdefault(str(cfg.get("name", run.name)), []).append(cfg)
    names = list(groups)
    cells: list[list[str]] = []
    for _label, fn in ROWS:
        row = []
        for g in names:
            if fn is None:
                seeds = sorted({c["seed"] for c in groups[g]})
                row.append(", ".join(map(str, seeds)))
                continue
            values = list(dict.fromkeys(str(fn(c)) for c in groups[g]))
            row.append(" | ".join(values))
        cells.append(row)
    return names, [label for label, _ in ROWS], cells


def to_markdown(names: list[str], rows: list[str], cells: list[list[str]]) -> str:
    lines = ["| Hyperparameter | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    lines += [f"| {r} | " + " | ".join(c) + " |" for r, c in zip(rows, cells, strict=True)]
    return "\n".join(lines) + "\n"


def _tex(s: str) -> str:
    return s.replace("_", r"\_").replace("%", r"\%").replace("->", r"$\to$").replace("|", r"/")


def to_latex(names: list[str], rows: list[str], cells: list[list[str]], caption: str) -> str:
    lines = [r"\begin{table}[]", r"\centering", rf"\caption{{{_tex(caption)}}}",
             r"\begin{tabular}{l|" + "l" * len(names) + "}", r"\hline",
             "Hyperparameter & " + " & ".join(_tex(n) for n in names) + r" \\ \hline"]
    lines += [_tex(r) + " & " + " & ".join(_tex(x) for x in c) + r" \\" for r, c in zip(rows, cells, strict=True)]
    lines += [r"\hline", r"\end{tabular}", r"\label{tab:hyperparam}", r"\end{table}"]
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> dict[str, Path]:
    args = common.base_parser(__doc__.splitlines()[0]).parse_args(argv)
    runs = common.find_runs(args.paths)
    names, rows, cells = table(runs)
    prov = common.provenance(runs)
    cols: dict[str, Sequence] = {"hyperparameter": rows}
    for i, n in enumerate(names):
        cols[n] = [c[i] for c in cells]
    out = {"csv": common.write_csv(args.out / "hparams.csv", cols, prov)}
    md = to_markdown(names, rows, cells) + f"\n{common.provenance_caption(prov)}\n"
    out["md"] = args.out / "hparams.md"
    out["md"].write_text(md)
    out["tex"] = args.out / "hparams.tex"
    out["tex"].write_text(to_latex(names, rows, cells, "Hyperparameters used (generated from the runs' configs; "
                                   + common.provenance_caption(prov) + ")."))
    print(md)
    print("wrote " + ", ".join(str(v) for v in out.values()))
    return out


if __name__ == "__main__":
    common.run_cli(main)
