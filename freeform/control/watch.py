"""One body's gait under a controller, to look at: ``freeform-control watch``.

The controller drives the body by its mean command for one episode — the episode ``evaluate`` scores for that body
(same env seed, same row, so the same headings and the same bits; for steering, whose figure is the mean of
several episodes' headings, the first of them, to rounding) — and a frame is taken every ``k`` control
periods, ``k`` the whole number nearest to giving the asked frame rate, and at the episode's end: every simulated
frame at that rate over the whole control window, from the end of the burn-in to the episode's last period.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from freeform.agents.controller_file import MeanPolicy
from freeform.control.evaluate import block_env, episode_of
from freeform.envs.control import open_loop_displacement, open_loop_moves
from freeform.sim import SimConfig


def writable(video: str) -> None:
    """Refuse, before anything is played, a video format this installation cannot write."""
    import importlib.util

    if video not in ("gif", "mp4"):
        raise ValueError(f"--video must be gif or mp4, got {video!r}")
    if video == "mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise ValueError("--video mp4 needs imageio-ffmpeg: pip install 'freeform[video]' (or --video gif)")


def periods_per_frame(fps: float, period: float) -> int:
    """The control periods between two frames for a frame rate of about ``fps`` (at least one period)."""
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"--fps must be a positive number of frames per second, got {fps!r}")
    return max(1, round(1.0 / (fps * period)))


@torch.no_grad()
def watch(saved: Any, grids: torch.Tensor, out: Path, fps: float = 40.0, video: str = "gif",
          headings: str | None = None, body: int = 0) -> dict:
    """Drive body ``body`` of ``grids`` (uint8 ``[M, ρ, ρ, ρ]``) with ``saved`` (a ``SavedController`` for a box that
    holds them) by its mean command for one episode, in the env ``evaluate`` plays the mean command in (every body
    of the file, one row each: the same bits; for steering, each body's first episode, which ``evaluate`` averages
    with the others in a larger batch: the same to rounding); write ``out/gait.<video>`` (``gif``, or ``mp4`` with the ``video``
    extra) and ``out/gait.json`` (the move, the frames, the frame rate, the body's own open-loop gait). Returns the
    figures."""
    writable(video)
    from freeform.render.gait import render_recording
    from freeform.render.video import write_video

    control, net = episode_of(saved, headings), saved.controller.eval()
    every = periods_per_frame(fps, control.period)
    if not 0 <= body < len(grids):
        raise ValueError(f"--body {body}: the file holds bodies 0 … {len(grids) - 1}")
    env = block_env(grids, saved, control, blocks=1)
    state, headings_seen = None, []  # (a recurrent controller's state, carried through the episode)

    policy = MeanPolicy(net)

    def act(obs: torch.Tensor) -> torch.Tensor:
        nonlocal state
        headings_seen.append(float(env.heading[body]))  # (the episode's: the env draws the next one's at its end)
        actions, state = policy(obs, state)
        return actions

    def rewarded(reward: torch.Tensor) -> None:
        nonlocal state
        state = policy.observe(state, reward)

    recording, _, moved = env.record(act, robot=body, every=every, rewarded=rewarded)
    heading = headings_seen[0]
    delivered = 1.0 / (every * control.period)
    out.mkdir(parents=True, exist_ok=True)
    write_video(out / f"gait.{video}", render_recording(recording), fps=delivered)
    sim = saved.sim or SimConfig()
    alone = grids[body: body + 1]
    gait = open_loop_displacement(alone, sim, control, headings=np.array([heading]), planar=control.headings == "any",
                                  moves=open_loop_moves(alone, sim, control))
    com = recording.positions[0].mean(1) / sim.voxel_size  # [frames, 3] (every voxel weighs the same)
    figures = {"body": body, "displacement": moved, "open_loop": float(gait[0]), "frames": len(recording.times),
               "fps": delivered, "seconds": float(recording.times[-1] - recording.times[0]),
               "heading_rad": None if control.headings == "any" else heading,
               "com_rise_max": float(com[:, 2].max() - com[0, 2]), "controller": str(Path(saved.path).resolve()),
               "unit": "voxel lengths over the control window (evaluate's mean_command for this body)"}
    (out / "gait.json").write_text(json.dumps(figures, indent=1))
    return figures


__all__ = ["periods_per_frame", "watch", "writable"]
