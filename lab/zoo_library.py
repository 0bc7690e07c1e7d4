"""The zoo's library: a teacher run's per-body controllers, each exported into the zoo with a card of its own.

    python -m lab.reference runs/library/design8 --out lab/results/library8/reference      # each body's own curve
    python -m lab.zoo_library runs/library/design8/checkpoints/epoch_000200.pt \\
        --reference lab/results/library8/reference --epoch 200 --out freeform/zoo/library

For each teacher i: ``OUT/d<i>/controller.pt`` and ``OUT/d<i>/body.npy`` (``freeform.run.teacher_runs.export_teacher``)
and ``OUT/d<i>/card.md`` (``d<first + i>`` with ``--first``: a second run's members beside the first's) — what it
is, the body it was trained on, its own move there (the ``lab.reference`` folder's figure at ``--epoch``, which must
be the exported checkpoint's), and where the library's card and command are
(``OUT/card.md``, written by hand: what the library reaches on bodies it never saw). Refuses an ``OUT`` member that
exists (nothing is overwritten).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

MEMBER_CARD = """# library/d{i}
One member of the zoo's library: the per-body controller of the library's body {i}, which `freeform-control fit`
tries on every body beside the zoo's students and, where it wins, adapts by the per-body teachers' recipe.

**What it is.** A context controller (`context`, {hidden} wide, wave head: the population controller's kind) trained
on one body alone for {epoch} epochs of PPO from the population controller (`experiment=control_teachers_cpu`, 4
copies of the body, headings any). The library, its command and what it reaches on bodies it never saw:
[card.md](../card.md).

**Its body** (`body.npy`, uint8 `[1, {rho}, {rho}, {rho}]`): {voxels} voxels ({passive} passive, {muscles} muscle),
box {box}. On it, by its mean command: **{own:.3f}** voxel lengths in 2 s (headings any).

**Size.** {kib} KiB (`controller.pt`, self-contained: weights, kind, episode and simulator).
"""


def member_card(i: int, body: np.ndarray, own: float, epoch: int, hidden: int, kib: int) -> str:
    """Member ``i``'s card: its body ``[ρ, ρ, ρ]`` (uint8 materials), its own move ``own`` at ``epoch``."""
    filled = np.argwhere(body > 0)
    box = tuple(int(x) for x in filled.max(0) - filled.min(0) + 1)
    return MEMBER_CARD.format(i=i, hidden=hidden, epoch=epoch, rho=body.shape[0], voxels=int((body > 0).sum()),
                              passive=int((body == 1).sum()), muscles=int((body > 1).sum()),
                              box=" × ".join(map(str, box)), own=own, kib=kib)


def main(argv: list[str] | None = None) -> None:
    from freeform.agents.controller_file import read_controller
    from freeform.run.teacher_runs import export_teacher
    from lab.fractions import reference_moves

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint", type=Path, help="the teacher run's checkpoint to export (its epoch: --epoch)")
    p.add_argument("--reference", type=Path, required=True, help="lab.reference's folder of that run")
    p.add_argument("--epoch", type=int, required=True, help="the checkpoint's epoch (a saved epoch of --reference)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--first", type=int, default=0,
                   help="the first member's number: teacher i is exported as d<first + i> (a second run's members "
                        "beside the first's)")
    args = p.parse_args(argv)
    if args.first < 0:
        p.error(f"--first {args.first}: a member number >= 0")
    try:
        _, own = reference_moves(args.reference, args.epoch)
        if used := [d for i in range(len(own)) if (d := args.out / f"d{args.first + i}").exists()]:
            raise ValueError(f"--out {args.out}: {used[0]} exists (nothing is overwritten)")
    except ValueError as exc:
        p.error(str(exc))
    for i, move in enumerate(own):
        member = args.out / f"d{args.first + i}"
        try:  # (a checkpoint that is no teacher run, or has fewer teachers, fails at the first: nothing written)
            controller = export_teacher(args.checkpoint, i, member)
        except (ValueError, FileNotFoundError) as exc:
            p.error(str(exc))
        saved = read_controller(controller)
        card = member_card(args.first + i, np.load(member / "body.npy")[0], float(move), args.epoch,
                           int(saved.controller.init_kwargs["hidden"]), round(controller.stat().st_size / 1024))
        (member / "card.md").write_text(card)
        print(f"{member}: own move {move:.3f}")


if __name__ == "__main__":
    main()
