"""Typed configuration of a training run: the dataclasses behind ``conf/`` and their validation.

Hydra composes ``conf/config.yaml`` (groups ``task``, ``env``, ``algo``, ``agent``, ``sim``, ``trainer``, ``experiment``) on
top of :class:`TrainConfig`, registered as the schema ``train_schema``. Because the schema is a structured config,
an unknown key (``agent.lrr=1``) or a value of the wrong type (``env.num_envs=abc``) fails while composing, with
Hydra's message naming the key. Value ranges (``env.resolution=7``) are checked by :func:`validate` (each section's
``validate(key)``, in the one style of ``freeform.validation``), which raises a ``ValueError`` naming the dotted key
and the allowed values: ``agent.lr must be > 0, got -1``.

One config: the ``agent`` section *is* ``freeform.agents.PPOConfig`` (:class:`AgentConfig` subclasses it and adds
the network's width), the ``sim`` section is ``freeform.sim.SimConfig``, and the ``algo`` section (which optimiser
designs: ``ppo``, or an evolutionary baseline) is ``freeform.evolve.AlgoConfig``.

The dataclasses hold the spec's defaults (``docs/training.md`` lists every field); the presets in
``conf/experiment/`` are the paper's Table I runs and the CPU demo.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

from omegaconf import DictConfig, OmegaConf

from freeform.agents.networks import TRUNK_IMPLEMENTATIONS
from freeform.agents.networks.controller_heads import HandSetWave, head_rule
from freeform.agents.networks.controllers import CODESIGN_KINDS
from freeform.agents.networks.controllers import CONTROLLERS as CONTROLLER_CLASSES
from freeform.agents.ppo import CLEANRL_DISCRETE_PRESET, CLEANRL_PRESET, PPOConfig
from freeform.envs.control_config import ControlConfig
from freeform.envs.design import EnvConfig
from freeform.evolve.config import AlgoConfig
from freeform.learner import learner_names
from freeform.sim import SimConfig
from freeform.validation import require


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
class AgentConfig(PPOConfig):
    """PPO and the actor-critic (``conf/agent/``): every field of ``freeform.agents.PPOConfig`` (same names, same
    meaning, same checks) plus the network's. Three PPO fields take their value from the run when left None."""

    rollout_steps: int | None = None  # type: ignore[assignment]
    """Steps per environment per epoch; None = env.steps (one episode per environment per epoch, the paper's; in a
    control run the control episode's steps)."""
    seed: int | None = None  # type: ignore[assignment]
    """Seed of PPO's sampling/shuffling generator and ``env.reset``; None = the run's ``seed``."""
    device: str | None = None
    """Device of the policy and the rollout storage; None = ``trainer.device``."""
    hidden: int = 128
    """h, width of the trunk's output and of both heads (128 volume, 256 locomotion)."""
    trunk: str = "auto"
    """The design network's two convolutions (``VoxelActorCritic(trunk=...)``, a co-design policy's too; the same
    function every way): "auto" (``freeform.agents.networks.resolve_trunk``: the sparse "fast" form on the CPU; on a
    GPU its CSR products in a CUDA graph, cuDNN eagerly, the deterministic "gather" form when deterministic
    algorithms are asked for), "fast", "gather" or "conv"."""

    def __post_init__(self) -> None:
        self.validate("agent")

    def validate(self, key: str) -> None:
        # The run-filled fields are checked once filled (ppo_config); here only their own ranges.
        filled = copy.copy(self)
        filled.rollout_steps = 1 if self.rollout_steps is None else self.rollout_steps
        filled.seed = 0 if self.seed is None else self.seed
        PPOConfig.validate(filled, key)
        require(isinstance(self.hidden, int) and self.hidden >= 1, f"{key}.hidden", "an int >= 1", self.hidden)
        require(self.trunk in TRUNK_IMPLEMENTATIONS, f"{key}.trunk", f"one of {TRUNK_IMPLEMENTATIONS}", self.trunk)


