"""The zoo: trained controllers that ship in the wheel, each with a card (what it is, the command that trained it,
what it reaches and against what reference, its size).

    from freeform import zoo
    zoo.names()                  # ['student', 'pool256_gen4', …, 'wave']
    saved = zoo.load("student")  # a SavedController: .controller (the network), .control, .sim
    print(zoo.card("student"))

``student`` is the best single controller for bodies it never saw (zero-shot). The others of :data:`STUDENTS` are
the students that, tried once each on a body beside it, keep most of what trying all 17 committed students gains
(chosen greedily on the 93 held-out bodies, checked on 32 fresh ones); ``wave`` is the hand-set travelling wave in the
same network (the student with its learnt heads at zero), so that it too can be adapted. :data:`LIBRARY` holds
per-body controllers of training bodies (``library/d0`` …, each beside its ``body.npy``): on a body they were not
trained on each is weak, but the best of them is often near what the body needs. All play the same episode (2 s of
strokes, headings any), so that ``freeform-control fit`` tries them side by side (:data:`TRIED`) and adapts whichever
wins, by the recipe of its kind. :data:`STARTS` are what the presets in ``conf/experiment`` start from. A config names
any of them by name (``control.controller_init=population``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

ZOO = Path(__file__).resolve().parent
CONTROLLER_FILE = "controller.pt"
CARD = "card.md"
STUDENTS = ("student", "pool256_gen4", "pool256", "reptile3_fresh", "iterated64", "reptile3", "wave")
"""The students ``freeform-control fit`` tries on a body, in the order they were chosen (each added the most to the
best of those before it on the 93 held-out bodies)."""
LIBRARY = tuple(f"library/d{i}" for i in range(24))
"""Per-body controllers of 24 training bodies (the design env's untrained bodies, body_seed 0), 200 epochs each by
the per-body teachers' recipe (``library/card.md``)."""
TRIED = STUDENTS + LIBRARY
"""What ``freeform-control fit`` tries on a body, in this order (a tie goes to the earlier)."""
STEERING = ("student_steering", "population_steering")
"""What ``freeform-control fit --headings random`` tries on a body (steering: a heading drawn each episode), in this
order: the steering student and the steering population controller."""
STARTS = ("student_gen3", "population", "population_steering", "student_steering")
"""The controllers the presets start from (``control.controller_init``) and that their figures were measured with."""
ORDER = TRIED + STARTS


class UnknownController(ValueError):
    """A name that is neither one of the zoo's nor a path to a controller file."""


def names() -> list[str]:
    """The zoo's controllers, in :data:`ORDER`."""
    return list(ORDER)


def path(name: str) -> Path:
    """The ``controller.pt`` of the zoo's controller ``name`` (refused with the zoo's names where it has none)."""
    if name not in ORDER:
        raise UnknownController(f"{name!r} is not a controller of the zoo ({', '.join(ORDER)}) nor a controller.pt "
                                "file: give one of those names or a path to a controller.pt")
    return ZOO / name / CONTROLLER_FILE


def resolve(spec: str | Path) -> Path:
    """A controller as the command line names it: a zoo name (:func:`names`), else a path to a ``controller.pt``,
    a folder holding one or a control run's directory (``freeform.agents.controller_file.read_controller``)."""
    if str(spec) in ORDER:
        return path(str(spec))
    if Path(spec).exists():
        return Path(spec)
    raise UnknownController(f"no such checkpoint, controller.pt or run folder as {str(spec)!r}, nor a controller of "
                            f"the zoo ({', '.join(ORDER)}): give one of those names or a path to a controller.pt")


def load(name: str) -> Any:
    """The zoo's controller ``name`` read back (a ``freeform.agents.controller_file.SavedController``)."""
    from freeform.agents.controller_file import read_controller

    return read_controller(path(name))


def card(name: str) -> str:
    """The card of the zoo's controller ``name``: what it is, how it was trained, what it reaches."""
    return (path(name).parent / CARD).read_text()


__all__ = ["CARD", "LIBRARY", "ORDER", "STARTS", "STEERING", "STUDENTS", "TRIED", "UnknownController", "ZOO", "card", "load", "names", "path", "resolve"]
