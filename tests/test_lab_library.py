"""``lab.library``: a library of per-body controllers as fit's candidates, each body scored without its own."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from freeform.tables import write_rows
from lab.library import choices, expected_best, figures, main, summary, trials


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
    extra = [{**r, "trial_t3": "0.0"} for r in table()]  # (one more: every body's own would be another's column)
    with pytest.raises(ValueError, match="and no more"):
        choices(extra, "t", own=True)


@pytest.mark.parametrize("size", [1, 2, 3, 5])
def test_a_random_librarys_expected_best_equals_the_mean_over_every_draw(size: int) -> None:
    rng = np.random.default_rng(size)
    lib = rng.gamma(2.0, 1.0, (4, 6))
    lib[1, 3] = lib[2, 2] = lib[3, 5] = -np.inf         # a body's own: never drawn (5 left for those rows)
    lib[0, 0] = lib[0, 1]                               # ties count as one more draw each
    floor = np.array([0.0, 1.5, 2.0, 10.0])             # the last body's zoo trial beats every draw
    got = expected_best(floor, lib, size)
    for i in range(4):
        drawable = [v for v in lib[i] if np.isfinite(v)]
        draws = [max(floor[i], *c) for c in itertools.combinations(drawable, size)]
        assert got[i] == pytest.approx(np.mean(draws), rel=1e-12)
    assert got[3] == 10.0
    whole = expected_best(floor, lib, 5)                # the whole library less the own: its best, no chance
    assert whole[1:].tolist() == pytest.approx(np.maximum(floor, np.where(np.isfinite(lib), lib, 0).max(1))[1:])
    with pytest.raises(ValueError, match="can draw from 5 controllers only"):
        expected_best(floor, lib, 6)


def test_sizes_print_a_random_librarys_row(tmp_path, capsys) -> None:
    write_rows(tmp_path / "t.csv", table())
    main([str(tmp_path / "t.csv"), "--library", "t", "--own", "--sizes", "1,2"])
    out = capsys.readouterr().out
    # body 0 draws t1 (2.0) or t2 (0.1 → its zoo 1.0); body 1 always 1.0; body 2 t0 (1.5) or t1 (→ 1.0)
    assert "zoo and 1 of the library: 1.250" in out and "zoo and 2 of the library: 1.500" in out
    assert trials(table(), "t", own=True)[1][0, 0] == -np.inf
    with pytest.raises(SystemExit):
        main([str(tmp_path / "t.csv"), "--library", "t", "--own", "--sizes", "one"])
    assert "--sizes 'one'" in capsys.readouterr().err


def test_with_figures_a_pick_is_made_by_its_trial_and_scored_by_its_figure(tmp_path, capsys) -> None:
    """Steering: the trials are other headings than the figures. Each body's pick is the best trial (its own left
    out), its move that candidate's mean_command in its evaluate table — never the trial that chose it."""
    lib_figure = np.array([[7.0, 0.3, 5.0], [4.0, 7.0, 0.0], [0.1, 6.0, 7.0]])   # (another order than the trials')
    for j in range(3):
        write_rows(tmp_path / f"t{j}.csv", [{"body": i, "mean_command": lib_figure[i, j]} for i in range(3)])
    write_rows(tmp_path / "zoo1.csv", [{"body": i, "mean_command": 0.25 * (i + 1)} for i in range(3)])
    template = str(tmp_path / "{name}.csv")
    best = choices(table(), "t", own=True, scored=figures(table(), "t", template))
    assert best["zoo"].tolist() == [0.25, 0.5, 0.75]
    assert best["library"].tolist() == [0.3, 4.0, 0.1]                  # t1, t0 (a tie: the first), t0
    assert best["zoo and library"].tolist() == [0.3, 0.5, 0.1]          # body 1's library trial 0.5 < the zoo's 1.0
    rng = np.random.default_rng(0)
    lib, fig = rng.gamma(2.0, 1.0, (3, 5)), rng.gamma(2.0, 1.0, (3, 5))
    lib[0, 0] = -np.inf
    floor, floor_figure = np.array([0.0, 1.5, 2.0]), np.array([9.0, 8.0, 7.0])
    got = expected_best(floor, lib, 2, floor_figure, fig)
    for i in range(3):
        drawable = [j for j in range(5) if np.isfinite(lib[i, j])]
        moves = [fig[i, max(c, key=lambda j: lib[i, j])] if max(lib[i, list(c)]) > floor[i] else floor_figure[i]
                 for c in itertools.combinations(drawable, 2)]
        assert got[i] == pytest.approx(np.mean(moves), rel=1e-12)
    write_rows(tmp_path / "table.csv", table())
    main([str(tmp_path / "table.csv"), "--library", "t", "--own", "--figures", template, "--sizes", "1,2"])
    out = capsys.readouterr().out
    # one of the library drawn: body 0 t1 (0.3) or t2 (trial 0.1 < 1.0: the zoo's 0.25); body 1 the zoo's 0.5 either
    # way; body 2 t0 (0.1) or t1 (trial 0.2 < 1.0: the zoo's 0.75) — each by its trial, scored by its figure
    assert "zoo and library: 0.300" in out and "zoo and 1 of the library: 0.400" in out
    assert "zoo and 2 of the library: 0.300" in out
    for bad, message in ((str(tmp_path / "missing_{name}.csv"), "--figures: no "),
                         (str(tmp_path / "{name}{other}.csv"), "the only field it may hold"),
                         (str(tmp_path / "t.csv"), "must hold {name}")):
        with pytest.raises(SystemExit):
            main([str(tmp_path / "table.csv"), "--library", "t", "--figures", bad])
        assert message in capsys.readouterr().err
    write_rows(tmp_path / "t1.csv", [{"body": i, "mean_command": 0.0} for i in (0, 2, 1)])  # (another order)
    with pytest.raises(ValueError, match="not the table's"):
        figures(table(), "t", template)


def test_firsts_are_the_library_before_it_grew_and_the_rest_is_paired_against_them(tmp_path, capsys) -> None:
    """Without ``--own`` (a body's own controller may win): the first member alone moves body 0 by its own 9.0 and
    leaves body 1 to the zoo (t0 moves it 0.5); the rest add t1's 9.0 on body 1 and t2's on body 2."""
    first = choices(table(), "t", own=False, members=1)["zoo and library"]
    assert first.tolist() == [9.0, 1.0, 1.5]                     # (t0 on body 1 is 0.5: the zoo's 1.0 stays)
    assert choices(table(), "t", own=False, members=2)["zoo and library"].tolist() == [9.0, 9.0, 1.5]
    for k in (0, 3):
        with pytest.raises(ValueError, match=f"--firsts {k}"):
            choices(table(), "t", own=False, members=k)
    write_rows(tmp_path / "t.csv", table())
    main([str(tmp_path / "t.csv"), "--library", "t", "--firsts", "1"])
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("zoo and the library's first 1")][0]
    assert "the whole library over it +5.167" in line and "(2 bodies gain)" in line   # (mean of 0, 8.0, 7.5)
