"""Typed configuration of a training run: the dataclasses behind ``conf/`` and their validation.

Hydra composes ``conf/config.yaml`` (groups ``task``, ``env``, ``agent``, ``sim``, ``trainer``, ``experiment``) on
top of :class:`TrainConfig`, registered as the schema ``train_schema``. Because the schema is a structured config,
an unknown key (``agent.lrr=1``) or a value of the wrong type (``env.num_envs=abc``) fails while composing, with
Hydra's message naming the key. Value ranges (``env.resolution=7``) are checked by :func:`validate`, which raises a
``ValueError`` naming the dotted key and the allowed values.

The dataclasses hold the spec's defaults (``docs/training.md`` lists every field); the presets in
``conf/experiment/`` are the paper's Table I runs and the CPU demo.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

if TYPE_CHECKING:
    from freeform.agents import PPOConfig

try:  # The simulator's typed config, once freeform.sim provides it (the physics work fills it in).
    from freeform.sim import SimConfig  # type: ignore[attr-defined]
except ImportError:  # pragma: no cover - exercised until freeform.sim lands

    @dataclass
    class SimConfig:  # type: ignore[no-redef]
        """Placeholder for ``freeform.sim.SimConfig`` (the Voxelyze simulation's parameters).

        It has no fields yet, so ``conf/sim/default.yaml`` is empty and any ``sim.*`` override fails as unknown.
        """


@dataclass
class TaskConfig:
    """What the designs are scored by (``conf/task/``)."""

    name: str = "volume"
    """Registered task name: ``volume`` or ``locomotion`` (see ``freeform.train.TASKS``)."""
    materials: int = 2
    """k, material count including 0 = empty: 2 for volume (empty, passive), 4 for locomotion."""
    options: dict[str, Any] = field(default_factory=dict)
    """Extra keyword arguments for the task's constructor (e.g. the locomotion reward's variant)."""


@dataclass
class EnvConfig:
    """The batched design environment, ``freeform.envs.DesignEnv`` (``conf/env/``)."""

    num_envs: int = 256
    """N, environments stepped in lock-step (one robot designed per environment and episode)."""
    resolution: int = 20
    """ρ, edge of the design grid in voxels (even: the network halves it)."""
    steps: int = 100
    """T, actions per episode."""
    bundle_size: int = 2
    """b, edge of the cube of voxels one action paints (even: the bundle is centred between voxels)."""
    action_bound: float = 2.0
    """B, every action component is clipped to [−B, B] and mapped to [0, 1] (spec: 2)."""


@dataclass
class AgentConfig:
    """PPO and the actor-critic (``conf/agent/``). Every field but ``hidden`` is the ``freeform.agents.PPOConfig``
    field of the same name (a test keeps the two in step); the run's ``seed`` and ``trainer.device`` fill
    PPOConfig's ``seed`` and ``device``, and PPOConfig checks the values (errors name ``agent.<field>``)."""

    hidden: int = 128
    """h, width of the trunk's output and of both heads (128 volume, 256 locomotion)."""
    lr: float = 1e-4
    """Adam learning rate."""
    gamma: float = 0.99
    """Discount γ."""
    gae_lambda: float = 1.0
    """GAE λ (1 = the paper's Monte-Carlo advantage G_t − V(s_t))."""
    clip_param: float = 0.3
    """PPO ratio clip ε."""
    kl_coeff: float = 0.2
    """Initial coefficient β of the KL penalty."""
    kl_target: float = 0.01
    """Target KL of the adaptive β."""
    vf_loss_coeff: float = 1.0
    """c_v, weight of the value loss."""
    vf_clip_param: float = 1e5
    """Clamp on the squared value error (RLlib's vf_clip_param)."""
    entropy_coeff: float = 0.0
    """c_e, weight of the entropy bonus."""
    num_sgd_iter: int = 50
    """SGD passes over each train batch."""
    sgd_minibatch_size: int = 128
    """Samples per minibatch."""
    rollout_steps: int | None = None
    """Steps per environment per epoch; None = env.steps (one episode per environment per epoch, the paper's)."""
    grad_clip: float | None = None
    """Global gradient-norm clip; None = none (the paper's)."""
    advantage_norm: str = "batch"
    """Advantage standardisation: "batch" (once over the train batch, the paper's), "minibatch" or "none"."""
    value_clip: str = "squared"
    """"squared": min((V − G)², vf_clip_param) (RLlib, the paper's); "ppo2": PPO2's clipped-V loss."""
    lr_schedule: str = "constant"
    """"constant" or "linear" (lr annealed to 0 over ``lr_anneal_epochs``)."""
    lr_anneal_epochs: int = 500
    """Epochs of the linear lr schedule."""


