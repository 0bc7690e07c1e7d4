"""Bodies no population run trains on (issue 42's generalisation test; a controller is scored on them by
``lab.heldout``): made by procedures the training stream
(``freeform.envs.population.design_cohort``: an untrained design policy placing 2³ bundles) never uses.

* ``hand_built``: shapes a person would draw on an 8³ grid — quadrupeds, tripods, bipeds, worms, crawlers, tables,
  arches, hoppers, wedges — in sizes and muscle layouts (front/back, left/right, alternating segments, top/bottom),
  each a connected body with voxels of both muscle groups.
* ``design_unseen``: for comparison, bodies of the training stream's own generator (an untrained design policy at
  locomotion_cpu's sizes) from a stream no run trains on (``body_seed`` 10,000): unseen bodies, not an unseen kind.
* ``grown``: random accretion (each body grown voxel by voxel from one seed voxel, a neighbour of the body chosen at
  random each time, biased along a random direction) with materials from a random smooth field (the sign of a
  random plane wave through the body: passive where it is near zero), a generator unlike the design env's bundles.

Materials as the design env's (k = 4): 0 empty, 1 passive, 2 and 3 muscles in anti-phase.

    python -m lab.heldout_bodies --out lab/results/heldout_bodies   # hand_built, grown, design_unseen .npy
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

RHO = 8
EMPTY, PASSIVE, A, B = 0, 1, 2, 3


def _box(g: np.ndarray, lo: tuple[int, int, int], hi: tuple[int, int, int], m: int) -> None:
    g[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = m


def hand_built() -> np.ndarray:
    """``[M, 8, 8, 8]`` uint8: the hand-built shapes (module docstring), each in a few sizes and muscle layouts."""
    bodies: list[np.ndarray] = []

    def add(g: np.ndarray) -> None:
        assert (g == A).any() and (g == B).any(), "a hand-built body has both muscle groups"
        bodies.append(g.astype(np.uint8))

    for length, legs_m in ((6, (A, B, B, A)), (8, (A, B, A, B)), (5, (A, A, B, B))):  # quadrupeds: a slab on 4 legs
        for torso in (PASSIVE, A):
            g = np.zeros((RHO,) * 3, np.uint8)
            _box(g, (0, 0, 2), (length, 4, 4), torso if torso == PASSIVE else A)
            if torso == A:
                _box(g, (length // 2, 0, 2), (length, 4, 4), B)
            for (x, y), m in zip(((0, 0), (0, 3), (length - 1, 0), (length - 1, 3)), legs_m, strict=True):
                _box(g, (x, y, 0), (x + 1, y + 1, 2), m)
            add(g)
    for width in (3, 5):  # tripods: a plate on three legs, each leg its own muscle group
        g = np.zeros((RHO,) * 3, np.uint8)
        _box(g, (0, 0, 2), (5, width, 3), PASSIVE)
        _box(g, (0, 0, 0), (1, 1, 2), A)
        _box(g, (0, width - 1, 0), (1, width, 2), A)
        _box(g, (4, width // 2, 0), (5, width // 2 + 1, 2), B)
        add(g)
    for height in (3, 5):  # bipeds: a torso on two legs of opposite groups
        g = np.zeros((RHO,) * 3, np.uint8)
        _box(g, (1, 1, height), (4, 4, height + 2), PASSIVE)
        _box(g, (1, 1, 0), (2, 4, height), A)
        _box(g, (3, 1, 0), (4, 4, height), B)
        add(g)
    for length, segment in ((8, 1), (8, 2), (6, 1), (7, 3)):  # worms: a bar of alternating segments
        g = np.zeros((RHO,) * 3, np.uint8)
        for x in range(length):
            _box(g, (x, 0, 0), (x + 1, 2, 2), A if (x // segment) % 2 == 0 else B)
        add(g)
    for depth in (2, 4):  # crawlers: a flat sheet, front muscles A, back muscles B, a passive middle
        g = np.zeros((RHO,) * 3, np.uint8)
        _box(g, (0, 0, 0), (7, 6, depth // 2), PASSIVE)
        _box(g, (0, 0, 0), (3, 6, depth // 2), A)
        _box(g, (4, 0, 0), (7, 6, depth // 2), B)
        add(g)
    for layout in ("left_right", "top_bottom", "front_back", "checker"):  # cubes of 4^3 in four muscle layouts
        g = np.zeros((RHO,) * 3, np.uint8)
        x, y, z = np.indices((4, 4, 4))
        split = {"left_right": y < 2, "top_bottom": z < 2, "front_back": x < 2, "checker": (x + y + z) % 2 == 0}[layout]
        g[:4, :4, :4] = np.where(split, A, B)
        add(g)
    for span in (5, 7):  # arches: two pillars of opposite groups and a passive beam
        g = np.zeros((RHO,) * 3, np.uint8)
        _box(g, (0, 0, 0), (1, 3, 3), A)
        _box(g, (span - 1, 0, 0), (span, 3, 3), B)
        _box(g, (0, 0, 3), (span, 3, 4), PASSIVE)
        add(g)
    for leg in (2, 3):  # tables: a top on four corner legs, diagonals paired
        g = np.zeros((RHO,) * 3, np.uint8)
        _box(g, (0, 0, leg), (6, 6, leg + 1), PASSIVE)
        for (x, y), m in zip(((0, 0), (5, 5), (0, 5), (5, 0)), (A, A, B, B), strict=True):
            _box(g, (x, y, 0), (x + 1, y + 1, leg), m)
        add(g)
    for foot in (2, 3):  # hoppers: a muscle A column on a muscle B foot
        g = np.zeros((RHO,) * 3, np.uint8)
        _box(g, (0, 0, 0), (foot, foot, 1), B)
        _box(g, (0, 0, 1), (2, 2, 5), A)
        add(g)
    for steps in (4, 6):  # wedges: a ramp of columns, rising muscles alternating
        g = np.zeros((RHO,) * 3, np.uint8)
        for x in range(steps):
            _box(g, (x, 0, 0), (x + 1, 3, x + 1), A if x % 2 == 0 else B)
        add(g)
    g = np.zeros((RHO,) * 3, np.uint8)  # an L: a passive foot and a muscle-pair upright
    _box(g, (0, 0, 0), (6, 2, 1), PASSIVE)
    _box(g, (0, 0, 1), (2, 2, 5), A)
    _box(g, (0, 0, 3), (2, 2, 5), B)
    add(g)
    return np.stack(bodies)


def grown(n: int, seed: int = 0, sizes: tuple[int, int] = (12, 90)) -> np.ndarray:
    """``[n, 8, 8, 8]`` uint8: random accretion with materials from a plane wave (module docstring); each body
    between ``sizes`` voxels, connected (6-neighbours), with both muscle groups."""
    rng = np.random.default_rng(seed)
    moves = np.array([(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)])
    out = []
    while len(out) < n:
        target = int(rng.integers(*sizes))
        bias = rng.normal(size=3) * np.array([1.0, 1.0, 0.4])
        cells = {(RHO // 2, RHO // 2, 0)}
        frontier = list(cells)
        while len(cells) < target:
            base = frontier[int(rng.integers(len(frontier)))]
            weights = np.exp(moves @ bias)
            step = moves[rng.choice(6, p=weights / weights.sum())]
            cell = tuple(int(c) for c in np.asarray(base) + step)
            if all(0 <= c < RHO for c in cell) and cell not in cells:
                cells.add(cell)
                frontier.append(cell)
        idx = np.array(sorted(cells))
        wave = rng.normal(size=3)
        wave /= np.linalg.norm(wave)
        phase = np.sin(2 * np.pi * (idx @ wave) / rng.uniform(3.0, 8.0) + rng.uniform(0, 2 * np.pi))
        material = np.where(phase > 0.3, A, np.where(phase < -0.3, B, PASSIVE))
        if not ((material == A).any() and (material == B).any()):
            continue
        g = np.zeros((RHO,) * 3, np.uint8)
        g[tuple(idx.T)] = material
        g = np.roll(g, -idx.min(0)[2], axis=2)  # (on the floor: the lowest voxel at z = 0)
        out.append(g)
    return np.stack(out)


def travelling_waves(sets: dict[str, np.ndarray], ks: tuple[float, ...] = (0.0, 0.5, 1.0, 1.5)) -> list[dict]:
    """One hand-set rule for every body: commands sin(2πt/T − k·x), x each voxel's place along x relative to its
    body's centre of mass (voxel lengths), in the population presets' window (1 s settling with zero commands, then
    2 s at a 0.025 s period, ramped, 26 /s) — the distance in the plane per body, averaged
    per set, beside the bodies' own sine gaits. Whether a rule that moves every kind of body exists at all."""
    import torch

    from freeform.envs.control import ControlConfig, ControlEnv, open_loop_displacement
    from freeform.sim import SimConfig

    control = ControlConfig(burn_in=1.0, duration=2.0, period=0.025, headings="any", ramp=True, command_rate=26.0)
    sim = SimConfig(burn_in=0.0)
    grids = np.concatenate(list(sets.values()))
    rows = [{"k": "open loop", **{name: float(open_loop_displacement(g, sim, control, planar=True).mean())
                                  for name, g in sets.items()}}]
    for k in ks:
        env = ControlEnv(grids, sim=sim, control=control)
        channel = {c: i for i, c in enumerate(env.channels)}
        obs, total = env.reset(), np.zeros(len(grids))
        for _ in range(control.steps):
            clock = torch.atan2(obs[:, channel["clock_sin"]], obs[:, channel["clock_cos"]])
            commands = torch.sin(clock - k * obs[:, channel["rel_x"]]) * obs[:, channel["filled"]]
            obs, reward, _, _ = env.step(commands.reshape(len(grids), -1))
            total += reward.numpy()
        row, start = {"k": k}, 0
        for name, g in sets.items():
            row[name], start = float(total[start:start + len(g)].mean()), start + len(g)
        rows.append(row)
        print(row)
    return rows


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="lab/results/heldout_bodies")
    p.add_argument("--grown", type=int, default=32, help="how many grown bodies")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--waves", action="store_true",
                   help="also move every body with one hand-set travelling wave (waves.csv; ~3 min on 2 cores)")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from freeform.envs.population import DesignBodies, design_cohort

    unseen = design_cohort(DesignBodies(), args.grown, 10_000, 0).numpy()
    sets = {"hand_built": hand_built(), "grown": grown(args.grown, args.seed), "design_unseen": unseen}
    for name, grids in sets.items():
        np.save(out / f"{name}.npy", grids)
        voxels = (grids > 0).reshape(len(grids), -1).sum(1)
        print(f"{name}: {len(grids)} bodies, {voxels.min()}-{voxels.max()} voxels (mean {voxels.mean():.0f}) -> "
              f"{out / (name + '.npy')}")

    if args.waves:
        from experiments.common import write_rows

        write_rows(out / "waves.csv", travelling_waves(sets))


if __name__ == "__main__":
    main()
