"""Does ``torch.compile`` pay for small-MLP PPO on the CPU? (issue 11: "``torch.compile`` only if its compile time
pays within a demo-sized run").

Times, eager and compiled, the two per-sample pieces of PPO on CleanRL's MuJoCo network (``MLPActorCritic(17, 6)``,
HalfCheetah's sizes): the **acting step** of a one-env rollout (observation normalisation with its running-statistics
update, the actor, sampling; the critic and the log-probabilities run once per rollout) and the **minibatch update**
(64 samples: forward, the clipped losses, backward, gradient clipping, fused Adam over the flat parameter vector),
both built from ``freeform.agents``' own pieces.
Prints µs per call, the compile seconds (the first compile includes Dynamo/Inductor's one-time start-up), and the
steps of a CleanRL-sized run (2,048 steps an epoch, 10 × 32 minibatches) after which the compile is paid back. One torch thread; ``FREEFORM_BENCH_QUICK=1`` shortens it.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time

import torch

from freeform.agents import MLPActorCritic
from freeform.agents.ppo import clipped_surrogate, gaussian_log_prob, ppo2_value_loss
from freeform.agents.ppo.flat_params import FlatParameters

OBS, ACT, MINIBATCH, BATCH = 17, 6, 64, 2048
UPDATES_PER_STEP = 10 * (BATCH // MINIBATCH) / BATCH  # minibatch updates per environment step (CleanRL's defaults)


def _timed(fn, calls: int, repeats: int = 3) -> float:
    """Best of ``repeats`` of the mean µs per call (a shared machine only ever adds time)."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(calls):
            fn()
        best = min(best, (time.perf_counter() - t0) / calls * 1e6)
    return best


def _compile_seconds(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def act_step(policy: MLPActorCritic):
    """One env's acting step as PPO.collect does it, stats as tensors (a Python count would recompile each step)."""

    def step(obs, mean, var, count, noise):
        x = obs.to(torch.float64)
        total = count + 1
        delta = x[0] - mean
        var = var * (count / total) + delta * delta * (count / (total * total))
        mean = mean + delta / total
        normed = ((x - mean) / torch.sqrt(var + 1e-8)).clamp(-10, 10).to(torch.float32)
        mu, log_std = policy.action_params(normed)  # the critic and log-probabilities run once per rollout
        return torch.addcmul(mu, torch.exp(log_std), noise), mean, var, total

    return step


def update_step(policy: MLPActorCritic):
    def loss(obs, actions, old_logprobs, advantages, returns, old_values):
        mu, log_std, value = policy(obs)
        ratio = torch.exp(gaussian_log_prob(actions, mu, log_std) - old_logprobs)
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
        return -clipped_surrogate(ratio, advantages, 0.2).mean() + 0.25 * ppo2_value_loss(value, old_values, returns, 0.2).mean()

    return loss


def main() -> None:
    quick = os.environ.get("FREEFORM_BENCH_QUICK") == "1"
    # A cold compile, as a user's first run pays it: Inductor's on-disk cache would hide most of it.
    cache, before = tempfile.mkdtemp(prefix="freeform-bench-inductor-"), os.environ.get("TORCHINDUCTOR_CACHE_DIR")
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = cache
    try:
        _run(quick)
    finally:  # the other benchmarks of `make bench` run in this process: give them their cache back
        if before is None:
            os.environ.pop("TORCHINDUCTOR_CACHE_DIR", None)
        else:
            os.environ["TORCHINDUCTOR_CACHE_DIR"] = before
        shutil.rmtree(cache, ignore_errors=True)


def _run(quick: bool) -> None:
    torch.set_num_threads(1)
    torch.manual_seed(0)
    policy = MLPActorCritic(OBS, ACT)
    flat = FlatParameters(policy.parameters())  # as PPO trains it
    optimizer = torch.optim.Adam([flat.value], lr=3e-4, eps=1e-5, fused=True)
    g = torch.Generator().manual_seed(0)
    batch = [torch.randn(BATCH, OBS, generator=g), torch.randn(BATCH, ACT, generator=g)] + [
        torch.randn(BATCH, generator=g) for _ in range(4)]
    stats = [torch.zeros(OBS, dtype=torch.float64), torch.ones(OBS, dtype=torch.float64), torch.tensor(1e-4, dtype=torch.float64)]
    obs, noise = torch.randn(1, OBS), torch.randn(1, ACT)

    def acting(fn):
        def call():
            with torch.no_grad():
                fn(obs, *stats, noise)
        return call

    def updating(fn):
        def call():
            idx = torch.randint(0, BATCH, (MINIBATCH,), generator=g)
            flat.zero_grad()
            fn(*(x.index_select(0, idx) for x in batch)).backward()
            flat.clip_grad_norm_(0.5)
            optimizer.step()
        return call

    rows = []
    for name, make, wrap, calls, per_step in (("acting step (1 env)", act_step, acting, 300 if quick else 3000, 1.0),
                                             ("minibatch update (64)", update_step, updating, 30 if quick else 320,
                                              UPDATES_PER_STEP)):
        eager = wrap(make(policy))
        eager()
        compiled = wrap(torch.compile(make(policy), dynamic=False))
        seconds = _compile_seconds(compiled)
        t_eager, t_compiled = _timed(eager, calls), _timed(compiled, calls)
        saved = (t_eager - t_compiled) * per_step * 1e-6  # seconds saved per environment step
        pays = f"{seconds / saved:,.0f} env steps" if saved > 0 else "never"
        rows.append((name, t_eager, t_compiled, seconds, pays))
    print("| piece | eager (µs) | compiled (µs) | compile (s) | compile paid back after |")
    print("|---|---|---|---|---|")
    for name, t_eager, t_compiled, seconds, pays in rows:
        print(f"| {name} | {t_eager:.0f} | {t_compiled:.0f} | {seconds:.1f} | {pays} |")


if __name__ == "__main__":
    main()
