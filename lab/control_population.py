"""The population controller's results across seeds and held-out sets, in one table and one figure (issue 42;
``docs/control.md``, "A travelling-wave head").

Reads what ``python -m lab.control --evaluate RUN --bodies SET.npy`` wrote for each training seed and set,
kept as ``RESULTS/seed<S>_<SET>_bodies.csv``, and each seed's training curve ``RESULTS/seed<S>.curve.csv``
(``epoch, reward_mean``), and writes:

* ``RESULTS/all_sets.csv``: per seed, over every held-out body of every set together, the means with 99 % bands
  across bodies (open loop, the controller stochastic and its mean command, the untrained controller stochastic and
  its mean command), the three paired differences per body, the ratio of the mean command's mean to the open
  loop's, and how many bodies the mean command moves beyond their own gait;
* ``RESULTS/control_population.png``: the training return per epoch of each seed, and per set the open-loop gaits,
  the untrained controller's mean command and the trained one's, with their 99 % bands.

    python -m lab.control_population --results lab/results/control_population

``--steer-waves``: instead, where the hand-set wave takes the held-out bodies when it travels along a heading, or at
an angle to it — the steering preset's wave head playing the hand-set wave exactly (its per-cell outputs 0), its wave
vector set to k·(cos o, sin o, 0) in the heading's frame (x along the heading), on every held-out body along random headings: the mean move along the
heading per set, k and offset o (``RESULTS/steer_waves.csv``; ≈ 5 min on 2 cores):

    python -m lab.control_population --steer-waves --results lab/results/control_population_steering

``--steer-feedback``: the same hand-set wave along the heading, turned after every control step by a gain times the
angle between the heading and the way the body moved over that step (integral feedback on the heading error): per
gain and set, the mean move along the heading (``RESULTS/steer_feedback.csv``; ≈ 2 min):

    python -m lab.control_population --steer-feedback --results lab/results/control_population_steering

``--steer-amplitudes``: the hand-set wave along the heading (k = 1.5, 1.0 and 2.0) at amplitudes from the sine's 1 up:
what a muscle receives stays within [−1, 1] and its bandwidth, so a larger amplitude asks for a fuller stroke, not a
larger one; per amplitude and set, the mean move along the heading (``RESULTS/steer_amplitudes.csv``; ≈ 3 min):

    python -m lab.control_population --steer-amplitudes --results lab/results/control_population_steering
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np

from experiments.common import mean_band, paired_band, pyplot, read_csv, write_rows

SETS = ("design_unseen", "grown", "hand_built")
COLUMNS = ("open_loop", "controller", "mean_command", "untrained", "untrained_mean_command")
PAIRS = (("mean_command", "open_loop"), ("controller", "untrained"), ("mean_command", "untrained_mean_command"))


def body_columns(results: Path, seed: int, name: str) -> dict[str, np.ndarray]:
    """One seed's ``bodies.csv`` of set ``name``: its columns, numeric ones as float arrays."""
    return read_csv(results / f"seed{seed}_{name}_bodies.csv")[1]


def seeds_in(results: Path) -> list[int]:
    """The seeds with a body table for every set (``seed<S>_<SET>_bodies.csv``), in order."""
    found = {int(m.group(1)) for p in results.glob("seed*_bodies.csv") if (m := re.match(r"seed(\d+)_", p.name))}
    return sorted(s for s in found if all((results / f"seed{s}_{name}_bodies.csv").is_file() for name in SETS))


def all_sets_row(results: Path, seed: int) -> dict[str, object]:
    """One seed's summary over the bodies of every set together (module docstring)."""
    tables = [body_columns(results, seed, name) for name in SETS]
    value = {c: np.concatenate([t[c] for t in tables]) for c in COLUMNS}
    out: dict[str, object] = {"seed": seed, "bodies": len(value["open_loop"])}
    for c in COLUMNS:
        out[c], out[f"{c}_band99"] = mean_band(value[c])
    for a, b in PAIRS:
        out[f"{a}_minus_{b}"], out[f"{a}_minus_{b}_band99"] = paired_band(value[a] - value[b])
    out["mean_command_over_open_loop"] = float(value["mean_command"].mean() / value["open_loop"].mean())
    out["beyond_own_gait"] = int((value["mean_command"] > value["open_loop"]).sum())
    return out


