"""``lab.library``: a library of per-body controllers as fit's candidates, each body scored without its own."""

from __future__ import annotations

import numpy as np
import pytest

from freeform.tables import write_rows
from lab.library import choices, main, summary


def table() -> list[dict[str, str]]:
    """Three bodies; the zoo's one candidate moves each 1.0; the library's t0–t2 move their own body 9.0 (the
    diagonal), body 0 is moved 2.0 by t1, body 1 0.5 by everything else, body 2 1.5 by t0."""
    lib = np.array([[9.0, 2.0, 0.1], [0.5, 9.0, 0.5], [1.5, 0.2, 9.0]])
    return [{"body": str(i), "trial_zoo1": "1.0", **{f"trial_t{j}": str(lib[i, j]) for j in range(3)}}
            for i in range(3)]


def test_each_body_is_chosen_for_without_its_own_controller_and_the_gain_is_paired(tmp_path, capsys) -> None:
    best = choices(table(), "t", own=True)
    assert best["zoo"].tolist() == [1.0, 1.0, 1.0]
    assert best["library"].tolist() == [2.0, 0.5, 1.5]          # (9.0, its own, never)
    assert best["zoo and library"].tolist() == [2.0, 1.0, 1.5]
    assert choices(table(), "t", own=False)["library"].tolist() == [9.0, 9.0, 9.0]
    rows = summary(best, reference=np.array([4.0, 2.0, 3.0]))
    both = rows[2]
    assert both["fraction"] == pytest.approx(4.5 / 9.0) and both["gain_over_zoo"] == pytest.approx(0.5)
    assert both["bodies_gaining"] == 2 and both["gain_band99"] > 0
    assert "gain_over_zoo" not in rows[0]
    write_rows(tmp_path / "t.csv", table())
    with pytest.raises(SystemExit):  # (a prefix that names no candidate: nothing to call the library)
        main([str(tmp_path / "t.csv"), "--library", "x"])
    assert "the prefix must name some" in capsys.readouterr().err
    short = [{k: v for k, v in r.items() if k != "trial_t2"} for r in table()]
    with pytest.raises(ValueError, match="the library needs one for every body"):
        choices(short, "t", own=True)
