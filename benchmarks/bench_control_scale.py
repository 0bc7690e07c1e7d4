"""Control learning at scale (issue 59): one epoch of the population preset (``control_population_cpu``: one
controller, N bodies × 4 copies) and of the teacher preset (``control_teachers_cpu``: N teachers in a bank × 4
copies) at N = 1,024 bodies on a GPU, split into rollout (of it, the environment) and update, with the samples per
second and the seconds an epoch costs per body. ``scripts/gpu_check.sh``'s ``control_scale`` step runs it.

    python -m benchmarks control_scale                          # on a CUDA machine: N = 1,024
    FREEFORM_BENCH_ARCH=cpu python -m benchmarks control_scale  # the CPU's figure at N = 16, the presets' own size

The CPU run is the comparison: the same presets at the size a 2-core host trains them, per body. Both epochs are
timed (the first one compiles); the second is the figure.
"""

from __future__ import annotations

import os

from benchmarks.bench_gpu import line, train_epochs
from freeform.sim import runtime

COPIES = 4
"""Environments per body in both presets (the population's copies, the bank's num_envs / teachers)."""

BODIES = {"cuda": 1024, "cpu": 16}
"""N by arch: the issue's 1,024 on a GPU; on the CPU the teacher preset's own 16 (64 environments)."""


def preset_overrides(n: int) -> dict[str, tuple[str, ...]]:
    """The two presets at ``n`` bodies × :data:`COPIES` environments (every run: 2 epochs, no renders, no
    checkpoints)."""
    common = (f"env.num_envs={COPIES * n}", "trainer.epochs=2", "trainer.progress=false", "trainer.checkpoint_every=0",
              "trainer.render_every=0")
    return {"control_population_cpu": (f"control.copies={COPIES}", *common),
            "control_teachers_cpu": (f"control.teachers={n}", *common)}


def main() -> None:
    arch = runtime.ensure(os.environ.get("FREEFORM_BENCH_ARCH", "auto"))
    device = "cuda" if arch == "cuda" else "cpu"
    n = int(os.environ.get("FREEFORM_BENCH_CONTROL_BODIES", BODIES["cuda" if arch == "cuda" else "cpu"]))
    print(f"control at scale on {runtime.describe()} ({arch}): {n} bodies x {COPIES} copies; epoch 2 of 2")
    for preset, overrides in preset_overrides(n).items():
        try:
            _, last, wall = train_epochs((f"experiment={preset}", f"trainer.device={device}", *overrides))
        except Exception as e:  # one preset's failure is a figure too; the other still runs
            line(preset, f"FAILED: {type(e).__name__}: {str(e)[:200]}")
            continue
        rollout, update = last.get("perf/time_rollout", float("nan")), last.get("perf/time_update", float("nan"))
        env, sps = last.get("perf/time_env", float("nan")), last.get("perf/samples_per_second", float("nan"))
        line(f"{preset}: rollout (of it env) | update | samples/s",
              f"{rollout:7.2f} s ({env:.2f}) | {update:6.2f} s | {sps:8.0f}")
        line("  an epoch per body | both epochs, compilation included",
              f"{(rollout + update) / n * 1e3:7.1f} ms | {wall:7.1f} s")


if __name__ == "__main__":
    main()
