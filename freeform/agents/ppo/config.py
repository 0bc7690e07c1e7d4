"""PPO's hyper-parameters (``PPOConfig``, the ``agent`` section of a run) and the CleanRL preset.

The defaults are RLlib 2.0.1's PPO with the paper's overrides (spec ``ppo.md``, Table I); common variants are
switches. A preset is data: :data:`CLEANRL_PRESET` holds only what differs from the defaults.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from freeform.validation import is_int, is_number, require

ADVANTAGE_NORMS = ("batch", "minibatch", "group", "none")
VALUE_CLIP_MODES = ("squared", "ppo2")
LR_SCHEDULES = ("constant", "linear")


@dataclass
class PPOConfig:
    """PPO hyper-parameters. The defaults are RLlib 2.0.1's PPO with the paper's overrides (Table I)."""

    lr: float = 1e-4
    """Adam learning rate (paper: 1e-4)."""
    gamma: float = 0.99
    """Discount factor γ."""
    gae_lambda: float = 1.0
    """GAE λ; 1 = plain discounted return minus V (the paper: "GAE disabled")."""
    clip_param: float = 0.3
    """Surrogate clip ε: the ratio π/π_old is clipped to [1 − ε, 1 + ε]."""
    kl_coeff: float = 0.2
    """Initial coefficient β of the KL(π_old ‖ π) penalty; 0 disables the penalty (β then stays 0)."""
    kl_target: float = 0.01
    """Target KL for the adaptive β: β ×= 1.5 above 2·target, β ×= 0.5 below target/2."""
    vf_loss_coeff: float = 1.0
    """Weight c_v of the value loss."""
    vf_clip_param: float = 1e5
    """``value_clip="squared"``: clamp of the squared value error (paper: 1e5, i.e. off). ``"ppo2"``: clip range of V
    around the rollout's V."""
    entropy_coeff: float = 0.0
    """Weight c_e of the entropy bonus."""
    num_sgd_iter: int = 30
    """SGD passes over the train batch per epoch (RLlib default 30; paper: volume 50, locomotion 10)."""
    sgd_minibatch_size: int = 128
    """Samples per minibatch; each pass reshuffles and uses ⌊B / size⌋ minibatches (the tail is dropped)."""
    rollout_steps: int = 100
    """Steps T collected from every environment per epoch (train batch = T·N)."""
    sequence_length: int = 32
    """A recurrent policy's (``freeform.agents.networks.recurrent``): each env's rollout is cut into chunks of this many steps
    (the last one padded and masked), each trained from the state stored at its start (truncated backpropagation
    through time); a minibatch holds ``max(1, sgd_minibatch_size // sequence_length)`` chunks. Feed-forward policies
    ignore it."""
    grad_clip: float | None = None
    """Max global gradient norm; None = no clipping (paper)."""
    seed: int = 0
    """Seeds the policy-sampling/shuffling generator and ``env.reset``."""
    device: str | None = None
    """Device of the policy and the rollout storage; None = the env's device."""
    advantage_norm: str = "batch"
    """"batch": standardise advantages once over the train batch (paper); "minibatch": per minibatch; "group": each
    group of environments (``env.reward_groups``, e.g. a teacher bank's bodies) by its own statistics over the
    batch, so that a body whose returns spread widely does not set every other's step size; "none"."""
    value_clip: str = "squared"
    """"squared": min((V − G)², vf_clip_param) (RLlib); "ppo2": max of the plain and the clipped-V squared error."""
    lr_schedule: str = "constant"
    """"constant", or "linear": lr · max(0, 1 − epoch / lr_anneal_epochs)."""
    lr_anneal_epochs: int = 500
    """Epochs over which the "linear" schedule anneals the lr to 0."""
    adam_eps: float = 1e-8
    """Adam's ε (torch's default 1e-8; CleanRL 1e-5)."""
    fused_adam: bool = False
    """Adam as one fused kernel (CPU or GPU): fewer operations per step of a small network (the speed: docs/ppo.md),
    the same update up to float rounding (not bit-identical to the default multi-tensor Adam). Off for the paper."""
    compile: bool = False
    """Hand the minibatch loss (:func:`minibatch_loss`: the policy's forward pass, the losses and, through autograd,
    their backward) to ``torch.compile``. For long runs of small networks on the CPU, where each of a minibatch's
    ≈ 100 operations costs more than its arithmetic: a few seconds of compiling at the first update, then shorter
    steps (measured: ``python -m benchmarks gym``, docs/ppo.md). Other rounding than eager; needs a C++ compiler. Off
    by default."""
    cuda_graph: bool = False
    """On a CUDA device, capture one minibatch's whole Adam step (zero the gradient, the loss, backward, clipping, a
    capturable Adam) as a CUDA graph once and replay it for every minibatch (``freeform.agents.ppo.graphed``): one
    launch instead of the step's hundreds, the same functions in the same order. One process only (a data-parallel
    rank's share of a minibatch varies in size); not with ``compile``. Off by default (the CPU has no graphs)."""
    obs_norm: bool = False
    """Normalise observations by their running mean/variance (over all envs, updated every step), clipped to
    ±``obs_clip``; the statistics are saved in checkpoints and applied by ``act``. Off for the paper."""
    obs_clip: float = 10.0
    """Clip of the normalised observations (``obs_norm``)."""
    reward_norm: bool = False
    """Divide the rewards PPO trains on by the running std of each env's discounted return, clipped to
    ±``reward_clip`` (Gymnasium's ``NormalizeReward``, SB3's ``VecNormalize``); episode statistics stay raw. Off for
    the paper."""
    reward_clip: float = 10.0
    """Clip of the scaled rewards (``reward_norm``)."""
    group_baseline: bool = False
    """Learn from each reward minus the mean of the same step's rewards in the env's other copies of that
    environment (``env.reward_groups``: ``PopulationControlEnv`` with ``control.copies`` >= 2), a leave-one-out
    baseline (RLOO's, per step): the copies start alike, so what is left is what the policy's noise did, without the
    spread between bodies. Unbiased: the siblings' rewards do not depend on this copy's actions. Episode statistics
    stay raw."""
    bootstrap_truncated: bool = True
    """An episode cut by a time limit (the env's ``info["truncated"]``) is bootstrapped with V of its last
    observation, as SB3 does; False: it ends as a terminated one does (CleanRL's scripts, which treat a
    truncation as a termination)."""
    eval_every: int = 0
    """Every this many epochs run ``eval_episodes`` deterministic episodes on the ``eval_env`` given to PPO and
    report ``eval_return`` (logged as ``charts/eval_return``); 0 = off."""
    eval_episodes: int = 10
    """Episodes per evaluation, spread over the eval env's environments."""
    eval_same_episodes: bool = False
    """Every evaluation replays the same episodes (the eval env reseeded ``seed + 1`` each time, not only the first):
    the evaluated curve then moves with the policy alone, not with the draws (a steering run's headings), and a
    resumed run evaluates what an uninterrupted one does. What ``trainer.plateau_on=eval_return`` reads best."""
    stats_window: int = 100
    """The episode statistics (``episode_reward_mean``, ``_max``, ``_min``, ``episode_length_mean``) are over the
    epoch's finished episodes; an epoch that finishes none reports the latest this many finished before it (SB3's
    episode buffer, ``stats_window_size``) instead of NaN; before the first finished episode they are absent."""

    def __post_init__(self) -> None:
        self.validate("PPOConfig")

    @classmethod
    def cleanrl(cls, **overrides: Any) -> PPOConfig:
        """CleanRL's ``ppo_continuous_action`` defaults (:data:`CLEANRL_PRESET`) with ``overrides`` on top."""
        return cls(**{**CLEANRL_PRESET, **overrides})

    @classmethod
    def cleanrl_discrete(cls, **overrides: Any) -> PPOConfig:
        """CleanRL's ``ppo.py`` defaults (:data:`CLEANRL_DISCRETE_PRESET`, for 4 envs) with ``overrides`` on top."""
        return cls(**{**CLEANRL_DISCRETE_PRESET, **overrides})

    def validate(self, key: str) -> None:
        """Raise ``ValueError`` naming ``<key>.<field>`` for the first value outside its range."""
        for name in ("lr", "clip_param", "vf_clip_param", "kl_target", "adam_eps", "obs_clip", "reward_clip"):
            value = getattr(self, name)
            require(is_number(value) and value > 0, f"{key}.{name}", "> 0", value)
        for name in ("gamma", "gae_lambda"):
            value = getattr(self, name)
            require(is_number(value) and 0.0 <= value <= 1.0, f"{key}.{name}", "in [0, 1]", value)
        for name in ("kl_coeff", "vf_loss_coeff", "entropy_coeff"):
            value = getattr(self, name)
            require(is_number(value) and value >= 0.0, f"{key}.{name}", ">= 0", value)
        for name in ("num_sgd_iter", "sgd_minibatch_size", "rollout_steps", "lr_anneal_epochs", "eval_episodes", "stats_window",
                     "sequence_length"):
            require(is_int(getattr(self, name), 1), f"{key}.{name}", "an int >= 1", getattr(self, name))
        require(is_int(self.eval_every, 0), f"{key}.eval_every", "an int >= 0 (0 = off)", self.eval_every)
        for name in ("obs_norm", "reward_norm", "fused_adam", "compile", "cuda_graph", "bootstrap_truncated",
                     "group_baseline", "eval_same_episodes"):
            require(isinstance(getattr(self, name), bool), f"{key}.{name}", "true or false", getattr(self, name))
        require(not (self.cuda_graph and self.compile), f"{key}.cuda_graph", "false when compile is true (pick one "
                "of the two ways to cut the update's launches)", self.cuda_graph)
        require(self.grad_clip is None or (is_number(self.grad_clip) and self.grad_clip > 0), f"{key}.grad_clip",
                "None or > 0", self.grad_clip)
        require(is_int(self.seed, -(2**63)), f"{key}.seed", "an int", self.seed)
        require(self.advantage_norm in ADVANTAGE_NORMS, f"{key}.advantage_norm", f"one of {ADVANTAGE_NORMS}", self.advantage_norm)
        require(self.value_clip in VALUE_CLIP_MODES, f"{key}.value_clip", f"one of {VALUE_CLIP_MODES}", self.value_clip)
        require(self.lr_schedule in LR_SCHEDULES, f"{key}.lr_schedule", f"one of {LR_SCHEDULES}", self.lr_schedule)
        if self.device is not None:
            try:
                torch.device(self.device)
            except (RuntimeError, TypeError) as e:
                raise ValueError(f"{key}.device must be None or a torch device string, got {self.device!r}") from e


