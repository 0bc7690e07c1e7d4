"""freeform vs Stable-Baselines3 vs CleanRL's own scripts on Gymnasium tasks: ``ppo_continuous_action.py`` for Box
actions (MuJoCo), ``ppo.py`` for discrete ones (CartPole-v1, Acrobot-v1, …).

Every run trains one framework on one task and seed for the same number of environment steps with the CleanRL
script's hyper-parameters (the task's action space picks the recipe, :data:`RECIPES`), in its own process with one
torch thread, one run at a time, and reports the **final return** (mean raw return of its last 20 training
episodes) and the **wall time** of the whole run (start-up included).

- Box actions, ``ppo_continuous_action``: 1 env × 2048 steps per update, 32 minibatches of 64, 10 passes, lr 3e-4
  annealed linearly to 0, γ 0.99, λ 0.95, clip 0.2, grad-norm 0.5, Adam ε 1e-5, observations and rewards
  normalised and clipped at 10, 64-64 tanh actor and critic, orthogonal init, state-independent log σ.
- Discrete actions, ``ppo.py``: 4 envs × 128 steps per update, 4 minibatches of 128, 4 passes, lr 2.5e-4 annealed
  linearly to 0, γ 0.99, λ 0.95, clip 0.2, entropy 0.01, grad-norm 0.5, Adam ε 1e-5, no normalisation, 64-64 tanh
  actor (logits) and critic, orthogonal init.

- ``freeform``: ``PPO`` with ``PPOConfig.cleanrl()`` (``cleanrl_discrete()``) on
  ``from_gymnasium(gym.make_vec(task, n, SAME_STEP))``.
- ``freeform-compile``: the same with ``PPOConfig.compile`` (``torch.compile``'s minibatch loss; a cold Inductor
  cache unless the machine has compiled it before — ``TORCHINDUCTOR_CACHE_DIR`` decides).
- ``sb3``: ``stable_baselines3.PPO("MlpPolicy")`` on ``make_vec_env(task, n)`` (wrapped in ``VecNormalize`` for the
  Box recipe) with the same values. SB3's value loss has no PPO2 max-clipping: ``vf_coef = 0.25`` gives the squared
  error CleanRL's weight (0.5 · ½), unclipped.
- ``cleanrl``: CleanRL's script itself (``--cleanrl-dir``, a directory holding ``ppo.py`` and
  ``ppo_continuous_action.py``, e.g. a checkout's ``cleanrl/``; default: the files of CleanRL's repository at the
  pinned commit below, fetched from GitHub into ``~/.cache/freeform``), run unmodified through
  ``benchmarks/cleanrl_compat.py``: the scripts were written for Gymnasium 0.29, which has no ``-v5`` tasks; the shim
  gives them 0.29's API on Gymnasium 1.x (``TransformObservation`` without an explicit space; vector envs that reset
  in the same step and report ``final_info`` per env), nothing else.

Time limits: SB3 bootstraps an episode cut by a time limit with V(last observation); CleanRL's scripts treat the
cut as a termination. freeform's Box preset bootstraps (as SB3), its ``ppo.py`` preset does not (as the script):
``PPOConfig.bootstrap_truncated``, ``docs/ppo.md``.

    python -m benchmarks.bench_gym --tasks HalfCheetah-v5 Hopper-v5 --steps 500000 --seeds 0 1   # the MuJoCo table
    python -m benchmarks.bench_gym --tasks CartPole-v1 Acrobot-v1 --steps 200000 --seeds 0 1 2 3 # the discrete one
    python -m benchmarks.bench_gym --tasks InvertedPendulum-v5 --steps 5000 --seeds 0            # end-to-end check
    python -m benchmarks gym        # (make bench) a short InvertedPendulum-v5 comparison, 3 × 50k steps
    python -m benchmarks.bench_gym --split --tasks HalfCheetah-v5   # where a step goes: freeform vs SB3

``--split`` times, in this one process and alternated, freeform's and SB3's rollout and update separately (process
time per environment step over ``--split-epochs`` updates of 2,048 steps, ``--repeats`` times), the Gymnasium step
inside freeform's rollout apart: the figures behind "where a step goes" in ``docs/ppo.md``.

**Memory** (``--memory``): tasks with a hidden variable — ``CartPole-v1-hidden`` (its two velocities hidden) and
``Pendulum-v1-hidden`` (its angular velocity hidden), ``freeform.envs.partial.HideEntries`` — with the recipe of the
base task, four runs each: ``freeform-lstm`` (``RecurrentActorCritic``, an LSTM of 256 per half and 64-64 tanh MLPs,
``sequence_length`` = the minibatch size, so a minibatch is one sequence), ``sb3-lstm`` (sb3-contrib's
``RecurrentPPO("MlpLstmPolicy")`` at its default sizes — the same — and the same values), ``freeform`` (the
feed-forward policy, memoryless) and ``freeform-privileged`` (the feed-forward actor, its critic given the hidden
entries as the ``"critic"`` observation group); asked for by name, ``freeform-lstm-sb3`` (``freeform-lstm`` with
SB3-contrib's loss settings where the recipe's preset differs: no value clipping, and — on CartPole, whose
``ppo.py`` preset ends an episode at its time limit — a time limit bootstrapped with V of the last observation),
``freeform-lstm-unclipped`` (the value loss unclipped alone) and ``freeform-lstm-bootstrap`` (the time-limit
bootstrap alone). Each row adds the **greedy return** (mean of 10 deterministic
episodes after training). Pendulum's rows take the ``box-memory`` recipe (8 envs × 256 steps, minibatches of 512:
8 chunks of 64 steps), CartPole's the discrete one (a chunk is an env's 128-step rollout). Defaults: 300k steps,
seeds 0-3, ``runs/bench_gym_memory``:

    python -m benchmarks.bench_gym --memory                      # the issue's table (two invocations side by side,
    python -m benchmarks.bench_gym --memory --seeds 0 1 &        #  e.g. seeds 0 1 and 2 3, share the results file)
    python -m benchmarks.bench_gym --memory --steps 4096 --seeds 0   # a smoke run

**Asymmetric** (``--memory --tasks Pendulum-v1-noisy --frameworks freeform freeform-privileged``): the policy's
observation with Gaussian noise (``NOISY``: σ per entry), the privileged critic given the clean one — does a critic
that knows the true state help a feed-forward actor that cannot? The base task's recipe, greedy returns as above.

Needs ``pip install 'freeform[bench]'`` (MuJoCo, SB3, sb3-contrib, tyro).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import os
import re
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path

from freeform.files import write_atomically

CLEANRL_COMMIT = "fe8d8a03c41a7ef5b523e2e354bd01c363e786bb"
CLEANRL_URL = f"https://raw.githubusercontent.com/vwxyzjn/cleanrl/{CLEANRL_COMMIT}/cleanrl/{{script}}"
FRAMEWORKS = ("freeform", "freeform-compile", "sb3", "cleanrl", "freeform-lstm", "sb3-lstm", "freeform-privileged",
              "freeform-lstm-sb3", "freeform-lstm-unclipped", "freeform-lstm-bootstrap")
MEMORY_FRAMEWORKS = ("freeform-lstm", "sb3-lstm", "freeform", "freeform-privileged")
NETWORKS = {"freeform": "mlp", "freeform-compile": "mlp", "freeform-lstm": "lstm", "freeform-privileged": "privileged",
            "freeform-lstm-sb3": "lstm-sb3", "freeform-lstm-unclipped": "lstm-unclipped",
            "freeform-lstm-bootstrap": "lstm-bootstrap"}
"""Each freeform framework's network (``freeform_ppo``'s ``network``): the one list of what a child run builds."""
HIDDEN = {"CartPole-v1-hidden": ("CartPole-v1", (1, 3)), "Pendulum-v1-hidden": ("Pendulum-v1", (2,))}
"""The memory tasks: a Gymnasium task and the entries of its observation hidden from the policy."""
NOISY = {"Pendulum-v1-noisy": ("Pendulum-v1", (0.2, 0.2, 1.0)),
         "CartPole-v1-noisy": ("CartPole-v1", (0.1, 0.2, 0.02, 0.2))}
"""The asymmetric tasks (``freeform.envs.partial.NoisyEntries``): a Gymnasium task and the σ of the Gaussian noise on
each entry of the observation the policy sees; a ``freeform-privileged`` critic reads the clean observation."""
GREEDY_EPISODES = 10
LAST_EPISODES = 20


@dataclass(frozen=True)
class Recipe:
    """One CleanRL script's setting: its file, envs per run and steps per update (the batch)."""

    script: str
    envs: int
    batch: int
    minibatch: int
    sequence: int
    """A recurrent policy's chunk length (steps; ``PPOConfig.sequence_length``, one chunk or more per minibatch)."""


