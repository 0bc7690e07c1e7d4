"""A trained policy for use outside training code: ``PPO.export(path)`` writes the actor's deterministic action as
an ONNX graph (through ``torch.export``: ``torch.onnx.export(..., dynamo=True)``), the observation normalisation
folded in, so the graph takes raw observations as the env gives them and returns what ``ppo.act(obs,
deterministic=True)`` returns.

Inputs and outputs (N, the batch, is a dynamic axis):

- ``obs [N, ...]`` in the env's dtype — or, for dict observations, one input per part the actor reads, named by its
  key (the ``"critic"`` group of an observation with groups is the critic's alone and is no input);
- a recurrent policy (``freeform.agents.networks.recurrent``): also ``state_<i>`` (its actor's hidden state, e.g. an LSTM's
  ``h``, ``c``, each ``[N, ...]``) and ``episode_start [N]`` bool (1 where the observation begins an episode: the state
  is reset there first); outputs ``state_out_<i>``, to feed back at the next step;
- output ``actions [N, A]``: a Gaussian's mean (unclipped, as ``act`` gives it), or the int64 indices of a discrete
  distribution.

The optional dependencies are the ``export`` extra (``pip install 'freeform[export]'``: onnx, onnxscript; onnxruntime
to run the file). A network the exporter cannot trace may offer ``for_export()``, a module of the same function that
it can (``VoxelActorCritic``: its plain ``Conv3d`` trunk instead of the sparse CPU one).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn as nn

from freeform.agents.networks.observation_groups import CRITIC
from freeform.agents.networks.recurrent import RecurrentPolicy, SplitRecurrentPolicy
from freeform.agents.ppo.normalization import RunningMeanStd
from freeform.distributions import ActionDistribution


class DeterministicActor(nn.Module):
    """Raw observations → the actions ``ppo.act(obs, deterministic=True)`` gives: normalisation (the saved
    statistics, not updated), the actor, the distribution's mode, the env's dtype. ``keys``: the dict observation's
    parts it takes, in input order (None: one tensor). ``stats``: ``{key: (mean, var)}`` float64 (key None for a
    tensor observation), empty without ``obs_norm``."""

    def __init__(self, policy: nn.Module, distribution: ActionDistribution, keys: Sequence[str] | None,
                 stats: Mapping[str | None, tuple[torch.Tensor, torch.Tensor]], obs_clip: float, split: bool,
                 recurrent: str | None) -> None:
        super().__init__()
        self.policy, self.distribution, self.keys, self.obs_clip = policy, distribution, keys, float(obs_clip)
        self.split, self.recurrent = split, recurrent
        self.stat_keys = list(stats)
        for i, (mean, var) in enumerate(stats.values()):
            self.register_buffer(f"mean_{i}", mean.detach().to(torch.float64).clone())
            self.register_buffer(f"var_{i}", var.detach().to(torch.float64).clone())

    def _normalize(self, x: torch.Tensor, key: str | None) -> torch.Tensor:
        if key not in self.stat_keys:
            return x
        i = self.stat_keys.index(key)
        return RunningMeanStd.normalize_with(x, getattr(self, f"mean_{i}"), getattr(self, f"var_{i}"), self.obs_clip)

    def forward(self, *inputs: torch.Tensor) -> Any:
        n_obs = 1 if self.keys is None else len(self.keys)
        parts, rest = inputs[:n_obs], inputs[n_obs:]
        obs: Any = (self._normalize(parts[0], None) if self.keys is None
                    else {k: self._normalize(x, k) for k, x in zip(self.keys, parts, strict=True)})
        if self.recurrent is None:
            params = tuple(self.policy.action_params(obs)) if self.split else tuple(self.policy(obs))[:-1]
            return self.distribution.env_actions(self.distribution.mode(params))
        *state, start = rest
        seq = {k: x[None] for k, x in obs.items()} if isinstance(obs, dict) else obs[None]
        if self.recurrent == "actor":
            params, state = self.policy.action_params(seq, tuple(state), start[None])
        else:
            *params, _, state = self.policy(seq, tuple(state), start[None])
        action = self.distribution.env_actions(self.distribution.mode(tuple(p[0] for p in params)))
        return (action, *state)


def export_onnx(ppo: Any, path: str | os.PathLike, opset: int | None = None) -> str:
    """Write ``ppo``'s (a ``freeform.agents.PPO``, taken as an argument: this module imports nothing back) deterministic actor to ``path`` as ONNX (module docstring); returns the path. Raises
    ``ImportError`` without the ``export`` extra and ``ValueError`` naming what cannot be exported."""
    try:
        import onnx  # noqa: F401
        import onnxscript  # noqa: F401  (torch's ONNX exporter for torch.export programs)
    except ImportError as e:
        raise ImportError(f"PPO.export needs onnx and onnxscript ({e.name} is missing): pip install "
                          "'freeform[export]'") from e
    policy = ppo.policy.for_export() if hasattr(ppo.policy, "for_export") else ppo.policy
    grouped, example = isinstance(ppo.obs, Mapping), ppo.obs
    keys = [k for k in example if k != CRITIC] if grouped else None
    stats: dict[str | None, tuple[torch.Tensor, torch.Tensor]] = {}
    if ppo.obs_rms is not None:
        rms = ppo.obs_rms
        stats = ({k: (r.mean, r.var) for k, r in rms.items() if k in keys} if isinstance(rms, Mapping)
                 else {None: (rms.mean, rms.var)})
    recurrent = None
    if isinstance(ppo.policy, RecurrentPolicy):
        recurrent = "actor" if isinstance(ppo.policy, SplitRecurrentPolicy) else "whole"
        if recurrent == "whole" and grouped and CRITIC in example:
            raise ValueError(f"{type(ppo.policy).__name__} runs its actor only with its critic (no action_params), "
                             "and the critic reads the 'critic' group, which an exported actor does not get: give "
                             "the network action_params(obs, actor_state, episode_start) (SplitRecurrentPolicy)")
    elif grouped and CRITIC in example and not ppo.critic_apart:
        raise ValueError(f"{type(ppo.policy).__name__} has no action_params(obs): its actor cannot run without the "
                         "critic's 'critic' group, which an exported actor does not get")
    actor = DeterministicActor(policy, ppo.distribution, keys, stats, ppo.config.obs_clip, ppo.critic_apart,
                               recurrent).eval()
    obs_inputs = [example[k] for k in keys] if grouped else [example]
    names = list(keys) if grouped else ["obs"]
    inputs, outputs = list(obs_inputs), ["actions"]
    batch = torch.export.Dim("batch", min=1)
    shapes: list[dict[int, Any]] = [{0: batch} for _ in obs_inputs]
    if recurrent is not None:
        state = ppo.policy_state if recurrent == "whole" else ppo.policy_state[: ppo.policy.actor_state_size]
        inputs += [*state, ppo.episode_start]
        names += [f"state_{i}" for i in range(len(state))] + ["episode_start"]
        outputs += [f"state_out_{i}" for i in range(len(state))]
        shapes += [{0: batch} for _ in range(len(state) + 1)]
    if obs_inputs[0].shape[0] < 2:  # torch.export specialises a batch of 1: trace with 2 rows
        inputs = [torch.cat([x, x]) for x in inputs]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            program = torch.onnx.export(actor, tuple(inputs), input_names=names, output_names=outputs,
                                        dynamic_shapes=(tuple(shapes),), dynamo=True, opset_version=opset,
                                        verbose=False)
    except Exception as e:
        cause = e.__cause__ or e  # (torch.onnx wraps torch.export's error in a page of advice)
        first = next((line for line in str(cause).splitlines() if line.strip()), "")
        raise ValueError(f"cannot export {type(ppo.policy).__name__} to ONNX ({type(cause).__name__}: {first}); a "
                         "network may offer for_export(), a module of the same function that torch.export can "
                         "trace") from e
    if ppo.dp.is_writer:  # (data-parallel: every rank holds the same actor; rank 0 writes)
        program.save(os.fspath(path))
    return os.fspath(path)


__all__ = ["DeterministicActor", "export_onnx"]