CLEANRL_PRESET: dict[str, Any] = dict(
    lr=3e-4, adam_eps=1e-5, lr_schedule="linear", lr_anneal_epochs=488,  # anneal over 1M steps / 2048 per epoch
    gamma=0.99, gae_lambda=0.95, rollout_steps=2048, sgd_minibatch_size=64, num_sgd_iter=10,  # 32 minibatches of 2048
    clip_param=0.2, kl_coeff=0.0, value_clip="ppo2", vf_clip_param=0.2, vf_loss_coeff=0.25,  # 0.5 · ½(V − G)²
    entropy_coeff=0.0, grad_clip=0.5, advantage_norm="minibatch", obs_norm=True, obs_clip=10.0, reward_norm=True,
    reward_clip=10.0, seed=1, fused_adam=True,
)
"""CleanRL's ``ppo_continuous_action.py`` defaults in PPOConfig's terms (one env × 2048 steps per epoch; with N envs
set ``rollout_steps`` = 2048 / N and ``lr_anneal_epochs`` = total steps / 2048 to keep its batch and schedule).
Its value loss ``vf_coef · ½ · max((V − G)², (V_clip − G)²)`` is ``vf_loss_coeff = 0.25`` with the PPO2 clip at
ε = 0.2. Two differences are left: CleanRL divides minibatch advantages by the sample std + 1e-8, freeform by the
population std (a factor √(63/64) at 64 samples), and an episode cut by a time limit is bootstrapped with V of its
last observation (the script treats it as terminated: ``bootstrap_truncated=False`` does so). Use it with ``MLPActorCritic`` (orthogonal init, state-independent
log σ) and actions clipped by the env (``freeform.envs.from_gymnasium`` clips)."""


