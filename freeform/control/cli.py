"""``freeform-control``: drive bodies of your own with trained controllers.

    freeform-control zoo                                          # the controllers that ship with freeform
    freeform-control evaluate student my_bodies.npy --out eval    # bodies.csv, summary.csv
    freeform-control watch student my_body.npy --out seen         # gait.gif, gait.json
    freeform-control fit my_bodies.npy --out fitted               # fitted/body<i>/controller.pt, bodies.csv
    freeform-control fit my_bodies.npy --headings random --out f  # the same for steering (a heading each episode)
    freeform-control gate student pool256 --trial 0.25 --out g.pt  # one controller that tries both, keeps the best

CONTROLLER is a zoo name or a path to a ``controller.pt`` (a folder holding one, a control run's directory).
BODIES is a ``.npy`` of uint8 grids ``[M, ρ, ρ, ρ]`` or one ``[ρ, ρ, ρ]``: 0 empty, 1 passive, 2 and 3 muscles in
anti-phase. Moves are in voxel lengths over the controller's 2 s control window. Bad input ends in one line,
``freeform-control: error: ...``, before anything is written.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from freeform.control.evaluate import EPISODES
from freeform.control.fit import DEFAULT_ADAPT_EPOCHS, TRIAL_EPISODES
from freeform.envs.control_config import HEADINGS


def _controller(spec: str, grids) -> object:
    """The controller ``spec`` (a zoo name or a path) built for a box that holds ``grids``."""
    from freeform.agents.controller_file import controller_for
    from freeform.zoo import resolve

    return controller_for(resolve(spec), grids)


def _bodies(path: str, spec: str | None = None):
    """The bodies of ``path`` in the materials of controller ``spec``'s simulator (the zoo's where None)."""
    from freeform.agents.controller_file import read_controller
    from freeform.control.bodies import read_bodies
    from freeform.sim import SimConfig
    from freeform.zoo import TRIED, resolve

    saved = read_controller(resolve(spec if spec is not None else TRIED[0]))
    return read_bodies(path, len((saved.sim or SimConfig()).materials))


def cmd_zoo(args: argparse.Namespace) -> None:
    from freeform import zoo

    def first_line(card: str) -> str:
        return next((line for line in card.splitlines() if line and not line.startswith("#")), "")

    library = f"{zoo.LIBRARY[0]} … {zoo.LIBRARY[-1]}"  # one line: the members' cards say the same but for the body
    for name in zoo.names():
        if name in zoo.LIBRARY[1:]:
            continue
        if name == zoo.LIBRARY[0]:
            print(f"{library:20s} {first_line((zoo.ZOO / 'library' / zoo.CARD).read_text())}")
        else:
            print(f"{name:20s} {first_line(zoo.card(name))}")
    tried = [n for n in zoo.TRIED if n not in zoo.LIBRARY] + [library]
    print(f"\n(the files: {zoo.ZOO}; `fit` tries {', '.join(tried)}, `fit --headings random` "
          f"{', '.join(zoo.STEERING)}; `zoo.card(name)` or card.md beside each controller.pt says what it is)")


def cmd_evaluate(args: argparse.Namespace) -> None:
    from freeform.control.evaluate import evaluate, summary, write

    grids = _bodies(args.bodies, args.controller)
    saved = _controller(args.controller, grids)
    rows = evaluate(saved, grids, args.episodes, args.headings)
    write(Path(args.out), rows)
    for row in summary(rows):
        print(f"{row['what']}: {row['mean']:.3f}" + (f" ± {row['band99']:.3f}" if "band99" in row else ""))


def cmd_watch(args: argparse.Namespace) -> None:
    from freeform.control.watch import watch, writable

    writable(args.video)
    grids = _bodies(args.bodies, args.controller)
    if args.body is None and len(grids) > 1:
        raise ValueError(f"watch {args.bodies}: the file holds {len(grids)} bodies: say which with --body I")
    figures = watch(_controller(args.controller, grids), grids, Path(args.out), args.fps, args.video, args.headings,
                    args.body or 0)
    print(json.dumps(figures, indent=1))


def cmd_fit(args: argparse.Namespace) -> None:
    from freeform.agents.controller_file import read_controller
    from freeform.control.fit import Fit, fit, no_earlier_fit
    from freeform.zoo import STEERING, TRIED, resolve

    out = Path(args.out)
    no_earlier_fit(out)
    candidates = tuple(args.candidates or (STEERING if args.headings == "random" else TRIED))
    how = Fit(candidates, args.trial, args.adapt_epochs, args.copies, seed=args.seed, curve_every=args.curve_every,
              adapt_seconds=args.adapt_seconds,
              settings=tuple(args.set), trial_episodes=args.trial_episodes,
              episodes=args.episodes)  # (checked before the bodies are read)
    own = read_controller(resolve(candidates[0])).control.headings
    if args.headings is not None and args.headings != own:
        raise ValueError(f"--headings {args.headings}: candidate {candidates[0]} plays headings {own!r}, and fit keeps "
                         f"each candidate's own task: give candidates of that task (the zoo's: "
                         f"{', '.join(STEERING)} along random headings, the rest headings any)")
    grids = _bodies(args.bodies, how.candidates[0])
    rows = fit(grids, out, how)
    for row in rows:
        print(f"body {row['body']}: {row['chosen']}, {row['mean_command']:.3f} voxel lengths "
              f"-> {row['controller_file']}")
    print(f"{rows[0]['seconds']:.1f} s a body; {out / 'bodies.csv'}")


def cmd_gate(args: argparse.Namespace) -> None:
    from freeform.agents.controller_file import read_controller
    from freeform.control.fit import gate

    saved = read_controller(gate(tuple(args.controllers), args.trial, Path(args.out)))
    seconds = saved.controller.trial * saved.control.decision_seconds
    print(f"{saved.path}: tries {', '.join(args.controllers)} for {seconds:g} s each (whole decisions), then plays "
          "the best; evaluate, watch and fit play it as any controller")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="freeform-control", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("zoo", help="list the zoo's controllers").set_defaults(run=cmd_zoo)
    e = sub.add_parser("evaluate", help="a controller on bodies: bodies.csv and summary.csv")
    e.add_argument("controller", help="a zoo name or a controller.pt")
    e.add_argument("bodies", help="a .npy of uint8 grids [M, ρ, ρ, ρ] or [ρ, ρ, ρ]")
    e.add_argument("--out", required=True)
    e.add_argument("--headings", choices=HEADINGS, default=None, help="the task (default: the controller's own)")
    e.add_argument("--episodes", type=int, default=EPISODES, help="episodes a body (the stochastic column's; "
                                                                  "along random headings the mean command's too)")
    e.set_defaults(run=cmd_evaluate)
    w = sub.add_parser("watch", help="one body's gait under a controller: gait.gif and gait.json")
    w.add_argument("controller", help="a zoo name or a controller.pt")
    w.add_argument("bodies", help="a .npy of one uint8 grid [ρ, ρ, ρ], or several [M, ρ, ρ, ρ] with --body")
    w.add_argument("--body", type=int, default=None, metavar="I", help="which body of the file (its row in "
                                                                         "evaluate's bodies.csv)")
    w.add_argument("--out", required=True)
    w.add_argument("--fps", type=float, default=40.0, help="frames per second (the nearest a whole number of "
                                                          "control periods gives)")
    w.add_argument("--video", choices=("gif", "mp4"), default="gif", help="mp4 needs pip install 'freeform[video]'")
    w.add_argument("--headings", choices=HEADINGS, default=None)
    w.set_defaults(run=cmd_watch)
    f = sub.add_parser("fit", help="a controller for each body: the zoo tried, the best kept and adapted")
    f.add_argument("bodies", help="a .npy of uint8 grids [M, ρ, ρ, ρ] or [ρ, ρ, ρ]")
    f.add_argument("--out", required=True)
    f.add_argument("--trial", type=float, default=None, metavar="SECONDS",
                   help="choose by the move after this many seconds of each candidate (default: the whole episode)")
    f.add_argument("--adapt-epochs", type=int, default=None, metavar="E",
                   help=f"epochs of PPO on each body from its chosen controller (0: trials alone; default "
                        f"{DEFAULT_ADAPT_EPOCHS}; with --adapt-seconds, the most it runs)")
    f.add_argument("--adapt-seconds", type=float, default=None, metavar="S",
                   help="adapt for as many epochs as fit in S seconds a body, trials included (e.g. 60)")
    f.add_argument("--copies", type=int, default=4, help="environments per body in the adaptation")
    f.add_argument("--candidates", nargs="+", default=None, metavar="CONTROLLER",
                   help="what to try (zoo names or controller.pt files; default: the zoo's for the task)")
    f.add_argument("--headings", choices=HEADINGS, default=None,
                   help="the task: 'random' fits steering controllers (a heading drawn each episode: the zoo's "
                        "student_steering, population_steering), 'any' walkers (default: the candidates' own)")
    f.add_argument("--episodes", type=int, default=None, metavar="K",
                   help=f"steering: episodes a body's figure averages, evaluate's (default {EPISODES})")
    f.add_argument("--trial-episodes", type=int, default=None, metavar="N",
                   help=f"steering: episodes a trial averages, along headings after the figures' (default "
                        f"{TRIAL_EPISODES})")
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--curve-every", type=int, default=0, metavar="K",
                   help="measure the bodies every K adaptation epochs into adaptation.csv and adaptation_bodies.csv (0: never)")
    f.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="change the adaptation's recipes (the control_adapt_cpu and control_teachers_cpu presets' "
                        "and their steering twins'), e.g. --set agent.lr=1e-3; repeatable")
    f.set_defaults(run=cmd_fit)
    g = sub.add_parser("gate", help="one controller that tries several within an episode and keeps the best")
    g.add_argument("controllers", nargs="+", metavar="CONTROLLER", help="zoo names or controller.pt files, tried in "
                                                                       "this order")
    g.add_argument("--trial", type=float, required=True, metavar="SECONDS", help="how long each is tried")
    g.add_argument("--out", required=True, help="the controller.pt to write (a new file)")
    g.set_defaults(run=cmd_gate)
    return p


def main(argv: list[str] | None = None) -> None:
    p = parser()
    args = p.parse_args(argv)
    try:
        args.run(args)
    except (ValueError, FileExistsError, FileNotFoundError) as e:
        print(f"freeform-control: error: {e}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