@dataclass
class TrainerConfig:
    """The training loop, its outputs and its resumption (``conf/trainer/``)."""

    epochs: int = 500
    """Training epochs (one rollout + PPO update each)."""
    device: str = "auto"
    """``auto`` (CUDA when available, else CPU), ``cpu``, ``cuda`` or ``cuda:<i>``."""
    threads: int = 0
    """torch CPU threads; 0 = torch's default."""
    checkpoint_every: int = 10
    """Every this many epochs keep a numbered checkpoint ``checkpoints/epoch_<e>.pt`` (``last.pt`` is rewritten
    every epoch); 0 = numbered ones off."""
    resume: str | None = None
    """Run directory or checkpoint file to continue from (the run's own config is used; only ``trainer.*`` may
    differ)."""
    record_designs: bool = True
    """Write ``records/epoch_<e>.npz`` (actions, final grids, rewards, critic values, body metrics) every epoch."""
    render_every: int = 0
    """Every this many epochs run the render callback (body images to TensorBoard); 0 = off."""
    print_every: int = 10
    """Every this many epochs print a summary line (console and the run's log); 0 = never."""
    progress: bool = True
    """Show a tqdm bar over epochs."""
    dry_run: bool = False
    """Print the resolved per-rank work split (and, from the command line, the jobs and the launch command) and
    run nothing (``docs/scaling.md``)."""


@dataclass
class TrainConfig:
    """A whole run: the composed ``conf/config.yaml``."""

    name: str = "default"
    """Experiment name; runs go to ``runs/<name>/<timestamp>`` (set by the ``experiment`` presets)."""
    seed: int = 0
    """Seeds the network's initialisation, the environment and PPO (torch, numpy and python RNGs)."""
    task: TaskConfig = field(default_factory=TaskConfig)
    env: EnvConfig = field(default_factory=EnvConfig)
    agent: AgentConfig = field(default_factory=AgentConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)


_DEVICE_PREFIXES = ("cuda:",)
_DEVICES = ("auto", "cpu", "cuda", "mps")


def _fail(key: str, allowed: str, value: object) -> None:
    raise ValueError(f"{key} must be {allowed}, got {value!r}")


