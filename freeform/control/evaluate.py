"""A controller on bodies of your own: each body's move under the controller (its mean command and its samples),
under the hand-set travelling wave, and along its own open-loop gait — ``freeform-control evaluate``.

Every figure is the body's move in the controller's episode (voxel lengths: the distance its centre of mass
travels in the plane over the control window, or along the heading for a heading task), from one env that plays
every group on its own block of rows with the same headings; the mean command is deterministic, so one episode of
it is the figure (``watch`` replays it frame by frame) — but along random headings, where each episode draws
another heading and the heading changes a body's move several-fold, its figure is the mean over the body's
episodes 0 … K−1 (``watch`` replays the first).
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from freeform.control.play import hand_set_wave, play
from freeform.envs.control import ControlConfig, ControlEnv, open_loop_displacement, open_loop_moves
from freeform.sim import SimConfig
from freeform.tables import mean_band, summary_row, write_rows

COLUMNS = ("open_loop", "hand_set_wave", "mean_command", "stochastic")
"""``bodies.csv``'s figures (voxel lengths): the mean command's is the body's first episode (deterministic), the
others means over its episodes. Along ``any`` or ``fixed`` headings every episode has the same heading, so they
compare like for like; along ``random`` headings the mean command's is the mean over the same episodes too."""

EPISODES = 4
"""Episodes a body's figures average unless told otherwise (``evaluate --episodes``; a steering figure of
``fit`` and of the lab's reference alike): along random headings, episodes 0 … 3 of each body."""


def figure_episodes(headings: str, episodes: int | None = None, default: int = EPISODES, flag: str = "--episodes",
                    who: str = "the controller") -> int:
    """How many episodes a body's figure (or trial) averages: ``episodes`` (None: ``default``) along random headings;
    one along any other, whose every episode is the same (more refused, naming ``flag`` and ``who``)."""
    if episodes is not None and not (isinstance(episodes, int | np.integer) and episodes >= 1):
        raise ValueError(f"{flag} must be a whole number >= 1, got {episodes!r}")
    if headings != "random":
        if episodes not in (None, 1):
            raise ValueError(f"{flag} {episodes}: {who} plays headings {headings!r}, whose every episode is the same "
                             "(more than one only for steering, headings random)")
        return 1
    return int(episodes or default)


def episode_draws(m: int, episodes: int = 1, first_episode: int = 0,
                  among: tuple[np.ndarray, int] | None = None) -> np.ndarray:
    """The draw of each row of ``m`` bodies × ``episodes`` (row ``i·episodes + j``: body i's episode j draws
    ``(first_episode + j)·M + i``, so that episode 0 of body i draws what row i of a one-episode env of the M
    bodies draws; ``first_episode`` 1 plays the episodes after it, never that one). ``among`` = (places, M): the
    bodies are those places of a set of M, each drawing what it draws in the set's env."""
    if not (isinstance(first_episode, int | np.integer) and first_episode >= 0):
        raise ValueError(f"first_episode must be a whole number >= 0, got {first_episode!r}")
    place, m_set = (np.arange(m), m) if among is None else (np.asarray(among[0]), among[1])
    if place.shape != (m,) or not ((0 <= place) & (place < m_set)).all():
        raise ValueError(f"among: {m} places in a set of {m_set}, got {place.tolist()}")
    return ((first_episode + np.arange(episodes))[None, :] * m_set + place[:, None]).reshape(-1)


def episode_of(saved: Any, headings: str | None = None) -> ControlConfig:
    """The episode a saved controller plays: its own, along ``headings`` where given (warned: another task than
    the one it was trained for)."""
    control = replace(saved.control, headings=headings or saved.control.headings)
    control.validate()
    if control.headings != saved.control.headings:
        warnings.warn(f"--headings {control.headings}: {saved.path} was trained for headings="
                      f"{saved.control.headings}, another task than the one played", stacklevel=3)
    return control