CLEANRL_DISCRETE_PRESET: dict[str, Any] = dict(
    lr=2.5e-4, adam_eps=1e-5, lr_schedule="linear", lr_anneal_epochs=976,  # anneal over 500k steps / 512 per epoch
    gamma=0.99, gae_lambda=0.95, rollout_steps=128, sgd_minibatch_size=128, num_sgd_iter=4,  # 4 envs: 4 minibatches
    clip_param=0.2, kl_coeff=0.0, value_clip="ppo2", vf_clip_param=0.2, vf_loss_coeff=0.25,  # 0.5 · ½(V − G)²
    entropy_coeff=0.01, grad_clip=0.5, advantage_norm="minibatch", obs_norm=False, reward_norm=False, seed=1,
    fused_adam=True, bootstrap_truncated=False,  # ppo.py: next_done = terminations | truncations
)
"""CleanRL's ``ppo.py`` defaults (the discrete-action script: CartPole-v1, 4 envs × 128 steps per epoch, 4 minibatches,
4 passes, entropy bonus 0.01, no normalisation of observations or rewards, a time limit ending the episode as a
termination does) in PPOConfig's terms; with N envs set
``rollout_steps`` = 512 / N and ``lr_anneal_epochs`` = total steps / 512. The value loss and advantage standardisation
as in :data:`CLEANRL_PRESET`. Use it with ``MLPActorCritic.for_env`` (its categorical head is ``ppo.py``'s network)."""


__all__ = ["ADVANTAGE_NORMS", "CLEANRL_DISCRETE_PRESET", "CLEANRL_PRESET", "LR_SCHEDULES", "PPOConfig", "VALUE_CLIP_MODES"]
