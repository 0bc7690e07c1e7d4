"""Agents: a hand-written batched PPO and its actor-critic networks."""
