"""freeform: reinforcement learning for freeform robot design (Li, Matthews, Kriegman, ICRA 2024).

Data flows grid -> body -> simulation -> reward -> PPO update:
``freeform.envs`` (design environment, tasks), ``freeform.body`` (largest component, metrics),
``freeform.sim`` (Voxelyze physics in Taichi), ``freeform.agents`` (batched PPO), ``freeform.train`` (Hydra app).
"""

__version__ = "0.1.0"