RECIPES = {"box": Recipe("ppo_continuous_action.py", envs=1, batch=2048, minibatch=64, sequence=64),
           "discrete": Recipe("ppo.py", envs=4, batch=512, minibatch=128, sequence=128),
           "box-memory": Recipe("ppo_continuous_action.py", envs=8, batch=2048, minibatch=512, sequence=64)}
"""``box-memory``: a Box task with hidden entries (``--memory``): the Box script's values on 8 envs × 256 steps and
minibatches of 512 (8 chunks of 64 steps), for every row of the task alike — the script's 320 minibatches of one
64-step chunk per update would make an LSTM's update 8x longer for the same samples."""


@functools.cache
def recipe(task: str) -> Recipe:
    """The task's recipe, from its action space: Box → ``ppo_continuous_action``, else ``ppo.py``."""
    import gymnasium as gym

    env = gym.make(base_task(task)[0])
    try:
        if not isinstance(env.action_space, gym.spaces.Box):
            return RECIPES["discrete"]
        return RECIPES["box-memory" if base_task(task)[1] else "box"]
    finally:
        env.close()


def base_task(task: str) -> tuple[str, tuple[int, ...]]:
    """(the Gymnasium task, the observation entries hidden from the policy) of a task name."""
    if task in NOISY:
        return NOISY[task][0], ()
    return HIDDEN.get(task, (task, ()))