def block_env(grids: torch.Tensor, saved: Any, control: ControlConfig, blocks: int, episodes: int = 1,
              seed: int = 0, first_episode: int = 0, among: tuple[np.ndarray, int] | None = None) -> ControlEnv:
    """One env of ``blocks`` blocks of rows, each every body × ``episodes``, drawn as :func:`episode_draws` says."""
    draws = episode_draws(len(grids), episodes, first_episode, among)
    return ControlEnv(grids.repeat_interleave(episodes, 0).repeat(blocks, 1, 1, 1), sim=saved.sim or SimConfig(),
                      control=control, seed=seed, box=tuple(saved.controller.box), first_env=np.tile(draws, blocks))


@torch.no_grad()
def evaluate(saved: Any, grids: torch.Tensor, episodes: int = EPISODES, headings: str | None = None,
             seed: int = 0) -> list[dict]:
    """``saved`` (a ``SavedController`` built for a box that holds ``grids``, uint8 ``[M, ρ, ρ, ρ]``) on every body:
    one row a body with its voxels and :data:`COLUMNS` (the stochastic mean's 99 % band beside it). The stochastic
    column and the hand-set wave are means over ``episodes`` episodes; the mean command is deterministic, and its
    column is the body's first episode, played in an env of one row a body — the env ``watch`` replays, so that
    its figure is this one to the bit (a controller's forward pass rounds by the batch it is given) — or, along
    random headings, the mean over the ``episodes`` episodes' headings (the first of them ``watch``'s)."""
    if not (isinstance(episodes, int) and episodes >= 1):
        raise ValueError(f"--episodes must be a whole number >= 1, got {episodes!r}")
    control, net = episode_of(saved, headings), saved.controller.eval()
    strokes = control.stroke_periods >= 1
    env = block_env(grids, saved, control, 1 + strokes, episodes, seed)
    groups = [("stochastic", net, False, True)]
    if strokes:  # (the wave is a stroke; a controller of per-period commands has none to compare with)
        groups.append(("hand_set_wave", hand_set_wave(env, net, None), False, False))
    played = play(env, groups, control.steps, seed)
    m, n = len(grids), episodes
    k = n if control.headings == "random" else 1  # (else every episode is alike: the first is the figure)
    mean_command = play(block_env(grids, saved, control, 1, k, seed), [("mean_command", net, False, False)],
                        control.steps, seed).returns[0].reshape(m, k)
    sim = saved.sim or SimConfig()
    gait = open_loop_displacement(grids.repeat_interleave(n, 0), sim, control, headings=played.heading[: m * n],
                                  planar=control.headings == "any",
                                  moves=np.repeat(open_loop_moves(grids, sim, control), n, 0)).reshape(m, n)
    figures = {"open_loop": gait, "mean_command": mean_command,
               **{name: played.returns[g].reshape(m, n) for g, (name, *_) in enumerate(groups)}}
    rows = []
    for i in range(m):
        _, band = mean_band(figures["stochastic"][i])
        rows.append({"body": i, "voxels": int((grids[i] > 0).sum()),
                     **{c: float(figures[c][i].mean()) for c in COLUMNS if c in figures},
                     "stochastic_band99": float(band)})
    return rows


def summary(rows: list[dict]) -> list[dict]:
    """``summary.csv``: each column's mean over the bodies with its 99 % band, the mean command over the hand-set
    wave, and the fraction of bodies it moves beyond their own gait."""
    column = {c: np.array([r[c] for r in rows]) for c in COLUMNS if c in rows[0]}
    out = [summary_row(c, v) for c, v in column.items()]
    if "hand_set_wave" in column:
        out.append({"what": "mean_command over hand_set_wave", "n": len(rows),
                    "mean": float(column["mean_command"].mean() / column["hand_set_wave"].mean())})
    out.append(summary_row("fraction of bodies beyond their own gait (mean command)",
                           (column["mean_command"] > column["open_loop"]).astype(float)))
    return out


def write(out: Path, rows: list[dict]) -> None:
    """``out/bodies.csv`` and ``out/summary.csv``."""
    write_rows(out / "bodies.csv", rows)
    write_rows(out / "summary.csv", summary(rows))


__all__ = ["COLUMNS", "EPISODES", "block_env", "episode_draws", "episode_of", "evaluate", "figure_episodes", "summary",
           "write"]
