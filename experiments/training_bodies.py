"""More and more varied bodies to train teachers on (issue 56): generators that neither the held-out sets
(``experiments.heldout_bodies``: hand-built shapes, random accretion, the design env's stream at body_seed 10,000)
nor the population stream use, so that a student distilled from their teachers is still scored on bodies of kinds
it never saw.

* ``primitives``: a union of 2–5 parts, each a random box or ellipsoid (1–5 voxels a side) placed to overlap the
  body built so far, each part one material (passive, or one of the two muscle groups): limbs, trunks and pads
  whose muscles follow the parts, as an animal's do.
* ``blobs``: the set where a smooth random field (a sum of 3–6 Gaussian bumps) exceeds the level that gives a
  random size, its materials from a second, signed field of bumps (a muscle group where it is far from zero,
  passive near it): rounded bodies whose muscle regions are patches, not the held-out grown set's plane-wave
  stripes.

Every body is its largest 6-connected component, on the floor (lowest voxel at z = 0), between ``sizes`` voxels, with
voxels of both muscle groups; a grid equal to any held-out body is redrawn. Materials as the design env's (k = 4):
0 empty, 1 passive, 2 and 3 muscles in anti-phase.

    python -m experiments.training_bodies --kind mixed --n 128 --seed 1 --out runs/bodies_mixed128.npy
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from experiments.heldout_bodies import PASSIVE, RHO, A, B
from freeform.body import largest_component

SIZES = (12, 100)
"""Voxels a body may have: the held-out sets' range (12–100)."""

MUSCLES = (A, B)

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


def blob_body(rng: np.random.Generator) -> np.ndarray:
    """One ``blobs`` grid (module docstring), before the size and muscle checks."""
    shape = _bumps(rng, signed=False)
    size = int(rng.integers(*SIZES))
    filled = shape >= np.sort(shape, axis=None)[-size]
    muscle = _bumps(rng, signed=True)
    level = rng.uniform(0.1, 0.4) * np.abs(muscle[filled]).max()
    grid = np.where(muscle > level, A, np.where(muscle < -level, B, PASSIVE)).astype(np.uint8) * filled
    return _on_floor(grid.astype(np.uint8))


GENERATORS: dict[str, Callable[[np.random.Generator], np.ndarray]] = {"primitives": primitive_body,
                                                                       "blobs": blob_body}


def _heldout(folder: Path) -> set[bytes]:
    """The held-out sets' grids (``*.npy`` in ``folder``), as bytes, to compare against; a folder without any is
    refused (run from the repository's root, or give --heldout)."""
    files = sorted(folder.glob("*.npy"))
    if not files:
        raise ValueError(f"--heldout {folder}: no held-out sets (.npy) there to keep out of the training bodies")
    return {g.tobytes() for f in files for g in np.load(f, allow_pickle=False)}


def training_bodies(kind: str, n: int, seed: int, heldout: Path = Path("docs/results/heldout_bodies")) -> np.ndarray:
    """``[n, 8, 8, 8]`` uint8 bodies of generator ``kind`` (``primitives``, ``blobs``, or ``mixed``: both, in turn),
    drawn from ``seed``; none equal to a held-out body in ``heldout``."""
    if kind not in (*GENERATORS, "mixed"):
        raise ValueError(f"--kind must be one of {[*GENERATORS, 'mixed']}, got {kind!r}")
    if n < 1:
        raise ValueError(f"--n must be >= 1, got {n}")
    kinds = list(GENERATORS) if kind == "mixed" else [kind]
    rng, avoid, out = np.random.default_rng(seed), _heldout(heldout), []
    while len(out) < n:
        grid = GENERATORS[kinds[len(out) % len(kinds)]](rng)
        voxels = int((grid > 0).sum())
        if SIZES[0] <= voxels <= SIZES[1] and all((grid == m).any() for m in MUSCLES) and grid.tobytes() not in avoid:
            out.append(grid)
    return np.stack(out)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--kind", default="mixed", help="primitives, blobs, or mixed (both in turn)")
    p.add_argument("--n", type=int, default=128, help="how many bodies")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--heldout", default="docs/results/heldout_bodies", help="folder of held-out .npy sets to avoid")
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
