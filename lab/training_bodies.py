"""More and more varied bodies to train teachers on (issue 56): generators that neither the held-out sets
(``lab.heldout_bodies``: hand-built shapes, random accretion, the design env's stream at body_seed 10,000)
nor the population stream use, so that a student distilled from their teachers is still scored on bodies of kinds
it never saw.

* ``primitives``: a union of 2–5 parts, each a random box or ellipsoid (1–5 voxels a side) placed to overlap the
  body built so far, each part one material (passive, or one of the two muscle groups): limbs, trunks and pads
  whose muscles follow the parts, as an animal's do.
* ``blobs``: the set where a smooth random field (a sum of 3–6 Gaussian bumps) exceeds the level that gives a
  random size, its materials from a second, signed field of bumps (a muscle group where it is far from zero,
  passive near it): rounded bodies whose muscle regions are patches, not the held-out grown set's plane-wave
  stripes.
* ``limbed``: a trunk (a box 2–5 voxels long and wide, 1–3 high) on 0–3-voxel legs (2, 3, 4 or 6 columns, one or
  two voxels thick, under its rim, some with a foot splayed outward), with 0–2 horizontal limbs (tails, arms) off its
  sides; each limb one muscle group, diagonal legs alike (a trot's pairing) or at random, the trunk mostly passive. The
  hand-built held-out set has quadrupeds and tripods of fixed proportions: this kind is nearest to it.
* ``cppn``: a compositional pattern-producing network's pattern (EvoGym's and the soft-robot literature's
  generator): a random two-layer network of sines, Gaussians, tanh and |·| over each cell's coordinates and its
  distance from the centre gives a shape field (its top cells, to a random size) and three material scores (the
  largest wins): repeated and mirrored parts, stripes and rings, unlike a sum of bumps.

Every body is its largest 6-connected component, on the floor (lowest voxel at z = 0), between ``sizes`` voxels, with
voxels of both muscle groups; a held-out body, wherever it sits in its grid, is redrawn. Materials as the design
env's (k = 4): 0 empty, 1 passive, 2 and 3 muscles in anti-phase.

    python -m lab.training_bodies --kind mixed --n 128 --seed 1 --out runs/bodies_mixed128.npy
    python -m lab.training_bodies --kind limbed,cppn --n 128 --seed 3 --out runs/bodies_limbed_cppn128.npy

``--kind`` names one generator, or several separated by commas taken in turn (``mixed``: ``primitives,blobs``).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from freeform.body import largest_component
from lab.heldout_bodies import PASSIVE, RHO, A, B

SIZES = (12, 100)
"""Voxels a body may have: the held-out sets' range (12–100)."""

MUSCLES = (A, B)

MAX_DRAWS = 100
"""Draws allowed a body before a generator is taken to be unable to make one (the kinds pass 18–69 % of draws:
primitives 34, blobs 36, limbed 69, cppn 18 % of 1,000 from seed 0)."""

CELLS = np.stack(np.meshgrid(*[np.arange(RHO)] * 3, indexing="ij"), -1).astype(float)
"""Every cell's coordinates, ``[ρ, ρ, ρ, 3]``: where the parts and the fields are evaluated."""


def _on_floor(grid: np.ndarray) -> np.ndarray:
    """``grid`` (its largest component) with its lowest voxel at z = 0."""
    grid = largest_component(torch.from_numpy(grid[None]))[0].numpy()
    z = np.nonzero(grid.any(axis=(0, 1)))[0]
    return np.roll(grid, -int(z[0]), axis=2) if len(z) else grid


def _part(rng: np.random.Generator, centre: np.ndarray) -> np.ndarray:
    """A random box or ellipsoid (half-sizes 0.5–2.5 voxels) about ``centre``: bool ``[ρ, ρ, ρ]``."""
    half = rng.uniform(0.5, 2.5, size=3)
    cells = CELLS - centre
    if rng.random() < 0.5:
        return (np.abs(cells) <= half).all(-1)
    return ((cells / (half + 0.5)) ** 2).sum(-1) <= 1.0


def primitive_body(rng: np.random.Generator) -> np.ndarray:
    """One ``primitives`` grid (module docstring), before the size and muscle checks."""
    grid = np.zeros((RHO,) * 3, np.uint8)
    centre = rng.uniform(2.0, RHO - 3.0, size=3) * np.array([1.0, 1.0, 0.5])
    for _ in range(int(rng.integers(2, 6))):
        part = _part(rng, centre) & (grid == 0)
        grid[part] = rng.choice([PASSIVE, A, B], p=[0.3, 0.35, 0.35])
        filled = np.argwhere(grid > 0)
        if len(filled):  # (the next part about a cell of the body: the parts overlap or touch)
            centre = filled[int(rng.integers(len(filled)))] + rng.normal(0.0, 1.5, size=3)
    return _on_floor(grid)