def gym_vec(task: str, envs: int, critic: bool = False):
    """The task's vector env (``SAME_STEP``), its hidden entries removed (``critic``: as the critic's group)."""
    import gymnasium as gym

    base, hidden = base_task(task)
    if task in NOISY:
        from freeform.envs.partial import NoisyEntries

        return gym.vector.SyncVectorEnv([lambda: NoisyEntries(gym.make(base), NOISY[task][1], critic=critic)] * envs,
                                        autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
    if not hidden:
        return gym.make_vec(task, num_envs=envs, vectorization_mode="sync",
                            vector_kwargs={"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP})
    from freeform.envs.partial import HideEntries

    return gym.vector.SyncVectorEnv([lambda: HideEntries(gym.make(base), hidden, critic=critic)] * envs,
                                    autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)


def final_return(returns: list[float]) -> float:
    """Mean of the last 20 episodes' returns (NaN when none finished)."""
    tail = returns[-LAST_EPISODES:]
    return sum(tail) / len(tail) if tail else math.nan


# ----------------------------------------------------------------------------------------------- the three runners


def freeform_ppo(task: str, steps: int, seed: int, compile: bool = False, network: str = "mlp"):
    """freeform's run: ``PPO`` with ``PPOConfig.cleanrl()`` on one ``SAME_STEP`` env (``cleanrl_discrete()`` on 4
    for a discrete task) with episode statistics (``compile``: with ``torch.compile``'s minibatch loss, the
    ``freeform-compile`` rows). ``network``: "mlp" (``MLPActorCritic``), "lstm" (``RecurrentActorCritic``, the
    ``freeform-lstm`` rows), "lstm-sb3" (the same with SB3-contrib's value loss, unclipped, and its time-limit
    bootstrap, which the Box preset already has: ``freeform-lstm-sb3``), "lstm-unclipped" (the value loss
    unclipped alone), "lstm-bootstrap" (the time-limit bootstrap alone) or "privileged" (the critic sees the hidden entries: ``freeform-privileged``)."""
    import gymnasium as gym
    import torch

    from freeform.agents import PPO, MLPActorCritic, PPOConfig, RecurrentActorCritic
    from freeform.envs import from_gymnasium

    r = recipe(task)
    privileged = network == "privileged"
    vec = gym.wrappers.vector.RecordEpisodeStatistics(gym_vec(task, r.envs, critic=privileged))
    env = from_gymnasium(vec, dict_obs=privileged)
    torch.manual_seed(seed)
    preset = PPOConfig.cleanrl if r.script == "ppo_continuous_action.py" else PPOConfig.cleanrl_discrete
    config = preset(seed=seed, rollout_steps=r.batch // r.envs, lr_anneal_epochs=max(1, steps // r.batch),
                    compile=compile, sgd_minibatch_size=r.minibatch, sequence_length=r.sequence)
    if network in ("lstm-sb3", "lstm-unclipped"):  # (a clip range no step reaches: the plain squared error)
        config = dataclasses.replace(config, vf_clip_param=1e9)
    if network in ("lstm-sb3", "lstm-bootstrap"):
        config = dataclasses.replace(config, bootstrap_truncated=True)
    if network.startswith("lstm"):
        return PPO(env, RecurrentActorCritic.for_env(env), config)
    return PPO(env, MLPActorCritic.for_env(env), config)


def run_freeform(task: str, steps: int, seed: int, compile: bool = False, network: str = "mlp") -> dict:
    ppo = freeform_ppo(task, steps, seed, compile, network)
    returns: list[float] = []
    for _ in range(steps // recipe(task).batch):
        ppo.train_epoch()
        for info in ppo.episode_infos:
            gym_info = info["gym_info"]
            if "episode" in gym_info:
                returns += [float(r) for r, ended in zip(gym_info["episode"]["r"], gym_info["_episode"], strict=True) if ended]
    out: dict = {"returns": returns}
    if base_task(task)[1] or task in NOISY:  # the memory and asymmetric rows: greedy episodes after training
        from freeform.envs import from_gymnasium

        eval_env = from_gymnasium(gym_vec(task, 1, critic=network == "privileged"), seed=10_000 + seed,
                                  dict_obs=network == "privileged")
        out["greedy"] = ppo.evaluate(eval_env, episodes=GREEDY_EPISODES)["eval_return"]
    return out


def sb3_model(task: str, seed: int):
    """SB3's run: ``PPO("MlpPolicy")`` on ``VecNormalize(make_vec_env(task, 1))`` with CleanRL's values (on
    ``make_vec_env(task, 4)`` with ``ppo.py``'s for a discrete task)."""
    import torch.nn as nn
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    r = recipe(task)
    common = dict(gamma=0.99, gae_lambda=0.95, clip_range=0.2, vf_coef=0.25, max_grad_norm=0.5, device="cpu",
                  policy_kwargs=dict(net_arch=dict(pi=[64, 64], vf=[64, 64]), activation_fn=nn.Tanh), seed=seed,
                  stats_window_size=LAST_EPISODES, verbose=0)
    if r.script == "ppo.py":
        env = make_vec_env(task, n_envs=r.envs, seed=seed)
        return PPO("MlpPolicy", env, learning_rate=lambda progress: 2.5e-4 * progress, n_steps=r.batch // r.envs,
                   batch_size=128, n_epochs=4, ent_coef=0.01, **common)
    env = VecNormalize(make_vec_env(task, n_envs=r.envs, seed=seed), gamma=0.99, clip_obs=10.0, clip_reward=10.0)
    return PPO("MlpPolicy", env, learning_rate=lambda progress: 3e-4 * progress, n_steps=r.batch // r.envs,
               batch_size=r.minibatch, n_epochs=10, ent_coef=0.0, **common)


def run_sb3(task: str, steps: int, seed: int) -> dict:
    model = sb3_model(task, seed)
    returns: list[float] = []
    batch = recipe(task).batch
    model.learn(total_timesteps=(steps // batch) * batch, callback=_SB3Episodes(returns))
    return {"returns": returns}


def sb3_lstm_model(task: str, seed: int):
    """sb3-contrib's ``RecurrentPPO("MlpLstmPolicy")`` at its default sizes (an LSTM of 256 per half, 64-64 tanh
    MLPs) with the recipe's values, on the task with its entries hidden (wrapping ``make_vec_env``'s ``Monitor``)."""
    from sb3_contrib import RecurrentPPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    from freeform.envs.partial import HideEntries

    base, hidden = base_task(task)
    r = recipe(task)
    common = dict(gamma=0.99, gae_lambda=0.95, clip_range=0.2, vf_coef=0.25, max_grad_norm=0.5, device="cpu",
                  seed=seed, stats_window_size=LAST_EPISODES, verbose=0)
    env = make_vec_env(base, n_envs=r.envs, seed=seed, wrapper_class=lambda e: HideEntries(e, hidden))
    if r.script == "ppo.py":
        return RecurrentPPO("MlpLstmPolicy", env, learning_rate=lambda progress: 2.5e-4 * progress,
                            n_steps=r.batch // r.envs, batch_size=128, n_epochs=4, ent_coef=0.01, **common), env
    env = VecNormalize(env, gamma=0.99, clip_obs=10.0, clip_reward=10.0)
    return RecurrentPPO("MlpLstmPolicy", env, learning_rate=lambda progress: 3e-4 * progress,
                        n_steps=r.batch // r.envs, batch_size=r.minibatch, n_epochs=10, ent_coef=0.0, **common), env


def run_sb3_lstm(task: str, steps: int, seed: int) -> dict:
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.vec_env import VecNormalize

    from freeform.envs.partial import HideEntries

    model, env = sb3_lstm_model(task, seed)
    returns: list[float] = []
    batch = recipe(task).batch
    model.learn(total_timesteps=(steps // batch) * batch, callback=_SB3Episodes(returns))
    base, hidden = base_task(task)
    eval_env = make_vec_env(base, n_envs=1, seed=10_000 + seed, wrapper_class=lambda e: HideEntries(e, hidden))
    if isinstance(env, VecNormalize):  # the training statistics, frozen; raw rewards
        eval_env = VecNormalize(eval_env, training=False, norm_reward=False)
        eval_env.obs_rms = env.obs_rms
    greedy, _ = evaluate_policy(model, eval_env, n_eval_episodes=GREEDY_EPISODES, deterministic=True)
    return {"returns": returns, "greedy": float(greedy)}


def _SB3Episodes(returns: list[float]):  # noqa: N802 - a factory for SB3's callback class (imported lazily)
    from stable_baselines3.common.callbacks import BaseCallback

    class Episodes(BaseCallback):
        def _on_step(self) -> bool:
            for info in self.locals["infos"]:
                if "episode" in info:
                    returns.append(float(info["episode"]["r"]))
            return True

    return Episodes()


BATCH = RECIPES["box"].batch  # (--split times the Box recipe)


def split_freeform(task: str, epochs: int, seed: int) -> dict[str, float]:
    """µs of process time per env step: freeform's rollout (of which inside ``env.step``) and update."""
    ppo = freeform_ppo(task, 1_000_000, seed)  # CleanRL's 1M-step lr schedule: the first epochs of a full run
    env = ppo.env
    step, time_env = env.step, 0.0

    def timed_step(actions):  # process time, as the rest (the rollout's own figure is wall time)
        nonlocal time_env
        t0 = time.process_time()
        out = step(actions)
        time_env += time.process_time() - t0
        return out

    env.step = timed_step
    rollout = update = 0.0
    for _ in range(epochs):
        t0 = time.process_time()
        ppo.collect()
        t1 = time.process_time()
        ppo.update()
        rollout, update = rollout + t1 - t0, update + time.process_time() - t1
    n = epochs * BATCH / 1e6
    return {"rollout": rollout / n, "env": time_env / n, "update": update / n}


def split_sb3(task: str, epochs: int, seed: int) -> dict[str, float]:
    """µs of process time per env step: SB3's ``collect_rollouts`` and ``train`` (the run of ``run_sb3``)."""
    model = sb3_model(task, seed)
    spent = {"rollout": 0.0, "update": 0.0}

    def timed(name, fn):
        def call(*args, **kwargs):
            t0 = time.process_time()
            result = fn(*args, **kwargs)
            spent[name] += time.process_time() - t0
            return result
        return call

    model.collect_rollouts = timed("rollout", model.collect_rollouts)
    model.train = timed("update", model.train)
    model.learn(total_timesteps=epochs * BATCH)
    n = epochs * BATCH / 1e6
    return {"rollout": spent["rollout"] / n, "env": math.nan, "update": spent["update"] / n}


def split(task: str, epochs: int, repeats: int, seed: int = 0) -> str:
    """Markdown: per repeat and framework, µs per env step in the rollout (env), the update and both."""
    import torch

    torch.set_num_threads(1)
    lines = [f"{task}, {epochs} updates of {BATCH} steps, process time, µs per environment step:",
             "| repeat | framework | rollout | of which env.step | update | total |", "|---|---|---|---|---|---|"]
    for r in range(repeats):
        for name, fn in (("freeform", split_freeform), ("sb3", split_sb3)):
            t = fn(task, epochs, seed)
            lines.append(f"| {r} | {name} | {t['rollout']:.0f} | {t['env']:.0f} | {t['update']:.0f} | "
                         f"{t['rollout'] + t['update']:.0f} |")
    return "\n".join(lines)


def cleanrl_script(name: str, directory: str | None) -> Path:
    """CleanRL's script ``name``: in ``directory``, else the pinned commit's file, fetched once and cached."""
    if directory:
        return Path(directory) / name
    cached = Path.home() / ".cache" / "freeform" / f"cleanrl-{CLEANRL_COMMIT[:12]}" / name
    if not cached.is_file():
        cached.parent.mkdir(parents=True, exist_ok=True)
        url = CLEANRL_URL.format(script=name)
        try:
            with urllib.request.urlopen(url, timeout=60) as response:
                cached.write_bytes(response.read())
        except OSError as exc:
            raise SystemExit(f"cannot fetch {url} ({exc}); pass --cleanrl-dir <a directory holding {name}>") from exc
    return cached


def run_cleanrl(task: str, steps: int, seed: int, script: Path, workdir: Path) -> list[float]:
    """CleanRL's script, unmodified, in a child process (through the API shim); its printed episodic returns."""
    workdir.mkdir(parents=True, exist_ok=True)
    batch = recipe(task).batch
    command = [sys.executable, str(Path(__file__).with_name("cleanrl_compat.py")), str(script),
               "--env-id", task, "--total-timesteps", str((steps // batch) * batch), "--seed", str(seed), "--no-cuda"]
    done = subprocess.run(command, cwd=workdir, capture_output=True, text=True, env=_child_env())
    if done.returncode != 0:
        raise RuntimeError(f"CleanRL's script failed ({done.returncode}):\n{done.stderr[-3000:]}")
    return [float(m) for m in re.findall(r"episodic_return=\[?([-0-9.eE+]+)", done.stdout)]


# ----------------------------------------------------------------------------------------------- orchestration


def _child_env() -> dict[str, str]:
    env = dict(os.environ)
    env.update(OMP_NUM_THREADS=env.get("OMP_NUM_THREADS", "1"), MKL_NUM_THREADS=env.get("OMP_NUM_THREADS", "1"))
    return env


def one_run(framework: str, task: str, steps: int, seed: int, cleanrl_dir: str | None, workdir: Path) -> dict:
    """One framework × task × seed in a fresh process: final return, episodes, wall seconds."""
    start = time.perf_counter()
    if framework == "cleanrl":
        script = cleanrl_script(recipe(task).script, cleanrl_dir)
        returns = run_cleanrl(task, steps, seed, script, workdir / f"cleanrl-{task}-{seed}")
    else:
        command = [sys.executable, "-m", "benchmarks.bench_gym", "--child", framework, "--tasks", task,
                   "--steps", str(steps), "--seeds", str(seed)]
        done = subprocess.run(command, capture_output=True, text=True, env=_child_env(),
                              cwd=Path(__file__).resolve().parent.parent)
        if done.returncode != 0:
            raise RuntimeError(f"{framework} failed ({done.returncode}):\n{done.stderr[-3000:]}")
        out = json.loads(done.stdout.strip().splitlines()[-1])
        returns = out["returns"]
    wall = time.perf_counter() - start
    batch = recipe(task).batch
    row = {"framework": framework, "task": task, "seed": seed, "steps": (steps // batch) * batch,
           "final_return": final_return(returns), "episodes": len(returns), "wall_s": wall}
    if framework != "cleanrl" and "greedy" in out:
        row["greedy_return"] = out["greedy"]
    return row


def table(results: list[dict]) -> str:
    """Markdown: per task and framework, the final return and wall time of every seed and their mean."""
    greedy = any("greedy_return" in r for r in results)  # the memory table: greedy returns, walls against the LSTM's
    base_fw = "freeform-lstm" if greedy else "freeform"
    lines = ["| task | framework | final return (mean of last 20 episodes), per seed | mean | "
             + ("greedy return (10 episodes), per seed | mean | " if greedy else "")
             + f"wall time per seed (s) | mean wall (s) | × {base_fw}'s wall |",
             "|---|---|---|---|" + ("---|---|" if greedy else "") + "---|---|---|"]
    for task in dict.fromkeys(r["task"] for r in results):
        base = [r["wall_s"] for r in results if r["task"] == task and r["framework"] == base_fw]
        base_wall = sum(base) / len(base) if base else math.nan
        for fw in FRAMEWORKS:
            rs = [r for r in results if r["task"] == task and r["framework"] == fw]
            if not rs:
                continue
            rets, walls = [r["final_return"] for r in rs], [r["wall_s"] for r in rs]
            mean_wall = sum(walls) / len(walls)
            greedy_cells = ""
            if greedy:
                g = [r.get("greedy_return", math.nan) for r in rs]
                greedy_cells = f"{', '.join(f'{x:.1f}' for x in g)} | {sum(g) / len(g):.1f} | "
            lines.append(f"| {task} | {fw} | {', '.join(f'{x:.1f}' for x in rets)} | {sum(rets) / len(rets):.1f} | "
                         f"{greedy_cells}{', '.join(f'{w:.0f}' for w in walls)} | {mean_wall:.0f} | "
                         f"{mean_wall / base_wall:.2f} |")
    return "\n".join(lines)


def parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_gym", description=__doc__.split("\n\n")[0])
    p.add_argument("--memory", action="store_true",
                   help="the memory table: hidden-variable tasks, LSTM policies (defaults below change with it)")
    p.add_argument("--tasks", nargs="+", default=None, help=f"default HalfCheetah-v5 Hopper-v5; --memory: {list(HIDDEN)}")
    p.add_argument("--steps", type=int, default=None,
                   help="environment steps per run, default 500k (--memory: 300k), rounded down to whole updates: "
                        "2048 steps, or 512 for discrete tasks")
    p.add_argument("--seeds", nargs="+", type=int, default=None, help="default 0 1 (--memory: 0 1 2 3)")
    p.add_argument("--frameworks", nargs="+", choices=FRAMEWORKS, default=None,
                   help=f"default freeform freeform-compile sb3 cleanrl; --memory: {' '.join(MEMORY_FRAMEWORKS)}")
    p.add_argument("--cleanrl-dir", default=os.environ.get("CLEANRL_DIR"),
                   help="a directory holding CleanRL's ppo.py and ppo_continuous_action.py (default: fetch the pinned "
                        "commit's)")
    p.add_argument("--workdir", default=None, help="where CleanRL's runs/ and the JSON results go (default "
                   "runs/bench_gym, --memory: runs/bench_gym_memory)")
    p.add_argument("--show", action="store_true", help="print the table of WORKDIR/results.json; run nothing")
    p.add_argument("--split", action="store_true", help="time freeform's and SB3's rollout and update apart instead")
    p.add_argument("--split-epochs", type=int, default=3, help="--split: updates of 2,048 steps per measurement")
    p.add_argument("--repeats", type=int, default=2, help="--split: alternations of the two frameworks")
    p.add_argument("--child", choices=(*NETWORKS, "sb3", "sb3-lstm"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    memory = args.memory
    for name, plain, mem in (("tasks", ["HalfCheetah-v5", "Hopper-v5"], list(HIDDEN)), ("steps", 500_000, 300_000),
                             ("seeds", [0, 1], [0, 1, 2, 3]), ("frameworks", list(FRAMEWORKS[:4]), list(MEMORY_FRAMEWORKS)),
                             ("workdir", "runs/bench_gym", "runs/bench_gym_memory")):
        if getattr(args, name) is None:
            setattr(args, name, mem if memory else plain)
    return args


def _key(row: dict) -> tuple:
    return row["framework"], row["task"], row["seed"], row["steps"]


def _read(store: Path) -> list[dict]:
    return json.loads(store.read_text()) if store.exists() else []


def run(argv: list[str] | None = None) -> list[dict]:
    args = parse(argv)
    if args.child:  # inside one run's own process
        task, steps, seed = args.tasks[0], args.steps, args.seeds[0]
        if args.child == "sb3":
            out = run_sb3(task, steps, seed)
        elif args.child == "sb3-lstm":
            out = run_sb3_lstm(task, steps, seed)
        else:
            out = run_freeform(task, steps, seed, compile=args.child == "freeform-compile",
                               network=NETWORKS[args.child])
        print(json.dumps(out))
        return []
    if args.split:
        for task in args.tasks:
            if recipe(task) is not RECIPES["box"]:
                raise SystemExit(f"--split times the Box recipe (2,048 steps per update); {task} is discrete")
            print(split(task, args.split_epochs, args.repeats), flush=True)
        return []
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    store = workdir / "results.json"
    # The file accumulates over invocations (a table can be run in parts, frameworks or seeds apart, even two
    # invocations at once) and is re-read and rewritten after every run, so hours of runs survive an interruption;
    # a rerun replaces its own row. --show prints the table of what it holds without running anything.
    for task in args.tasks if not args.show else ():
        for seed in args.seeds:
            for fw in args.frameworks:
                result = one_run(fw, task, args.steps, seed, args.cleanrl_dir, workdir)
                rows = [r for r in _read(store) if _key(r) != _key(result)] + [result]
                text = json.dumps(rows, indent=1).encode()
                write_atomically(store, lambda f, text=text: f.write(text))
                greedy = f", greedy {result['greedy_return']:.1f}" if "greedy_return" in result else ""
                print(f"{fw:9s} {task} seed {seed}: final return {result['final_return']:.1f} "
                      f"({result['episodes']} episodes{greedy}), wall {result['wall_s']:.1f} s", flush=True)
    shown = [r for r in _read(store) if r["task"] in args.tasks
             and r["steps"] == (args.steps // recipe(r["task"]).batch) * recipe(r["task"]).batch
             and r["seed"] in args.seeds and r["framework"] in args.frameworks]
    shown.sort(key=lambda r: (args.tasks.index(r["task"]), r["seed"], FRAMEWORKS.index(r["framework"])))
    print()
    print(table(shown))
    return shown


def main() -> None:
    """``python -m benchmarks gym`` / ``make bench``: a short InvertedPendulum-v5 comparison (50k steps, seed 0)."""
    run(["--tasks", "InvertedPendulum-v5", "--steps", "50000", "--seeds", "0"])


if __name__ == "__main__":
    run(sys.argv[1:])
