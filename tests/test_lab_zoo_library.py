"""``lab.zoo_library``: a member's card states its body and its own move as they are."""

from __future__ import annotations

import numpy as np
import pytest

from freeform.tables import write_rows
from lab.zoo_library import main, member_card


def test_a_members_card_counts_its_body_and_names_its_own_move() -> None:
    body = np.zeros((4, 4, 4), np.uint8)
    body[1:4, 2, 0] = [2, 1, 3]       # a bar of three along x, a muscle at each end
    body[1, 2, 1] = 1                  # and a passive voxel above the first
    card = member_card(5, body, own=1.23456, epoch=240, hidden=16, kib=76)
    assert card.startswith("# library/d5\n")
    assert "4 voxels (2 passive, 2 muscle)" in card and "box 3 × 1 × 2." in card
    assert "**1.235** voxel lengths" in card and "for 240 epochs" in card and "16 wide" in card
    assert "`[1, 4, 4, 4]`" in card and "76 KiB" in card


def test_an_existing_member_is_refused_and_kept(tmp_path, capsys) -> None:
    write_rows(tmp_path / "ref" / "bodies.csv", [{"body": 0, "epoch240": 1.0}, {"body": 1, "epoch240": 2.0}])
    (tmp_path / "zoo" / "d1").mkdir(parents=True)
    (tmp_path / "zoo" / "d1" / "card.md").write_text("mine")
    with pytest.raises(SystemExit):
        main([str(tmp_path / "nosuch.pt"), "--reference", str(tmp_path / "ref"), "--epoch", "240",
              "--out", str(tmp_path / "zoo")])
    assert "d1 exists (nothing is overwritten)" in capsys.readouterr().err
    assert (tmp_path / "zoo" / "d1" / "card.md").read_text() == "mine" and not (tmp_path / "zoo" / "d0").exists()


def test_a_checkpoint_that_is_no_teacher_run_is_refused_and_nothing_written(tmp_path, capsys) -> None:
    write_rows(tmp_path / "ref" / "bodies.csv", [{"body": 0, "epoch240": 1.0}])
    with pytest.raises(SystemExit):
        main([str(tmp_path / "nosuch.pt"), "--reference", str(tmp_path / "ref"), "--epoch", "240",
              "--out", str(tmp_path / "zoo")])
    assert "nosuch.pt" in capsys.readouterr().err and not (tmp_path / "zoo").exists()


def test_a_second_runs_members_are_numbered_after_the_first_and_an_existing_one_refused(tmp_path, capsys) -> None:
    """``--first 8``: teacher 0 of the run is d8; d8 existing is refused and kept, d0 beside it is no obstacle."""
    write_rows(tmp_path / "ref" / "bodies.csv", [{"body": 0, "epoch200": 1.0}, {"body": 1, "epoch200": 2.0}])
    (tmp_path / "zoo" / "d0").mkdir(parents=True)
    (tmp_path / "zoo" / "d8").mkdir(parents=True)
    with pytest.raises(SystemExit):
        main([str(tmp_path / "nosuch.pt"), "--reference", str(tmp_path / "ref"), "--epoch", "200",
              "--out", str(tmp_path / "zoo"), "--first", "8"])
    assert "d8 exists (nothing is overwritten)" in capsys.readouterr().err
    (tmp_path / "zoo" / "d8").rmdir()
    with pytest.raises(SystemExit):  # (past the check on d8, d9: the checkpoint is the next refusal)
        main([str(tmp_path / "nosuch.pt"), "--reference", str(tmp_path / "ref"), "--epoch", "200",
              "--out", str(tmp_path / "zoo"), "--first", "8"])
    assert "nosuch.pt" in capsys.readouterr().err and not (tmp_path / "zoo" / "d8").exists()
