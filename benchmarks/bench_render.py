"""What rendering costs: one design image, the 3-image TensorBoard log, the gait-video log, against a CPU-demo epoch.

Figures (wall time, medians of repeats):
- ``render_grid`` of an untrained policy's 20³ design (k = 4, T = 100; ~340 voxels drawn, body + translucent rest);
- ``log_epoch_renders`` without a simulator (best / median / random images into a TensorBoard event file);
- the locomotion gait video of ``log_bodies``: simulation (``VideoConfig.seconds``), frames, GIF encoding;
- a locomotion CPU-demo epoch (``experiment=locomotion_cpu``, measured here by training a few epochs), and the
  share of it that rendering every 10 epochs costs (the target: < 5 %).

``python -m benchmarks render``. Timings on a shared 2-core machine are pessimistic.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from freeform.render import (
    RenderConfig,
    VideoConfig,
    encode_gif,
    log_epoch_renders,
    render_grid,
    render_recording,
    simulate_gait,
)

EVERY = 10  # trainer.render_every the target assumes


def _median_time(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _designs(n: int, resolution: int, steps: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Final grids and bodies of an untrained (a ~ N(0, I)) policy, k = 4."""
    from freeform.body import largest_component
    from freeform.envs.design import DesignEnv, EnvConfig
    from freeform.evolve import untrained_design_grids

    grids = untrained_design_grids(DesignEnv(n, EnvConfig(resolution=resolution, steps=steps),
                                             materials=4, compute_metrics=False), seed)
    return grids.numpy(), largest_component(grids).numpy()


def _demo_epoch_seconds(epochs: int = 4) -> tuple[float, Path]:
    """Median seconds per epoch (after the first, which compiles kernels) of the locomotion CPU demo."""
    from freeform.config import compose
    from freeform.train import train

    cfg = compose("experiment=locomotion_cpu", f"trainer.epochs={epochs}", "trainer.checkpoint_every=0",
                  "trainer.progress=false", "trainer.print_every=0", "trainer.render_every=0")
    run_dir = Path(tempfile.mkdtemp(prefix="bench_render_demo_"))
    stamps: list[float] = []
    train(cfg, run_dir, callbacks=[lambda ctx: stamps.append(time.perf_counter())])
    return statistics.median(np.diff(stamps)), run_dir


def main() -> None:
    from torch.utils.tensorboard import SummaryWriter

    grids, bodies = _designs(8, 20, 100)
    drawn = int((grids > 0).sum(axis=(1, 2, 3)).mean())
    cfg = RenderConfig()
    render_grid(grids[0], bodies[0], cfg)  # warm up (font loading)
    t_image = _median_time(lambda: render_grid(grids[1], bodies[1], cfg), 15)
    print(f"render_grid, 20^3 untrained design ({drawn} voxels drawn, {cfg.size} px): {1e3 * t_image:.1f} ms")

    with tempfile.TemporaryDirectory() as tmp:
        writer = SummaryWriter(log_dir=tmp)
        rewards = np.arange(len(grids), dtype=np.float64)
        t_log = _median_time(lambda: log_epoch_renders(writer, grids, rewards, 0, rng=0), 5)
        writer.close()
    print(f"log_epoch_renders, bodies + 3 images into TensorBoard (no video): {1e3 * t_log:.1f} ms")

    # Locomotion: the CPU demo's designs (ρ = 8, T = 20), its epoch time, and the gait video of its best robot.
    from freeform.config import TrainConfig
    from freeform.render import gait_simulator

    try:
        epoch_s, run_dir = _demo_epoch_seconds()
    except Exception as exc:  # the training app is another part; report and go on with the rendering figures
        print(f"(could not time a CPU-demo epoch: {type(exc).__name__}: {exc})")
        epoch_s, run_dir = float("nan"), None
    demo_grids, demo_bodies = _designs(32, 8, 20, seed=1)
    best = int(np.argmax((demo_bodies > 0).sum(axis=(1, 2, 3))))
    sim_cfg = TrainConfig().sim
    if run_dir is not None:
        from freeform.render_cli import run_sim_config

        sim_cfg = run_sim_config(run_dir)
    video = VideoConfig()
    simulator = gait_simulator(sim_cfg, video.seconds)
    simulate_gait(simulator, demo_bodies[best], video.fps)  # compile
    t_sim = _median_time(lambda: simulate_gait(simulator, demo_bodies[best], video.fps), 3)
    recording = simulate_gait(simulator, demo_bodies[best], video.fps)
    small = RenderConfig(size=video.size)
    t_frames = _median_time(lambda: render_recording(recording, 0, small), 3)
    frames = render_recording(recording, 0, small)
    t_gif = _median_time(lambda: encode_gif(frames, video.fps), 3)
    n_vox = int((demo_bodies[best] > 0).sum())
    print(f"gait video ({video.seconds:g} s, {len(frames)} frames of {video.size} px, {n_vox}-voxel demo body): "
          f"simulate {1e3 * t_sim:.0f} ms + frames {1e3 * t_frames:.0f} ms + GIF {1e3 * t_gif:.0f} ms "
          f"({len(encode_gif(frames, video.fps)) // 1024} KiB)")

    with tempfile.TemporaryDirectory() as tmp:
        writer = SummaryWriter(log_dir=tmp)
        r = (demo_bodies > 0).sum(axis=(1, 2, 3)).astype(np.float64)
        t_full = _median_time(
            lambda: log_epoch_renders(writer, demo_grids, r, 0, rng=0, simulator=simulator), 3
        )
        writer.close()
    print(f"log_epoch_renders, locomotion demo (3 images + gait GIF): {1e3 * t_full:.0f} ms")
    if np.isfinite(epoch_s):
        share = t_full / EVERY / epoch_s
        print(f"locomotion CPU-demo epoch: {epoch_s:.2f} s; rendering every {EVERY} epochs costs "
              f"{100 * share:.1f} % of an epoch (target < 5 %)")


if __name__ == "__main__":
    main()
