"""The training bodies' generators (``lab.training_bodies``): each body a connected robot on the floor, in
the held-out sets' size range, with both muscle groups; no held-out grid among them; a seed gives the same set. The
components are checked against scipy's labelling (an independent oracle)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from lab.training_bodies import SIZES, main, training_bodies


@pytest.mark.parametrize("kind", ["primitives", "blobs", "limbed", "cppn"])
def test_every_body_is_one_robot_on_the_floor_with_both_muscles(kind: str) -> None:
    grids = training_bodies(kind, 24, seed=3)
    assert grids.shape == (24, 8, 8, 8) and grids.dtype == np.uint8
    for g in grids:
        _, count = ndimage.label(g > 0)  # (6-connectivity: scipy's default structure)
        assert count == 1
        assert (g[:, :, 0] > 0).any()
        assert SIZES[0] <= (g > 0).sum() <= SIZES[1]
        assert set(np.unique(g)) >= {0, 2, 3} and g.max() <= 3
    assert len({g.tobytes() for g in grids}) == 24  # (no body twice)
    np.testing.assert_array_equal(training_bodies(kind, 24, seed=3), grids)
    assert not np.array_equal(training_bodies(kind, 24, seed=4), grids)


def test_no_held_out_body_is_drawn_and_bad_input_is_refused(tmp_path: Path) -> None:
    grids = training_bodies("mixed", 6, seed=0)
    heldout = tmp_path / "heldout"
    heldout.mkdir()
    # the third body drawn, held out shifted in a larger grid: still the same body, redrawn in its place
    shifted = np.zeros((1, 10, 10, 10), np.uint8)
    shifted[0, 2:10, 1:9, 0:8] = grids[2]
    np.save(heldout / "set.npy", shifted)
    again = training_bodies("mixed", 6, seed=0, heldout=heldout)
    assert not any(np.array_equal(g, grids[2]) for g in again)
    np.testing.assert_array_equal(again[:2], grids[:2])
    with pytest.raises(ValueError, match=r"--kind: \['cubes'\] not a generator"):
        training_bodies("limbed,cubes", 4, seed=0)
    with pytest.raises(SystemExit, match="must name a .npy"):
        main(["--n", "2", "--out", str(tmp_path / "bodies.txt")])
    main(["--kind", "blobs", "--n", "3", "--out", str(tmp_path / "b.npy")])
    np.testing.assert_array_equal(np.load(tmp_path / "b.npy"), training_bodies("blobs", 3, seed=1))
    with pytest.raises(ValueError, match="no held-out sets"):
        training_bodies("blobs", 2, seed=0, heldout=tmp_path / "nowhere")


def test_kinds_in_turn() -> None:
    """``a,b`` draws a body of a, then of b, in turn from one generator stream; ``mixed`` is ``primitives,blobs``
    (the sets the committed teachers trained on, drawn before the new kinds existed, stay bit for bit)."""
    np.testing.assert_array_equal(training_bodies("mixed", 6, seed=2), training_bodies("primitives,blobs", 6, seed=2))
    both = training_bodies("limbed,cppn", 6, seed=2)
    assert not np.array_equal(both, training_bodies("cppn,limbed", 6, seed=2))
    # (the first body is the first one the first kind's generator gives from the seed; the second is the other kind)
    np.testing.assert_array_equal(both[0], training_bodies("limbed", 1, seed=2)[0])
    assert not any(np.array_equal(both[1], g) for g in training_bodies("limbed", 12, seed=2))


def test_limbed_bodies_stand_on_separate_legs_under_a_wider_trunk() -> None:
    """Most ``limbed`` bodies touch the floor with two or more separate feet (scipy's labelling of the floor layer)
    under a layer wider than the floor's; a body lying flat (no legs) is the exception."""
    legged = 0
    for g in training_bodies("limbed", 60, seed=4):
        floor = g[:, :, 0] > 0
        _, feet = ndimage.label(floor)
        widest = max(int((g[:, :, z] > 0).sum()) for z in range(g.shape[2]))
        legged += feet >= 2 and widest > floor.sum()
    assert legged >= 30, legged


def test_a_generator_that_cannot_make_a_body_is_refused_not_looped_on(monkeypatch: pytest.MonkeyPatch) -> None:
    from lab import training_bodies as tb

    monkeypatch.setitem(tb.GENERATORS, "empty", lambda rng: np.zeros((8, 8, 8), np.uint8))
    with pytest.raises(ValueError, match=r"--kind limbed,empty: 1 of 3 bodies passed the checks .* in 300 draws"):
        tb.training_bodies("limbed,empty", 3, seed=0)