def _bumps(rng: np.random.Generator, signed: bool) -> np.ndarray:
    """A sum of 3–6 Gaussian bumps (widths 1–3 voxels) over the grid's cells, each ±1 if ``signed``."""
    field = np.zeros((RHO,) * 3)
    for _ in range(int(rng.integers(3, 7))):
        centre = rng.uniform(0.0, RHO - 1.0, size=3) * np.array([1.0, 1.0, 0.6])
        width = rng.uniform(1.0, 3.0)
        sign = rng.choice([-1.0, 1.0]) if signed else 1.0
        field += sign * np.exp(-((CELLS - centre) ** 2).sum(-1) / (2 * width**2))
    return field


def _top(field: np.ndarray, size: int) -> np.ndarray:
    """The ``size`` cells where ``field`` is largest (ties kept): bool ``[ρ, ρ, ρ]``."""
    return field >= np.sort(field, axis=None)[-size]


def blob_body(rng: np.random.Generator) -> np.ndarray:
    """One ``blobs`` grid (module docstring), before the size and muscle checks."""
    shape = _bumps(rng, signed=False)
    filled = _top(shape, int(rng.integers(*SIZES)))
    muscle = _bumps(rng, signed=True)
    level = rng.uniform(0.1, 0.4) * np.abs(muscle[filled]).max()
    grid = np.where(muscle > level, A, np.where(muscle < -level, B, PASSIVE)).astype(np.uint8) * filled
    return _on_floor(grid.astype(np.uint8))