def figure(results: Path, seeds: list[int], path: Path, moved: str = "distance in the plane") -> None:
    plt = pyplot()
    fig, (curve_ax, bar_ax) = plt.subplots(1, 2, figsize=(10, 3.6), gridspec_kw={"width_ratios": [1, 1.3]})
    for seed in seeds:
        curve = results / f"seed{seed}.curve.csv"
        if curve.is_file():
            columns = read_csv(curve)[1]
            curve_ax.plot(columns["epoch"], columns["reward_mean"], lw=1, label=f"seed {seed}")
    curve_ax.set(xlabel="epoch", ylabel="training return (voxel lengths in 2 s)",
                 title="training: the stream of bodies")
    curve_ax.legend(fontsize=7)
    # (the open-loop gaits and the untrained controller are the same for every seed: drawn once)
    bars = [("open_loop", "own open-loop gait", "tab:grey", seeds[0], ""),
            ("untrained_mean_command", "untrained (the hand-set wave)", "tab:orange", seeds[0], "")]
    bars += [("mean_command", "trained, mean command", "tab:blue", seed, f", seed {seed}") for seed in seeds]
    width = 0.8 / len(bars)
    for b, (column, label, colour, seed, which) in enumerate(bars):
        means, bands = zip(*(mean_band(body_columns(results, seed, name)[column]) for name in SETS), strict=True)
        x = np.arange(len(SETS)) - 0.4 + width * (b + 0.5)
        bar_ax.bar(x, means, width, yerr=bands, color=colour, alpha=1.0 - 0.3 * max(0, b - 2), capsize=2,
                   label=label + which)
    bar_ax.set_xticks(np.arange(len(SETS)), [f"{name}\n({len(body_columns(results, seeds[0], name)['body'])} bodies)"
                                             for name in SETS])
    bar_ax.set(ylabel=f"{moved} in 2 s (voxel lengths)", title="zero-shot on held-out bodies (99 % bands)")
    bar_ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=150)


def held_out_sets(bodies: Path, materials: int) -> dict:
    """Every held-out set of ``bodies/SET.npy`` as ``--evaluate`` reads it (``lab.heldout.read_bodies``)."""
    from lab.heldout import read_bodies

    return {name: read_bodies(bodies / f"{name}.npy", materials) for name in SETS}


def set_sizes(bodies: Path) -> list[int]:
    """The bodies in each held-out set, in ``SETS``' order (the steering preset's materials)."""
    from freeform.config import compose

    return [len(g) for g in held_out_sets(bodies, len(compose("experiment=control_population_steering_cpu").sim.materials)).values()]


def hand_set_wave(bodies: Path, k: float, variants: int, turn, amplitude: float = 1.0) -> dict[str, np.ndarray]:
    """The steering preset's wave head playing the hand-set wave (``amplitude``) exactly (its per-cell outputs 0) on every held-out
    body of ``bodies/SET.npy`` (read as ``--evaluate`` reads them), ``variants`` times over, one episode each along
    seed 0's random headings: per set, the move along the heading ``[variants, bodies]``. Before each control step
    the wave vector is k·(cos o, sin o, 0) in the heading's frame (x along the heading), o = ``turn(step, env,
    moved)`` ``[variants · all bodies]`` (variant-major within each set), ``moved`` each body's centre-of-mass move
    ``[N, 2]`` over the step before (None at the first)."""
    import torch

    from freeform.agents.networks.controllers import HandSetWave, build_controller, controller_step
    from freeform.config import compose
    from freeform.envs.control import ControlEnv

    cfg = compose("experiment=control_population_steering_cpu")
    control, sim = cfg.control.episode(), cfg.sim
    sets = held_out_sets(bodies, len(sim.materials))
    grids = torch.cat([g.repeat(variants, 1, 1, 1) for g in sets.values()])
    first = np.concatenate([np.tile(np.arange(len(g)), variants) for g in sets.values()])
    env = ControlEnv(grids, sim=sim, control=control, seed=0, first_env=first)
    net = build_controller(cfg.control.controller, env, cfg.agent.hidden, head="wave",
                           wave=HandSetWave(k, amplitude)).eval()
    with torch.no_grad():  # the hand-set wave exactly: no per-cell amplitude, phase or correction, and the wave
        for layer in (net.actor, net.wave_k):  # vector wave_k0 alone, turned per environment below
            layer.weight.zero_()
            layer.bias.zero_()
    obs, total, moved = env.reset(), torch.zeros(env.num_envs, dtype=torch.float64), None
    for step in range(control.steps):
        angle = torch.as_tensor(turn(step, env, moved), dtype=torch.float32)
        net.wave_k0 = k * torch.stack([torch.cos(angle), torch.sin(angle), torch.zeros_like(angle)], 1)  # ([N, 3])
        before = env._com[:, :2].copy()
        with torch.no_grad():
            outputs, _ = controller_step(net, obs, None)
        obs, reward, _, _ = env.step(net.distribution.mode(outputs[:3]))
        total += reward.double()
        moved = env._com[:, :2] - before
    out, start = {}, 0
    for name, g in sets.items():
        out[name] = total[start: start + variants * len(g)].numpy().reshape(variants, len(g))
        start += variants * len(g)
    return out


def steer_waves(bodies: Path, ks: tuple[float, ...] = (1.0, 1.5, 2.0),
                offsets: tuple[float, ...] = (0.0, 0.5 * np.pi, np.pi, -0.5 * np.pi)) -> list[dict]:
    """The rows of ``--steer-waves`` (module docstring): per k, offset and set, the mean move along the heading of
    the hand-set wave held at that offset from the heading."""
    sizes = set_sizes(bodies)
    angle = np.concatenate([np.repeat(offsets, n) for n in sizes])
    rows = []
    for k in ks:
        moves = hand_set_wave(bodies, k, len(offsets), lambda step, env, moved: angle)
        for name in SETS:
            for offset, along in zip(offsets, moves[name], strict=True):
                mean, band = mean_band(along)
                rows.append({"set": name, "k": k, "offset_rad": round(float(offset), 4), "along_heading": float(mean),
                             "band99": float(band), "bodies": moves[name].shape[1]})
                print(rows[-1], flush=True)
    return rows


