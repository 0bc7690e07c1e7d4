"""What training logs to TensorBoard every ``trainer.render_every`` epochs: the best, the median and a random body
as images and, for locomotion, a GIF of the best robot's gait."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from freeform.render.designs import render_grid
from freeform.render.gait import VideoConfig, gait_simulator, render_recording, simulate_gait
from freeform.render.raster import RenderConfig
from freeform.render.video import check_frames, encode_gif
from freeform.surface import as_grid

if TYPE_CHECKING:  # the type hints only: rendering never needs Taichi or TensorBoard to import
    from torch.utils.tensorboard import SummaryWriter

    from freeform.sim import Simulator


def add_gif(writer: SummaryWriter, tag: str, frames: np.ndarray, step: int, fps: float = 20.0) -> None:
    """Log an animated GIF as a TensorBoard image summary (TensorBoard's image tab plays it).

    This is what ``SummaryWriter.add_video`` does, minus its moviepy dependency (whose 2.x releases removed the
    ``moviepy.editor`` module that ``add_video`` imports, so it silently writes nothing).
    """
    from tensorboard.compat.proto.summary_pb2 import Summary

    arr = check_frames(frames)
    image = Summary.Image(height=arr.shape[1], width=arr.shape[2], colorspace=3,
                          encoded_image_string=encode_gif(arr, fps))
    # SummaryWriter has no public way to add a prebuilt summary; add_video itself goes through this file writer.
    writer._get_file_writer().add_summary(Summary(value=[Summary.Value(tag=tag, image=image)]), step)


def pick_bodies(rewards: np.ndarray, rng: np.random.Generator) -> dict[str, int]:
    """Indices of the best, the median and a random design of an epoch (``rewards [E]``).

    The median is the lower middle element of the stable sort (ties keep episode order), so it is always an
    actual design rather than an interpolated reward.
    """
    r = np.asarray(rewards, dtype=np.float64).reshape(-1)
    if r.size == 0:
        raise ValueError("rewards must hold at least one episode")
    order = np.argsort(r, kind="stable")
    return {"best": int(np.argmax(r)), "median": int(order[(r.size - 1) // 2]), "random": int(rng.integers(r.size))}


def _bodies_of(final_grids: np.ndarray) -> np.ndarray:
    """The bodies (largest components) of ``final_grids`` via ``freeform.body``."""
    from freeform.body import largest_component  # the body owner's definition (spec: ties, 6-connectivity)

    out = largest_component(torch.from_numpy(np.ascontiguousarray(final_grids)))
    return out.detach().to("cpu").numpy().astype(np.uint8) if isinstance(out, torch.Tensor) else np.asarray(out)


def log_epoch_renders(
    writer: SummaryWriter,
    final_grids: torch.Tensor | np.ndarray,
    rewards: torch.Tensor | np.ndarray,
    step: int,
    rng: np.random.Generator | int | None = None,
    simulator: Simulator | None = None,
    config: RenderConfig | None = None,
    video: VideoConfig | None = None,
) -> dict[str, int]:
    """Log one epoch's designs to TensorBoard at global step ``step``.

    Images ``bodies/best``, ``bodies/median``, ``bodies/random`` (each captioned with its reward) and, when a
    ``simulator`` is given (locomotion: one configured for a short run, e.g. burn_in 0 and duration
    ``video.seconds``), a GIF ``bodies/best_gait`` of the best robot. ``final_grids``: uint8 ``[E, ρ, ρ, ρ]`` (their
    bodies computed with ``freeform.body``); ``rewards [E]``. Returns the chosen indices.
    """
    prefix = "bodies"
    grids = as_grid(final_grids, "final_grids", 4)
    r = rewards.detach().to("cpu").numpy() if isinstance(rewards, torch.Tensor) else np.asarray(rewards)
    r = r.astype(np.float64).reshape(-1)
    if len(r) != len(grids):
        raise ValueError(f"rewards must hold one value per grid ({len(grids)}), got {len(r)}")
    b = _bodies_of(grids)
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    chosen = pick_bodies(r, gen)
    cfg = config if config is not None else RenderConfig()
    for name, i in chosen.items():
        volume = int((b[i] > 0).sum())
        image = render_grid(grids[i], b[i], cfg, [f"{name} #{i}", f"reward {r[i]:.3g}", f"{volume} voxels"])
        writer.add_image(f"{prefix}/{name}", image, step, dataformats="HWC")
    if simulator is not None and (b[chosen["best"]] > 0).any():
        vid = video if video is not None else VideoConfig()
        recording = simulate_gait(simulator, b[chosen["best"]], vid.fps)
        frames = render_recording(recording, 0, replace(cfg, size=vid.size))
        add_gif(writer, f"{prefix}/best_gait", frames, step, vid.fps)
    writer.flush()
    return chosen


def log_bodies(writer: SummaryWriter, final_grids: Any, rewards: Any, step: int, cfg: Any) -> dict[str, int]:
    """The training loop's render hook: :func:`log_epoch_renders` configured from a ``TrainConfig``.

    The random pick is seeded by (run seed, step), so a resumed run logs the same bodies; a locomotion task gets
    the gait GIF of its best robot (simulated ``VideoConfig.seconds`` with the run's ``sim`` settings).
    """
    rng = np.random.default_rng([int(getattr(cfg, "seed", 0)), int(step)])
    simulator = None
    task = getattr(cfg, "task", None)
    if getattr(task, "name", None) == "locomotion":
        arch = str((getattr(task, "options", None) or {}).get("arch", "auto"))  # the task's own simulator device
        simulator = gait_simulator(cfg.sim, VideoConfig().seconds, arch)
    return log_epoch_renders(writer, final_grids, rewards, step, rng, simulator)


def log_controlled_gait(writer: SummaryWriter, env: Any, act: Any, step: int, video: VideoConfig | None = None) -> float:
    """A control run's render hook: one episode of robot 0 of ``env`` (a ``ControlEnv`` or ``CodesignEnv``: its
    ``record(act)``) under the policy ``act`` (observations → actions, e.g. ``PPO.act(obs, deterministic=True)``),
    logged as the GIF ``bodies/controlled_gait`` at ``video.fps`` frames per simulated second (the burn-in not shown).
    Returns the episode's return (NaN when a co-design episode built no body: nothing is logged)."""
    vid = video if video is not None else VideoConfig()
    recorded = env.record(act)
    if recorded is None:
        return float("nan")
    recording, _, total = recorded
    every = max(1, round(1.0 / (vid.fps * env.control.period)))
    frames = render_recording(recording, 0, replace(RenderConfig(), size=vid.size),
                              frames=np.arange(0, len(recording.times), every))
    add_gif(writer, "bodies/controlled_gait", frames, step, vid.fps)
    writer.flush()
    return total


__all__ = ["add_gif", "log_bodies", "log_controlled_gait", "log_epoch_renders", "pick_bodies"]