def limbed_body(rng: np.random.Generator) -> np.ndarray:
    """One ``limbed`` grid (module docstring), before the size and muscle checks."""
    grid = np.zeros((RHO,) * 3, np.uint8)
    size = rng.integers([2, 2, 1], [6, 6, 4])
    leg = int(rng.integers(0, 4))
    lo = np.array([*(rng.integers(1, RHO - size[:2]) if leg else rng.integers(0, RHO - size[:2] + 1)), leg])
    hi = lo + size  # (at most 3 + 3 high: the trunk always fits under the ceiling)
    grid[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = rng.choice([PASSIVE, A, B], p=[0.6, 0.2, 0.2])
    mid = (lo[1] + hi[1] - 1) // 2
    corners = list(dict.fromkeys([(lo[0], lo[1]), (hi[0] - 1, hi[1] - 1), (hi[0] - 1, lo[1]), (lo[0], hi[1] - 1),
                                  (lo[0], mid), (hi[0] - 1, mid)]))  # (a trunk 2 wide has no middle legs of its own)
    count = int(rng.choice([2, 3, 4, 6])) if leg else 0
    trot = rng.random() < 0.5
    for x, y in corners[:count]:
        m = (A if (x == lo[0]) == (y == lo[1]) else B) if trot else int(rng.choice(MUSCLES))  # (trot: diagonals alike)
        t = int(rng.integers(1, 3))
        out = np.sign([x - (lo[0] + hi[0] - 1) / 2, y - (lo[1] + hi[1] - 1) / 2]).astype(int)
        xs = slice(x, x + t) if out[0] <= 0 else slice(x - t + 1, x + 1)  # (thick legs grow inward, x - 1 >= 0)
        ys = slice(y, y + t) if out[1] <= 0 else slice(y - t + 1, y + 1)
        grid[xs, ys, 0:leg] = m
        if rng.random() < 0.4:  # (a foot splayed outward along one axis: it shares a face with its leg)
            foot = [x, y, 0]
            axis = int(rng.choice(np.flatnonzero(out))) if out.any() else 0
            foot[axis] = int(np.clip(foot[axis] + (out[axis] or 1), 0, RHO - 1))
            grid[tuple(foot)] = m
    for _ in range(int(rng.integers(0, 3))):  # (tails and arms at the trunk's height)
        axis, side = int(rng.integers(2)), int(rng.choice([-1, 1]))
        z = int(rng.integers(lo[2], hi[2]))
        other = int(rng.integers(lo[1 - axis], hi[1 - axis]))
        start = hi[axis] if side > 0 else lo[axis] - 1
        cells = [start + side * k for k in range(int(rng.integers(1, 4)))]
        cells = [c for c in cells if 0 <= c < RHO]
        idx = [0, 0, z]
        m = int(rng.choice(MUSCLES))
        for c in cells:
            idx[axis], idx[1 - axis] = c, other
            grid[tuple(idx)] = m
    return _on_floor(grid)


ACTIVATIONS: tuple[Callable[[np.ndarray], np.ndarray], ...] = (
    np.sin, lambda v: np.exp(-v**2), np.tanh, np.abs)
"""A CPPN node's functions: periodic, bell, sigmoid-like and mirror-symmetric."""


def cppn_body(rng: np.random.Generator) -> np.ndarray:
    """One ``cppn`` grid (module docstring), before the size and muscle checks."""
    centre = (RHO - 1) / 2
    coords = (CELLS - centre) / centre  # (each axis in [-1, 1])
    layer = np.concatenate([coords, np.linalg.norm(coords, axis=-1, keepdims=True),
                            np.ones(coords.shape[:-1] + (1,))], -1).reshape(-1, 5)
    for width in (int(rng.integers(3, 6)), int(rng.integers(3, 6))):
        weights = rng.normal(0.0, 1.5, size=(layer.shape[1], width))
        acts = rng.integers(len(ACTIVATIONS), size=width)
        pre = layer @ weights
        layer = np.stack([ACTIVATIONS[a](pre[:, j]) for j, a in enumerate(acts)], -1)
    out = (layer @ rng.normal(0.0, 1.0, size=(layer.shape[1], 4))).reshape((RHO,) * 3 + (4,))
    size = int(rng.integers(*SIZES))
    filled = _top(out[..., 0] - 0.5 * (coords[..., 2] + 1), size)  # (pulled towards the floor, to stand on it)
    return _on_floor((np.argmax(out[..., 1:], -1) + PASSIVE).astype(np.uint8) * filled)


GENERATORS: dict[str, Callable[[np.random.Generator], np.ndarray]] = {
    "primitives": primitive_body, "blobs": blob_body, "limbed": limbed_body, "cppn": cppn_body}

ALIASES = {"mixed": "primitives,blobs"}


def _shape(grid: np.ndarray) -> bytes:
    """A body up to where it sits in its grid: its bounding box's size and cells, as bytes."""
    filled = np.nonzero(grid)
    crop = grid[tuple(slice(int(i.min()), int(i.max()) + 1) for i in filled)] if filled[0].size else grid[:0, :0, :0]
    return np.asarray(crop.shape, np.int64).tobytes() + np.ascontiguousarray(crop, np.uint8).tobytes()


def _heldout(folder: Path) -> set[bytes]:
    """The held-out sets' bodies (``*.npy`` in ``folder``) up to a shift (:func:`_shape`), to compare against; a
    folder without any is refused (run from the repository's root, or give --heldout)."""
    files = sorted(folder.glob("*.npy"))
    if not files:
        raise ValueError(f"--heldout {folder}: no held-out sets (.npy) there to keep out of the training bodies")
    return {_shape(g) for f in files for g in np.load(f, allow_pickle=False)}


def training_bodies(kind: str, n: int, seed: int, heldout: Path = Path("lab/results/heldout_bodies")) -> np.ndarray:
    """``[n, 8, 8, 8]`` uint8 bodies of generator ``kind`` (one of :data:`GENERATORS`, several separated by commas
    taken in turn, or an alias: ``mixed`` = ``primitives,blobs``), drawn from ``seed``; none a held-out body of
    ``heldout`` or one shifted in its grid."""
    kinds = ALIASES.get(kind, kind).split(",")
    unknown = [k for k in kinds if k not in GENERATORS]
    if unknown:
        raise ValueError(f"--kind: {unknown} not a generator; give one of {[*GENERATORS, *ALIASES]} or several "
                         f"separated by commas, got {kind!r}")
    if n < 1:
        raise ValueError(f"--n must be >= 1, got {n}")
    rng, avoid, out = np.random.default_rng(seed), _heldout(heldout), []
    for _ in range(MAX_DRAWS * n):
        if len(out) == n:
            break
        grid = GENERATORS[kinds[len(out) % len(kinds)]](rng)
        voxels = int((grid > 0).sum())
        if SIZES[0] <= voxels <= SIZES[1] and all((grid == m).any() for m in MUSCLES) and _shape(grid) not in avoid:
            out.append(grid)
    if len(out) < n:
        raise ValueError(f"--kind {kind}: {len(out)} of {n} bodies passed the checks (connected, {SIZES[0]}–"
                         f"{SIZES[1]} voxels, both muscles, not held out) in {MAX_DRAWS * n} draws; a generator "
                         f"must make such a body in at least 1 of {MAX_DRAWS} draws — fix it, or leave it out of "
                         f"--kind")
    return np.stack(out)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--kind", default="mixed",
                   help=f"one of {[*GENERATORS]}, several separated by commas (taken in turn), or mixed "
                        f"(= {ALIASES['mixed']})")
    p.add_argument("--n", type=int, default=128, help="how many bodies")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--heldout", default="lab/results/heldout_bodies", help="folder of held-out .npy sets to avoid")
    p.add_argument("--out", required=True, help="the .npy to write (uint8 [n, 8, 8, 8])")
    args = p.parse_args(argv)
    out = Path(args.out)
    if out.suffix != ".npy":
        raise SystemExit(f"--out must name a .npy file, got {out}")
    grids = training_bodies(args.kind, args.n, args.seed, Path(args.heldout))
    out.parent.mkdir(parents=True, exist_ok=True)
    np.save(out, grids)
    voxels = (grids > 0).reshape(len(grids), -1).sum(1)
    print(f"{args.kind}: {len(grids)} bodies, {voxels.min()}-{voxels.max()} voxels (mean {voxels.mean():.0f}) -> {out}")


if __name__ == "__main__":
    main()
