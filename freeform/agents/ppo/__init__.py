"""PPO, following the data: ``config`` (PPOConfig, presets) → ``rollout`` (storage, the minibatch's named sample
columns) → ``losses`` (the pure functions) → ``collect`` (rollout collection) → ``update`` (minibatch SGD, the KL
rule; ``graphed``: its CUDA graph) → ``checkpoints`` (state, save, load) → ``ppo`` (the public class, whose parts the
collection, update and checkpoints are). ``from freeform.agents.ppo import ...`` gives every public name."""

from freeform.agents.ppo.config import (
    ADVANTAGE_NORMS,
    CLEANRL_DISCRETE_PRESET,
    CLEANRL_PRESET,
    LR_SCHEDULES,
    VALUE_CLIP_MODES,
    PPOConfig,
)
from freeform.agents.ppo.losses import (
    clamped_value_loss,
    clipped_surrogate,
    compute_advantages,
    discounted_cumsum,
    explained_variance,
    gaussian_entropy,
    gaussian_kl,
    gaussian_log_prob,
    minibatch_loss,
    ppo2_value_loss,
    ppo_loss,
    sequence_minibatch_loss,
    standardize,
    update_kl_coeff,
)
from freeform.agents.ppo.ppo import PPO, builtin_policies, choose_distribution, policy_class_name
from freeform.agents.ppo.rollout import (
    Observation,
    Rollout,
    Samples,
    minibatch_samples,
    obs_first,
    obs_map,
    obs_shapes,
    sample_columns,
)

__all__ = ["ADVANTAGE_NORMS", "CLEANRL_DISCRETE_PRESET", "CLEANRL_PRESET", "LR_SCHEDULES", "PPO", "VALUE_CLIP_MODES", "PPOConfig", "Rollout",
           "Samples", "Observation", "builtin_policies", "choose_distribution", "obs_first", "obs_map", "obs_shapes", "clamped_value_loss", "clipped_surrogate", "compute_advantages",
           "discounted_cumsum", "explained_variance", "gaussian_entropy", "gaussian_kl", "gaussian_log_prob",
           "minibatch_loss", "minibatch_samples", "policy_class_name", "ppo2_value_loss", "ppo_loss", "sample_columns",
           "sequence_minibatch_loss",
           "standardize", "update_kl_coeff"]