BODY_SOURCES = ("walker", "untrained_designs", "codesign", "population")
CONTROLLERS = tuple(CONTROLLER_CLASSES)
"""``control.controller``'s kinds: the names of ``freeform.agents.networks.controllers.CONTROLLERS``."""
CODESIGN_CONTROLLERS = CODESIGN_KINDS
"""The kinds a co-design run's controller may be (``freeform.agents.networks.controllers.CODESIGN_KINDS``)."""


@dataclass
class ControlRunConfig(ControlConfig):
    """A closed-loop control run (``conf/experiment/control_*``; ``docs/control.md``): every field of
    ``freeform.envs.control.ControlConfig`` (the episode's timing and task) plus the bodies and the controller.
    A run with a ``control`` section trains a controller on fixed bodies instead of designing them."""

    bodies: str = "walker"
    """Which bodies are controlled, ``env.num_envs`` of them (given fewer, each is repeated in turn):
    ``walker`` — the best open-loop gait of ``candidates`` bodies that an untrained design policy builds with the
    ``env`` and ``task.materials`` sizes (the control demo's body); ``untrained_designs`` — ``env.num_envs``
    such bodies, all different; a path — a ``.npy`` of uint8 grids ``[ρ, ρ, ρ]`` or ``[M, ρ, ρ, ρ]``, or a design
    record ``records/epoch_<e>.npz`` of a design run, whose best ``top`` designs are taken; ``codesign`` — none
    given: each episode first designs its body (``env.steps`` design actions at the ``env`` sizes, the design env's)
    and then controls it, one PPO learning both (``freeform.envs.CodesignEnv``, ``docs/codesign.md``);
    ``population`` — a stream of bodies an untrained design policy builds, a fresh cohort of ``env.num_envs`` every
    ``refresh_every`` episodes, drawn from a pool of ``pool`` settled cohorts, on the ρ³ box
    (``freeform.envs.PopulationControlEnv``): one controller for many bodies."""
    pool: int = 4
    """``bodies=population``: how many cohorts of ``env.num_envs`` bodies an episode draws from (each settled once
    and restored when drawn again)."""
    refresh_every: int = 1
    """``bodies=population``: episodes between two new cohorts (the oldest leaves the pool); 0: a fixed
    population of ``pool · env.num_envs`` bodies."""
    copies: int = 1
    """``bodies=population``: environments per body (``env.num_envs / copies`` bodies a cohort), each body's copies
    starting from the same settled state: with ``agent.group_baseline`` a copy's rewards are judged against its
    siblings' (``freeform.envs.population``)."""
    designer: str | None = None
    """``bodies=population``: a design run's directory (or checkpoint) whose last policy builds the stream's bodies,
    sampled as in training, instead of an untrained policy: the controller adapts to what a design policy builds
    (one round of alternating co-design, ``docs/codesign.md``). The run's design sizes must be this run's. None:
    untrained designs."""
    teachers: int = 0
    """A bank of per-body controllers (``freeform.agents.distill.teachers``, issue 56): M >= 1 trains M controllers at
    once, one per body, each with its own weights, all starting from the same controller (``controller_init`` where
    given): the first M bodies of ``bodies`` (``untrained_designs``, a ``.npy`` or a record; not ``population`` or
    ``codesign``), environment i driving body i mod M (``env.num_envs`` a multiple of M). 0: one controller for
    every body."""
    top: int = 1
    """From a design record: how many of its best designs (by reward) are controlled."""
    candidates: int = 256
    """``bodies=walker``: how many untrained designs the walker is the best of."""
    body_seed: int = 0
    """Seed of the untrained designs (``walker``, ``untrained_designs``): apart from the run's ``seed``, so that a
    sweep over seeds trains controllers of the same bodies."""
    controller: str = "conv"
    """A kind of ``freeform.agents.networks.controllers.CONTROLLERS``: ``conv`` (``ConvController``: one set of weights for
    every cell, any body), ``mlp`` (``MLPController`` over the flattened box: the baseline), ``context``
    (``ContextConvController``: masked convolutions with the body's pooled features), ``attention``
    (``VoxelAttentionController``: attention over the body's voxels), or either with a memory of the episode
    (``context_gru``, ``attention_gru``: recurrent; ``attention_gru`` starts from an ``attention`` controller's
    weights), or ``attention_hyper`` (``HyperAttentionController``: ``attention`` whose actor each body writes, a
    hypernetwork; also starts from an ``attention`` controller's weights); all but the first two are unchanged by
    padding. Width: ``hidden``."""
    head: str = "direct"
    """The controller's actor head (``freeform.agents.networks.controller_heads.HEADS``): ``direct`` (each cell's mean command),
    ``rhythm`` (each cell's amplitude and phase of a rhythm at the actuation clock's frequency, and an offset;
    ``controller=context`` or ``attention``) or ``stroke`` (each cell's (a, b) of a stroke, with
    ``control.stroke_periods`` >= 1) or ``wave`` (a stroke whose mean is a travelling wave: the body's wave vector,
    each cell's amplitude and phase offset, and a free correction; ``controller=context``, ``attention`` or their ``_gru`` kinds, with
    ``control.stroke_periods`` >= 1)."""
    wave_k: float = 1.0
    """``head=wave``: the wave number the untrained controller plays along x, or along the heading where the task
    has one (rad per voxel length): every voxel receives sin(2πt/T − wave_k·x), x its place along that direction
    from the centre of mass; 0: every voxel in one phase."""
    wave_amplitude: float = 1.0
    """``head=wave``: the amplitude of the wave the untrained controller plays (> 0; what a muscle receives stays
    within [−1, 1] and its bandwidth, so > 1 is a fuller stroke than the sine: ``docs/control.md``, "Steering")."""
    wave_gain: float = 1.0
    """``head=wave``: how far the trained head's mean command goes from the hand-set wave — the wave's strokes plus
    ``wave_gain`` × the head's change to them (>= 0; 1: as trained; ``HandSetWave.gain``)."""
    init_log_std: float = -0.5
    """The controller's initial log σ (commands lie in [−1, 1])."""
    hidden: int | None = None
    """The controller's width; None: ``agent.hidden`` (a co-design run's ``agent.hidden`` is its design network's)."""
    controller_init: str | None = None
    """Start the controller from a trained one: a control or co-design run's directory (its ``checkpoints/last.pt``)
    or a checkpoint file; the controller's weights are loaded (the same ``controller`` kind and width), the rest
    starts fresh. A co-design run so starts with a controller that already drives bodies (a warm start: its
    robot-seconds belong to the co-design run's budget). None: from scratch."""
    prior: str | None = None
    """Regularise towards a trained controller (Distral, ``freeform.agents.distill.prior``): a ``controller.pt``, a results
    folder holding one, or a control run; each step's reward gains ``prior_coeff`` × its log-likelihood of the
    action taken per acting entry — teachers (``teachers`` > 0) kept near one student. None: no prior."""
    prior_coeff: float = 0.05
    """The prior's weight (> 0; with ``prior``)."""

    @property
    def codesign(self) -> bool:
        return self.bodies == "codesign"

    @property
    def hand_set_wave(self) -> HandSetWave:
        """What a ``head=wave`` controller plays untrained (``wave_k``, ``wave_amplitude``), and its ``wave_gain``."""
        return HandSetWave(self.wave_k, self.wave_amplitude, self.wave_gain)

    def validate(self, key: str = "control") -> None:
        super().validate(key)
        require(isinstance(self.bodies, str) and self.bodies != "", f"{key}.bodies",
                f"one of {list(BODY_SOURCES)} or a path to a .npy of grids or a design record .npz", self.bodies)
        require(self.top >= 1, f"{key}.top", "an integer >= 1", self.top)
        require(self.candidates >= 1, f"{key}.candidates", "an integer >= 1", self.candidates)
        require(isinstance(self.pool, int) and self.pool >= 1, f"{key}.pool", "an integer >= 1", self.pool)
        require(isinstance(self.refresh_every, int) and self.refresh_every >= 0, f"{key}.refresh_every",
                "an integer >= 0 (0: a fixed pool)", self.refresh_every)
        require(isinstance(self.copies, int) and self.copies >= 1 and (self.copies == 1 or self.bodies == "population"),
                f"{key}.copies", "an integer >= 1 (> 1 with bodies=population)", self.copies)
        require(isinstance(self.teachers, int) and self.teachers >= 0
                and (self.teachers == 0 or self.bodies not in ("population", "codesign")), f"{key}.teachers",
                "an integer >= 0 (> 0: one controller per body, on fixed bodies: not population or codesign)",
                self.teachers)
        require(self.controller in CONTROLLERS, f"{key}.controller", f"one of {list(CONTROLLERS)}", self.controller)
        require(self.hidden is None or self.hidden >= 1, f"{key}.hidden", "None or an integer >= 1", self.hidden)
        allowed = head_rule(self.controller, self.head, strokes=self.stroke_periods >= 1)
        require(allowed is None, f"{key}.head", allowed, self.head)
        require(math.isfinite(self.wave_k), f"{key}.wave_k", "a finite wave number (rad per voxel length)", self.wave_k)
        require(math.isfinite(self.wave_amplitude) and self.wave_amplitude > 0, f"{key}.wave_amplitude",
                "a finite amplitude > 0", self.wave_amplitude)
        require(math.isfinite(self.wave_gain) and self.wave_gain >= 0, f"{key}.wave_gain", "a finite gain >= 0",
                self.wave_gain)
        require(self.designer is None or (isinstance(self.designer, str) and self.designer != ""
                                          and self.bodies == "population"),
                f"{key}.designer", "None or a path to a design run or checkpoint (with bodies=population)",
                self.designer)
        require(self.controller_init is None or (isinstance(self.controller_init, str) and self.controller_init != ""),
                f"{key}.controller_init", "None or a path to a control run or checkpoint", self.controller_init)
        require(self.prior is None or (isinstance(self.prior, str) and self.prior != "" and not self.codesign),
                f"{key}.prior", "None or a path to a controller.pt or a control run (not with bodies=codesign)",
                self.prior)
        require(isinstance(self.prior_coeff, (int, float)) and self.prior_coeff > 0, f"{key}.prior_coeff",
                "a number > 0", self.prior_coeff)
        require(not (self.codesign and self.privileged_critic), f"{key}.privileged_critic",
                "false with bodies=codesign (a co-design episode observes its design first)", self.privileged_critic)
        require(not self.codesign or self.controller in CODESIGN_CONTROLLERS, f"{key}.controller",
                f"one of {list(CODESIGN_CONTROLLERS)} with bodies=codesign (feed-forward, one set of weights for "
                "every cell: each episode's body differs)", self.controller)

    def episode(self) -> ControlConfig:
        """The env's part (``ControlEnv(control=...)``)."""
        return ControlConfig(**{f.name: getattr(self, f.name) for f in dataclasses.fields(ControlConfig)})


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
    resume: str | None = "auto"
    """``auto``: continue the run in its own run directory when ``checkpoints/last.pt`` is there, else start fresh
    (a requeued job, or the same command with the same ``hydra.run.dir``, picks up where it stopped); a run
    directory or checkpoint file: continue that run, in its directory; None: always start fresh. A resumed run uses
    the checkpoint's config: only ``trainer.*`` and what PPO's evaluation reports (``agent.eval_*``) may differ."""
    stop_grace_s: float = 60.0
    """After SIGTERM/SIGUSR2, how long the epoch in progress may take to finish before it is abandoned (0: at
    once); the run then checkpoints and exits with status 75 (``freeform.preemption``)."""
    record_designs: bool = True
    """Write ``records/epoch_<e>.npz`` (actions, final grids, rewards, critic values, body metrics) every epoch."""
    record_actions: bool = True
    """Keep each episode's actions in the records; off, a record's ``actions`` are ``[E, T, 0]`` (a control run's
    are one command per cell of the box per control step, megabytes an epoch; its controller is in the
    checkpoints)."""
    render_every: int = 0
    """Every this many epochs run the render callback (body images to TensorBoard); 0 = off."""
    print_every: int = 10
    """Every this many epochs print a summary line (console and the run's log); 0 = never."""
    plateau_window: int = 0
    """Stop before ``epochs`` once the run's curve has stopped improving: when the mean of the last this many
    epochs' points (``plateau_on``: the training return, ``episode_reward_mean``, or the evaluation's) is less than
    ``plateau_gain`` above the mean of the window before them (``freeform.run.trainer.flattened``; ``epochs`` is then
    the cap). 0: train every epoch."""
    plateau_gain: float = 0.02
    """With ``plateau_window``: the relative gain a window must add over the one before to go on (0.02: 2 %)."""
    plateau_on: str = "return"
    """The curve ``plateau_window`` reads (``PLATEAU_CURVES``): "return", the training return of every epoch; or
    "eval_return", the deterministic evaluation's (``agent.eval_every``: a window of ``plateau_window`` epochs holds
    ``plateau_window / agent.eval_every`` of its points). The training return of a steering run is one heading a body
    an epoch, so a window of it flattens on the headings' luck; its evaluation, along the same headings every time
    (``agent.eval_same_episodes``), moves with the policy alone."""
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
    algo: AlgoConfig = field(default_factory=AlgoConfig)
    """``ppo`` (the ``agent`` section) or an evolutionary optimiser (``freeform.evolve``)."""
    agent: AgentConfig = field(default_factory=AgentConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    control: ControlRunConfig | None = None
    """None: a design run (the paper's). Set (the ``control_*`` presets): closed-loop control of fixed bodies —
    the env is a ``freeform.envs.control.ControlEnv``, PPO trains a controller (``docs/control.md``)."""


_DEVICES = ("auto", "cpu", "cuda", "mps")
PLATEAU_CURVES = ("return", "eval_return")
"""What ``trainer.plateau_window`` reads: the training return of every epoch, or PPO's evaluation (``eval_return``)."""


def _validate_env(e: EnvConfig) -> None:
    require(e.num_envs >= 1, "env.num_envs", "an integer >= 1", e.num_envs)
    require(e.resolution >= 2 and e.resolution % 2 == 0, "env.resolution",
            "an even integer >= 2 (the network's stride-2 convolution halves it)", e.resolution)
    require(e.steps >= 1, "env.steps", "an integer >= 1", e.steps)
    require(2 <= e.bundle_size <= e.resolution and e.bundle_size % 2 == 0, "env.bundle_size",
            f"an even integer in [2, env.resolution={e.resolution}]", e.bundle_size)
    require(e.action_bound > 0, "env.action_bound", "> 0", e.action_bound)
    require(0 <= e.dense_every <= e.steps, "env.dense_every", f"an integer in [0, env.steps={e.steps}] (0 = sparse)",
            e.dense_every)


def _validate_trainer(t: TrainerConfig) -> None:
    require(t.epochs >= 0, "trainer.epochs", "an integer >= 0", t.epochs)
    require(t.device in _DEVICES or (t.device.startswith("cuda:") and t.device[5:].isdigit()), "trainer.device",
            f"one of {list(_DEVICES)} or 'cuda:<index>'", t.device)
    for name in ("threads", "checkpoint_every", "render_every", "print_every", "plateau_window"):
        require(getattr(t, name) >= 0, f"trainer.{name}", "an integer >= 0 (0 = off/default)", getattr(t, name))
    require(t.stop_grace_s >= 0, "trainer.stop_grace_s", "a number of seconds >= 0", t.stop_grace_s)
    require(t.plateau_gain >= 0, "trainer.plateau_gain", "a relative gain >= 0 (0.02: 2 %)", t.plateau_gain)
    require(t.plateau_on in PLATEAU_CURVES, "trainer.plateau_on", f"one of {list(PLATEAU_CURVES)}", t.plateau_on)


def episode_steps(cfg: TrainConfig) -> int:
    """Steps of one episode of the run's env: T design steps, a control run's control steps, or both (co-design)."""
    control = cfg.control
    if control is None:
        return cfg.env.steps
    return control.steps + (cfg.env.steps if control.codesign else 0)


def _validate_control(cfg: TrainConfig) -> None:
    control = cfg.control
    assert control is not None
    control.validate("control")
    require(cfg.algo.name in ("ppo", "distill"), "algo.name",
            "ppo or distill in a control run (a controller is trained by PPO, or distilled from teachers)", cfg.algo.name)
    require(cfg.algo.name != "distill" or control.teachers > 0, "control.teachers",
            "the teacher run's M with algo.name=distill (environment i is taught by teacher i mod M)", control.teachers)
    if cfg.algo.name == "distill":
        from freeform.agents.distill import DistillConfig

        DistillConfig.from_algo(cfg.algo).validate("algo")
    require(not cfg.env.dense_every, "env.dense_every", "0 in a control run (design rewards have no design here)",
            cfg.env.dense_every)
    require(not control.teachers or cfg.env.num_envs % control.teachers == 0, "env.num_envs",
            f"a multiple of control.teachers = {control.teachers} (environment i drives body i mod M)", cfg.env.num_envs)
    steps = episode_steps(cfg)
    rollout = cfg.agent.rollout_steps
    what = (f"{steps} steps ({cfg.env.steps} design + {control.steps} control)" if control.codesign
            else f"{steps} steps (control.duration / control.period)")
    require(rollout is None or rollout % steps == 0, "agent.rollout_steps",
            f"a multiple of the control episode's {what}, or None: every epoch ends between episodes, where a "
            f"control run checkpoints", rollout)
    require(not cfg.agent.obs_norm, "agent.obs_norm", "false in a control run (the controller reads its action mask "
            "from an observation channel, which must stay 0/1)", cfg.agent.obs_norm)


def validate(cfg: TrainConfig) -> TrainConfig:
    """Check value ranges the types cannot express; raise ``ValueError`` naming the dotted key. Returns ``cfg``."""
    _validate_env(cfg.env)
    require(cfg.task.materials >= 2, "task.materials", "an integer >= 2 (index 0 is empty)", cfg.task.materials)
    if cfg.task.name != "volume":  # a simulated task: every material the designs use must be one the physics knows
        require(cfg.task.materials <= len(cfg.sim.materials) + 1, "task.materials",
                f"<= len(sim.materials) + 1 = {len(cfg.sim.materials) + 1} (materials 1..k-1 are simulated as "
                f"sim.materials[0..k-2])", cfg.task.materials)
    cfg.algo.validate("algo", cfg.env.num_envs, names=learner_names())  # (the registry, below config and app)
    require(cfg.algo.name == "ppo" or not cfg.env.dense_every, "env.dense_every",
            f"0 with algo.name={cfg.algo.name} (evolution scores whole designs; dense rewards are for PPO)",
            cfg.env.dense_every)
    cfg.agent.validate("agent")
    if cfg.control is not None:
        _validate_control(cfg)
    ppo_config(cfg, device="cpu")  # the agent section with the run's values filled in
    cfg.sim.validate("sim")
    _validate_trainer(cfg.trainer)
    # a rule whose curve is never made would never fire: refused, naming what makes it
    if cfg.trainer.plateau_on == "eval_return" and cfg.trainer.plateau_window:
        every = cfg.agent.eval_every
        require(cfg.algo.name == "ppo", "trainer.plateau_on", f"'return' for algo.name={cfg.algo.name} (eval_return is "
                "PPO's evaluation, which a distillation or evolution does not run)", cfg.trainer.plateau_on)
        require(every > 0, "trainer.plateau_on", "'return' where agent.eval_every=0 (eval_return is the "
                "evaluation's curve: set agent.eval_every)", cfg.trainer.plateau_on)
        require(cfg.trainer.plateau_window % every == 0, "trainer.plateau_window", f"a multiple of agent.eval_every="
                f"{every} with plateau_on=eval_return (a window of whole evaluations)", cfg.trainer.plateau_window)
    return cfg


def ppo_config(cfg: TrainConfig, device: str | None) -> PPOConfig:
    """The run's ``freeform.agents.PPOConfig``: the ``agent`` section (less the network's fields) with
    ``rollout_steps`` defaulting to ``env.steps``, ``seed`` to the run's and ``device`` to ``device``."""
    agent = cfg.agent
    values = {f.name: getattr(agent, f.name) for f in dataclasses.fields(PPOConfig)}
    episode = episode_steps(cfg)
    values["rollout_steps"] = agent.rollout_steps if agent.rollout_steps is not None else episode
    values["seed"] = agent.seed if agent.seed is not None else cfg.seed
    values["device"] = agent.device if agent.device is not None else device
    try:
        return PPOConfig(**values)
    except ValueError as exc:
        raise ValueError(str(exc).replace("PPOConfig.", "agent.", 1)) from exc


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


def compose(*overrides: str) -> TrainConfig:
    """The validated :class:`TrainConfig` that ``freeform-train *overrides`` runs, composed from the installed
    ``conf/`` (``compose("experiment=rough_cpu", "trainer.epochs=3")``): for scripts, benchmarks and tests that
    start from a preset instead of restating its numbers. Not inside a running Hydra app (Hydra is initialised
    here)."""
    return to_dataclass(compose_raw(*overrides))


def compose_raw(*overrides: str) -> Any:
    """The composed config of ``freeform-train *overrides`` as Hydra's ``DictConfig``, neither typed into
    :class:`TrainConfig` nor validated (what a command line's check looks at before the run starts)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from freeform._conf_dir import conf_dir

    register_configs()
    with initialize_config_dir(version_base="1.3", config_dir=str(conf_dir()), job_name="train"):
        return hydra_compose("config", overrides=list(overrides))


def cleanrl_agent(preset: dict[str, Any] = CLEANRL_PRESET) -> AgentConfig:
    """``agent=cleanrl``: CleanRL's ``ppo_continuous_action.py`` (``freeform.agents.ppo.CLEANRL_PRESET``), with the
    run filling ``rollout_steps`` (= env.steps) and ``seed`` (the run's); ``agent=cleanrl_discrete`` the same from
    ``ppo.py``'s values (``CLEANRL_DISCRETE_PRESET``: its entropy bonus, 4 passes, no normalisation)."""
    return AgentConfig(**{**preset, "rollout_steps": None, "seed": None})


def register_configs() -> None:
    """Register :class:`TrainConfig` with Hydra's ConfigStore as ``train_schema`` (``conf/config.yaml``'s base), and
    the presets written in Python (``agent=cleanrl``, ``agent=cleanrl_discrete``): built from their one source, not restated in YAML."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    store.store(name="train_schema", node=TrainConfig)
    store.store(group="agent", name="cleanrl", node=cleanrl_agent())
    store.store(group="agent", name="cleanrl_discrete", node=cleanrl_agent(CLEANRL_DISCRETE_PRESET))


__all__ = [
    "AgentConfig",
    "AlgoConfig",
    "BODY_SOURCES",
    "CONTROLLERS",
    "ControlRunConfig",
    "EnvConfig",
    "SimConfig",
    "TaskConfig",
    "TrainConfig",
    "TrainerConfig",
    "compose",
    "episode_steps",
    "flatten",
    "from_container",
    "ppo_config",
    "register_configs",
    "to_container",
    "to_dataclass",
    "validate",
]
