"""Run CleanRL's ``ppo_continuous_action.py`` unmodified on Gymnasium 1.x: ``python cleanrl_compat.py SCRIPT ARGS...``.

The script targets Gymnasium 0.29 (CleanRL pins ``gymnasium==0.29.1``), which has no MuJoCo ``-v5`` tasks. Two of
its calls changed in Gymnasium 1.0; this shim restores 0.29's behaviour for them and changes nothing else:

- ``gym.wrappers.TransformObservation(env, func)``: 1.x requires the transformed space as a third argument; the
  script's transform (a clip) keeps the space, so the env's own is passed.
- ``gym.vector.SyncVectorEnv``: 0.29 reset an env in the step that ended its episode and reported that episode's
  info as ``infos["final_info"]``, one dict (or None) per env, which the script reads for ``episodic_return``.
  1.x resets in the *next* step by default; here the vector env resets in the same step (``AutoresetMode.SAME_STEP``,
  0.29's semantics, which the script's ``dones`` logic assumes) and ``final_info`` is given in the per-env layout.

Then the script runs as ``__main__`` (``runpy``), with ``sys.argv`` = SCRIPT ARGS.
"""

from __future__ import annotations

import runpy
import sys

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

_TransformObservation = gym.wrappers.TransformObservation
_SyncVectorEnv = gym.vector.SyncVectorEnv


class TransformObservation(_TransformObservation):
    def __init__(self, env, func, observation_space=None):  # type: ignore[no-untyped-def]
        super().__init__(env, func, observation_space if observation_space is not None else env.observation_space)


class SyncVectorEnv(_SyncVectorEnv):
    def __init__(self, env_fns, **kwargs):  # type: ignore[no-untyped-def]
        kwargs.setdefault("autoreset_mode", AutoresetMode.SAME_STEP)
        super().__init__(env_fns, **kwargs)

    def step(self, actions):  # type: ignore[no-untyped-def]
        obs, rewards, terminations, truncations, infos = super().step(actions)
        if "final_info" in infos:  # 1.x: a dict of arrays over envs -> 0.29: an array of per-env dicts
            batched, mask = infos["final_info"], infos.get("_final_info", np.ones(self.num_envs, dtype=bool))
            per_env = np.array([None] * self.num_envs, dtype=object)
            for i in np.flatnonzero(mask):
                info = {}
                if "episode" in batched and batched.get("_episode", mask)[i]:
                    info["episode"] = {k: np.array([v[i]]) for k, v in batched["episode"].items()}
                per_env[i] = info
            infos = {**infos, "final_info": per_env}
        return obs, rewards, terminations, truncations, infos


gym.wrappers.TransformObservation = TransformObservation
gym.vector.SyncVectorEnv = SyncVectorEnv

if __name__ == "__main__":
    script = sys.argv[1]
    sys.argv = sys.argv[1:]
    runpy.run_path(script, run_name="__main__")