def steer_feedback(bodies: Path, k: float = 1.5, gains: tuple[float, ...] = (0.0, 0.3, 0.6, 1.0)) -> list[dict]:
    """The rows of ``--steer-feedback`` (module docstring): the hand-set wave turned after every control step by
    ``gain`` × the angle between the heading and the body's last move (integral feedback on the heading error; gain
    0: held along the heading), per gain and set, the mean move along the heading."""
    sizes = set_sizes(bodies)
    gain = np.concatenate([np.repeat(gains, n) for n in sizes])
    offset = np.zeros(len(gain))

    def turn(step, env, moved):
        nonlocal offset
        if moved is None:
            offset = np.zeros(len(gain))
        else:  # heading minus the direction moved, in (−π, π]
            error = np.angle(np.exp(1j * (env.heading - np.arctan2(moved[:, 1], moved[:, 0]))))
            offset = offset + gain * error
        return offset

    moves = hand_set_wave(bodies, k, len(gains), turn)
    rows = []
    for name in [*SETS, "all"]:
        for g, gg in enumerate(gains):
            along = np.concatenate([moves[n][g] for n in SETS]) if name == "all" else moves[name][g]
            mean, band = mean_band(along)
            rows.append({"set": name, "k": k, "gain": gg, "along_heading": float(mean), "band99": float(band),
                         "bodies": len(along)})
            print(rows[-1], flush=True)
    return rows


def steer_amplitudes(bodies: Path, waves: tuple[tuple[float, float], ...] = (
        (1.5, 1.0), (1.5, 1.3), (1.5, 1.6), (1.5, 2.0), (1.5, 3.0), (1.0, 1.6), (2.0, 1.6))) -> list[dict]:
    """The rows of ``--steer-amplitudes`` (module docstring): per (k, amplitude) of ``waves`` and set (and all
    sets together), the mean move along the heading of the hand-set wave along it."""
    zero = np.zeros(sum(set_sizes(bodies)))
    rows = []
    for k, amplitude in waves:
        moves = hand_set_wave(bodies, k, 1, lambda step, env, moved: zero, amplitude=amplitude)
        for name in [*SETS, "all"]:
            along = np.concatenate([moves[n][0] for n in SETS]) if name == "all" else moves[name][0]
            mean, band = mean_band(along)
            rows.append({"set": name, "k": k, "amplitude": amplitude, "along_heading": float(mean),
                         "band99": float(band), "bodies": len(along)})
            print(rows[-1], flush=True)
    return rows


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--results", default="lab/results/control_population")
    p.add_argument("--steer-waves", action="store_true",
                   help="the hand-set wave along headings and at angles to them (steer_waves.csv; module docstring)")
    p.add_argument("--steer-feedback", action="store_true",
                   help="the hand-set wave turned by the heading error after every step (steer_feedback.csv)")
    p.add_argument("--steer-amplitudes", action="store_true",
                   help="the hand-set wave along the heading at amplitudes from 1 up (steer_amplitudes.csv)")
    p.add_argument("--bodies", default="lab/results/heldout_bodies", help="the held-out sets' folder")
    p.add_argument("--headings", choices=("any", "random"), default="any",
                   help="what the evaluations scored: the distance in the plane (any) or the move along random "
                        "headings (random: a steering controller's; its open loop is ~0, so no ratio is printed)")
    args = p.parse_args(argv)
    results = Path(args.results)
    if args.steer_waves:
        write_rows(results / "steer_waves.csv", steer_waves(Path(args.bodies)))
        return
    if args.steer_feedback:
        write_rows(results / "steer_feedback.csv", steer_feedback(Path(args.bodies)))
        return
    if args.steer_amplitudes:
        write_rows(results / "steer_amplitudes.csv", steer_amplitudes(Path(args.bodies)))
        return
    seeds = seeds_in(results)
    if not seeds:
        raise SystemExit(f"{results}: no seed<S>_<SET>_bodies.csv for every set of {SETS}")
    rows = [all_sets_row(results, seed) for seed in seeds]
    write_rows(results / "all_sets.csv", rows)
    for row in rows:
        ratio = f" (x{row['mean_command_over_open_loop']:.2f})" if args.headings == "any" else ""
        print(f"seed {row['seed']}: mean command {row['mean_command']:.3f} ± {row['mean_command_band99']:.3f} against "
              f"open loop {row['open_loop']:.3f}{ratio}, {row['beyond_own_gait']} of {row['bodies']} beyond their "
              f"gait; over the untrained mean command {row['mean_command_minus_untrained_mean_command']:+.3f} ± "
              f"{row['mean_command_minus_untrained_mean_command_band99']:.3f}")
    figure(results, seeds, results / "control_population.png",
           moved="distance in the plane" if args.headings == "any" else "along a random heading")


if __name__ == "__main__":
    main()