def validate(cfg: TrainConfig) -> TrainConfig:
    """Check value ranges the types cannot express; raise ``ValueError`` naming the dotted key. Returns ``cfg``."""
    e, a, t, k = cfg.env, cfg.agent, cfg.trainer, cfg.task
    if e.num_envs < 1:
        _fail("env.num_envs", "an integer >= 1", e.num_envs)
    if e.resolution < 2 or e.resolution % 2:
        _fail("env.resolution", "an even integer >= 2 (the network's stride-2 convolution halves it)", e.resolution)
    if e.steps < 1:
        _fail("env.steps", "an integer >= 1", e.steps)
    if not 2 <= e.bundle_size <= e.resolution or e.bundle_size % 2:
        _fail("env.bundle_size", f"an even integer in [2, env.resolution={e.resolution}]", e.bundle_size)
    if not e.action_bound > 0:
        _fail("env.action_bound", "> 0", e.action_bound)
    if k.materials < 2:
        _fail("task.materials", "an integer >= 2 (index 0 is empty)", k.materials)
    if a.hidden < 1:
        _fail("agent.hidden", "an integer >= 1", a.hidden)
    ppo_config(cfg, device="cpu")  # PPOConfig checks the rest of the agent section
    sim_validate = getattr(cfg.sim, "validate", None)
    if callable(sim_validate):
        try:
            sim_validate()
        except ValueError as exc:
            raise ValueError(str(exc).replace("SimConfig.", "sim.")) from exc
    if t.epochs < 0:
        _fail("trainer.epochs", "an integer >= 0", t.epochs)
    if t.device not in _DEVICES and not (t.device.startswith(_DEVICE_PREFIXES) and t.device[5:].isdigit()):
        _fail("trainer.device", f"one of {list(_DEVICES)} or 'cuda:<index>'", t.device)
    for name in ("threads", "checkpoint_every", "render_every", "print_every"):
        if getattr(t, name) < 0:
            _fail(f"trainer.{name}", "an integer >= 0 (0 = off/default)", getattr(t, name))
    return cfg


def ppo_config(cfg: TrainConfig, device: str | None) -> PPOConfig:
    """The run's ``freeform.agents.PPOConfig``: the ``agent`` section (less ``hidden``), ``rollout_steps`` defaulting
    to ``env.steps``, the run's ``seed`` and ``device``. A value PPOConfig rejects raises ``ValueError`` naming
    ``agent.<field>``."""
    from freeform.agents import PPOConfig

    fields = {f.name: getattr(cfg.agent, f.name) for f in dataclasses.fields(AgentConfig) if f.name != "hidden"}
    if fields["rollout_steps"] is None:
        fields["rollout_steps"] = cfg.env.steps
    try:
        return PPOConfig(**fields, seed=cfg.seed, device=device)
    except ValueError as exc:
        raise ValueError(str(exc).replace("PPOConfig.", "agent.")) from exc


def to_dataclass(cfg: DictConfig | TrainConfig) -> TrainConfig:
    """A composed Hydra/OmegaConf config -> a validated :class:`TrainConfig` (plain dataclasses, no OmegaConf)."""
    if isinstance(cfg, TrainConfig):
        return validate(cfg)
    if not isinstance(cfg, DictConfig):
        raise ValueError(f"cfg must be a DictConfig or TrainConfig, got {type(cfg).__name__}")
    merged = OmegaConf.merge(OmegaConf.structured(TrainConfig), cfg)  # re-checks keys and types
    obj = OmegaConf.to_object(merged)
    assert isinstance(obj, TrainConfig)
    return validate(obj)


def to_container(cfg: TrainConfig) -> dict[str, Any]:
    """Plain nested dict of ``cfg`` (what checkpoints store and TensorBoard shows)."""
    return dataclasses.asdict(cfg)


def from_container(data: dict[str, Any]) -> TrainConfig:
    """Inverse of :func:`to_container` (for a config read back from a checkpoint), validated."""
    return to_dataclass(OmegaConf.create(data))


def flatten(data: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"env": {"num_envs": 8}}`` -> ``{"env.num_envs": 8}`` (for hparams and config comparison)."""
    out: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict) and value:
            out.update(flatten(value, f"{name}."))
        else:
            out[name] = value
    return out


def register_configs() -> None:
    """Register :class:`TrainConfig` with Hydra's ConfigStore as ``train_schema`` (``conf/config.yaml``'s base)."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name="train_schema", node=TrainConfig)


__all__ = [
    "AgentConfig",
    "EnvConfig",
    "SimConfig",
    "TaskConfig",
    "TrainConfig",
    "TrainerConfig",
    "flatten",
    "from_container",
    "ppo_config",
    "register_configs",
    "to_container",
    "to_dataclass",
    "validate",
]
