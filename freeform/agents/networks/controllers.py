"""Controllers for the control env (:class:`freeform.envs.control.ControlEnv`) and a registry of them by kind.

Every controller reads observations ``[N, C, Bx, By, Bz]`` (the env's box; ``filled_channel`` marks the body's
cells, ``mask_channel`` the cells whose command acts) and returns a ``MaskedDiagGaussian``'s parameters and the
critic's value: ``(mean [N, A], log_std [N, A], mask [N, A], value [N])``, A = Bx·By·Bz, C order; the mask is read
from the observation. Each keeps its constructor's arguments in ``init_kwargs`` and has ``for_env(env, hidden,
log_std)``; the actor's head starts near 0 (an untrained controller leaves a body near rest, or on its open-loop
gait under residual control; a ``wave`` head plays its hand-set travelling wave) and σ is one learned number.

=============  ==============================  =====================  ==========================================
kind           class                           one set of weights     padding changes nothing
=============  ==============================  =====================  ==========================================
``conv``       :class:`ConvController`         any box                no: its biases leak into the padding
``mlp``        :class:`MLPController`          its own box only       (one box)
``context``    :class:`ContextConvController`  any box                yes: features masked after every layer
``attention``  :class:`VoxelAttentionController`  any box              yes: only the filled cells are tokens
=============  ==============================  =====================  ==========================================

``context_gru`` and ``attention_gru`` are ``context`` and ``attention`` with a memory of the episode (recurrent
policies, ``freeform.agents.networks.recurrent``), ``attention_hyper`` is ``attention`` with an actor that each body writes
(a hypernetwork); the voxel-token kinds live in :mod:`freeform.agents.networks.attention_controllers`.

"Padding changes nothing": a body's commands (on its cells) and value are the same, within float rounding,
whether it sits alone in its own box or in the larger box of a batch with larger bodies (the env pads every body
to the batch's box, at its corner). The costs of each on the 2-core CPU are in ``docs/control.md``.

:func:`build_controller` builds one by kind for an env. The actor heads the body controllers share are in
:mod:`freeform.agents.networks.controller_heads`; the self-contained ``controller.pt`` (``save_controller``,
``read_controller``) in :mod:`freeform.agents.controller_file`.
"""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn as nn
import torch.nn.functional as F

from freeform.agents.networks import MLPActorCritic, rebuild
from freeform.agents.networks.attention_controllers import (
    HyperAttentionController,
    RecurrentAttentionController,
    VoxelAttentionController,
)
from freeform.agents.networks.controller_heads import (
    DEFAULT_WAVE,
    ControlInputs,
    FromInputs,
    HandSetWave,
    body_controller_setup,
    cell_means,
    check_control_input,
    env_wave,
    head_rule,
    masked_pool,
    wave_at_gain,
)
from freeform.agents.networks.observation_groups import CRITIC, POLICY, is_grouped
from freeform.agents.networks.recurrent import RecurrentPolicy, run_rnn
from freeform.distributions import MaskedDiagGaussian


class ConvController(nn.Module):
    """A controller that fits any body: a fully convolutional 3-D actor-critic over a body's cells.

    Observations ``[N, C, Bx, By, Bz]`` (the control env's box; channel ``mask_channel`` marks the cells whose
    command acts). Trunk: Conv3d(C→h, 3³, pad 1) → ReLU → Conv3d(h→h, 3³, pad 1) → ReLU, so each cell's features
    see its 5³ neighbourhood and the task features every filled cell carries; one set of weights for every cell of
    every body. Actor: Conv3d(h→1, 1³) = each cell's mean command, a learned log σ shared by all cells. Critic: the
    trunk's features averaged over the filled cells (channel ``filled_channel``) → Linear(h→h) → tanh → Linear(h→1).
    Outputs ``(mean, log_std, mask [N, Bx·By·Bz], value [N])``: a ``MaskedDiagGaussian``'s parameters, the mask read
    from the observation.

    Padding is not neutral here: the first convolution's bias makes every empty cell's features non-zero, and the
    second reads them, so a body's commands depend on the box it is padded to, i.e. on the other bodies of its
    batch (a test shows it). Kept as it is: the trained results in ``docs/control.md`` are this network's.
    """

    def __init__(self, channels: int, box: tuple[int, int, int] | list[int], mask_channel: int, filled_channel: int = 0,
                 hidden: int = 16, log_std: float = 0.0) -> None:
        super().__init__()
        box = check_control_input(channels, box, mask_channel=mask_channel, filled_channel=filled_channel)
        if not isinstance(hidden, int) or hidden < 1:
            raise ValueError(f"hidden must be a positive int, got {hidden!r}")
        self.init_kwargs = dict(channels=channels, box=box, mask_channel=mask_channel, filled_channel=filled_channel,
                                hidden=hidden, log_std=log_std)
        self.box, self.mask_channel, self.filled_channel = box, mask_channel, filled_channel
        self.distribution = MaskedDiagGaussian(math.prod(box))
        self.conv1 = nn.Conv3d(channels, hidden, 3, padding=1)
        self.conv2 = nn.Conv3d(hidden, hidden, 3, padding=1)
        self.actor = nn.Conv3d(hidden, 1, 1)
        nn.init.normal_(self.actor.weight, std=0.01)  # the untrained controller commands ≈ 0: a body at rest
        nn.init.zeros_(self.actor.bias)
        self.log_std = nn.Parameter(torch.tensor(float(log_std)))
        self.critic_fc = nn.Linear(hidden, hidden)
        self.critic_out = nn.Linear(hidden, 1)

    fits_any_box = True
    padding_invariant = False

    @classmethod
    def for_env(cls, env: Any, hidden: int = 16, log_std: float = 0.0) -> ConvController:
        """The controller for a ``ControlEnv`` (its box, channels and mask channel)."""
        return cls(env.observation_shape[0], env.observation_shape[1:], env.mask_channel, env.filled_channel, hidden,
                   log_std)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``[N, C, Bx, By, Bz]`` → (mean, log_std, mask ``[N, Bx·By·Bz]``, value ``[N]``)."""
        n = obs.shape[0]
        x = F.relu(self.conv2(F.relu(self.conv1(obs))))
        mean = self.actor(x).reshape(n, -1)
        mask = obs[:, self.mask_channel].reshape(n, -1)
        filled = obs[:, self.filled_channel : self.filled_channel + 1]
        pooled = (x * filled).sum((2, 3, 4)) / filled.sum((2, 3, 4)).clamp_min(1.0)
        value = self.critic_out(torch.tanh(self.critic_fc(pooled))).squeeze(-1)
        return mean, self.log_std.expand_as(mean), mask, value


class MLPController(nn.Module):
    """The baseline controller: tanh MLPs over the whole flattened box (``MLPActorCritic``'s layers), one output per
    cell, a learned log σ per cell; the mask read from channel ``mask_channel`` as in :class:`ConvController`.
    Unlike the convolutional one it fits one box size and learns each cell apart."""

    fits_any_box = False
    padding_invariant = False

    def __init__(self, channels: int, box: tuple[int, int, int] | list[int], mask_channel: int,
                 hidden: tuple[int, ...] | list[int] = (64, 64), log_std: float = 0.0) -> None:

        super().__init__()
        box = check_control_input(channels, box, mask_channel=mask_channel)
        cells = math.prod(box)
        self.init_kwargs = dict(channels=channels, box=box, mask_channel=mask_channel, hidden=tuple(hidden),
                                log_std=log_std)
        self.box, self.mask_channel = box, mask_channel
        self.distribution = MaskedDiagGaussian(cells)
        self.net = MLPActorCritic(channels * cells, cells, hidden)
        with torch.no_grad():
            self.net.log_std.fill_(float(log_std))

    @classmethod
    def for_env(cls, env: Any, hidden: int | tuple[int, ...] | list[int] = (64, 64), log_std: float = 0.0) -> MLPController:
        """The controller for a ``ControlEnv``; an int ``hidden`` h is two layers of h."""
        hidden = (hidden, hidden) if isinstance(hidden, int) else hidden
        return cls(env.observation_shape[0], env.observation_shape[1:], env.mask_channel, hidden, log_std)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``[N, C, Bx, By, Bz]`` → (mean, log_std, mask ``[N, Bx·By·Bz]``, value ``[N]``)."""
        mean, log_std, value = self.net(obs)
        return mean, log_std, obs[:, self.mask_channel].reshape(obs.shape[0], -1), value


class ContextConvController(FromInputs, nn.Module):
    """A masked convolutional controller with a view of the whole body: each cell's command reads its 5³
    neighbourhood and the body's pooled features, and the padding around a body changes nothing.

    Observations ``[N, C, Bx, By, Bz]``; f = the ``filled`` channel ``[N, 1, Bx, By, Bz]``. Trunk::

        x = ReLU(Conv3d(C→h, 3³)(obs)) · f
        for each of ``blocks`` blocks:   x = ReLU(Conv3d(h→h, 3³)(x) + Linear(2h→h)(pool(x))) · f

    with pool(x) ``[N, 2h]`` the mean and max of x over the filled cells, broadcast to every cell. Multiplying by f
    after every layer keeps the padding's features 0 (a bias never leaks into it), so a body in a larger box sees
    the zeros it would see at its own box's edge: the same commands. Actor: Conv3d(h→1, 1³) · f, each cell's mean
    command (weights N(0, 0.01²), bias 0; the other heads of ``controller_heads.HEADS``: Conv3d(h→3, 1³), the cell's
    rhythm; Conv3d(h→2, 1³), a stroke's (a, b); Conv3d(h→4, 1³), a wave's amplitude, phase and correction, with the
    body's wave vector Linear(2h→3)(pool(x)) added to the hand-set wave's ``k`` along x); one learned log σ. Critic: pool(x) →
    Linear(2h→h) → tanh → Linear(h→1).

    One block (the default) is ConvController's two 3³ convolutions plus the body's context, at about its cost on
    the CPU (``python -m benchmarks controllers``); each further block adds a 3³ convolution and a round of context.
    """

    fits_any_box = True
    padding_invariant = True

    def __init__(self, inputs: ControlInputs, hidden: int = 16, blocks: int = 1, log_std: float = 0.0,
                 head: str = "direct", wave: dict[str, Any] | None = None) -> None:
        super().__init__()
        outputs = body_controller_setup(self, inputs, head, log_std, wave, hidden=hidden, blocks=blocks)
        self.conv_in = nn.Conv3d(inputs.channels, hidden, 3, padding=1)
        self.convs = nn.ModuleList(nn.Conv3d(hidden, hidden, 3, padding=1) for _ in range(blocks))
        self.contexts = nn.ModuleList(nn.Linear(2 * hidden, hidden) for _ in range(blocks))
        self.actor = nn.Conv3d(hidden, outputs, 1)
        nn.init.normal_(self.actor.weight, std=0.01)  # the untrained controller commands ≈ 0
        nn.init.zeros_(self.actor.bias)
        self.log_std = nn.Parameter(torch.tensor(float(log_std)))
        self.critic_fc = nn.Linear(2 * hidden, hidden)
        self.critic_out = nn.Linear(hidden, 1)

    @classmethod
    def for_env(cls, env: Any, hidden: int = 16, log_std: float = 0.0, head: str = "direct",
                wave: HandSetWave = DEFAULT_WAVE) -> ContextConvController:
        """The controller for a ``ControlEnv`` (its box, channels, mask and filled channels; a wave head's
        untrained ``wave``)."""
        return cls(ControlInputs.of(env, head), hidden, log_std=log_std, head=head, wave=env_wave(env, head, wave))

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``[N, C, Bx, By, Bz]`` → (mean, log_std, mask ``[N, Bx·By·Bz]``, value ``[N]``)."""
        filled = obs[:, self.filled_channel : self.filled_channel + 1]
        x = F.relu(self.conv_in(obs)) * filled
        for conv, context in zip(self.convs, self.contexts, strict=True):
            x = F.relu(conv(x) + context(masked_pool(x, filled))[:, :, None, None, None]) * filled
        pooled = masked_pool(x, filled)
        mean, mask = cell_means(self, self.actor(x), obs, filled, pooled)
        value = self.critic_out(torch.tanh(self.critic_fc(pooled))).squeeze(-1)
        return mean, self.log_std.expand_as(mean), mask, value


class RecurrentContextController(FromInputs, nn.Module):
    """:class:`ContextConvController` with a memory of how this body has moved: a GRU over the body's pooled
    features, step after step of the episode, whose state joins the body's context in every cell's command and in
    the critic. A controller meeting a body it never saw can then tell, from the body's answers to its last
    commands (sensed velocities, strains, contacts), what kind of body it drives — the implicit system
    identification that a feed-forward controller, which sees one instant, cannot do.

    A recurrent policy (``freeform.agents.networks.recurrent``): observations ``[T, N, C, Bx, By, Bz]``, the state
    ``(h [N, 1, M],)`` (zeros at an episode's start; actor and critic share it), ``episode_start [T, N]``. Trunk at
    each step, f the ``filled`` channel::

        x = ReLU(Conv3d(C→h, 3³)(obs)) · f
        m_t = GRU(pool(x), m_{t−1})                                     (M wide: ``memory``)
        x = ReLU(Conv3d(h→h, 3³)(x) + Linear(2h+M→h)([pool(x), m_t])) · f

    then ContextConvController's heads (``direct``, ``rhythm``, ``stroke``, ``wave``), the critic on
    ``[pool(x), m_t]``.
    Padding changes nothing, as there. The convolutions run on all T·N observations at once; only the GRU steps.
    """

    fits_any_box = True
    padding_invariant = True
    actor_state_size = 1  # the GRU's state is the actor's (the critic reads it): an exported actor carries it all

    def __init__(self, inputs: ControlInputs, hidden: int = 16, memory: int = 32, log_std: float = 0.0,
                 head: str = "direct", wave: dict[str, Any] | None = None) -> None:
        super().__init__()
        outputs = body_controller_setup(self, inputs, head, log_std, wave, hidden=hidden, memory=memory)
        self.memory = memory
        self.conv_in = nn.Conv3d(inputs.channels, hidden, 3, padding=1)
        self.gru = nn.GRU(2 * hidden, memory)
        self.conv = nn.Conv3d(hidden, hidden, 3, padding=1)
        self.context = nn.Linear(2 * hidden + memory, hidden)
        self.actor = nn.Conv3d(hidden, outputs, 1)
        nn.init.normal_(self.actor.weight, std=0.01)  # the untrained controller commands ≈ 0
        nn.init.zeros_(self.actor.bias)
        self.log_std = nn.Parameter(torch.tensor(float(log_std)))
        self.critic_fc = nn.Linear(2 * hidden + memory, hidden)
        self.critic_out = nn.Linear(hidden, 1)

    @classmethod
    def for_env(cls, env: Any, hidden: int = 16, log_std: float = 0.0, head: str = "direct",
                memory: int = 32, wave: HandSetWave = DEFAULT_WAVE) -> RecurrentContextController:
        """The controller for a ``ControlEnv`` (its box, channels, mask and filled channels; a wave head's
        untrained ``wave``)."""
        return cls(ControlInputs.of(env, head), hidden, memory, log_std=log_std, head=head,
                   wave=env_wave(env, head, wave))

    def initial_state(self, num_envs: int) -> tuple[torch.Tensor, ...]:
        """``(zeros [N, 1, memory],)``: the GRU's state at an episode's start."""
        return (self.log_std.new_zeros(num_envs, 1, self.memory),)

    def _steps(self, obs: torch.Tensor, state: tuple[torch.Tensor, ...], episode_start: torch.Tensor
               ) -> tuple[tuple[torch.Tensor, ...], torch.Tensor, tuple[torch.Tensor, ...]]:
        """→ ((mean, log σ, mask) ``[T, N, A]`` each, the critic's input ``[T·N, 2h+M]``, the state after the last
        step)."""
        steps, n = obs.shape[:2]
        o = obs.flatten(0, 1)
        filled = o[:, self.filled_channel : self.filled_channel + 1]
        x = F.relu(self.conv_in(o)) * filled
        pooled = masked_pool(x, filled)
        m, state = run_rnn(self.gru, pooled.view(steps, n, -1), state, episode_start)
        x = F.relu(self.conv(x) + self.context(torch.cat([pooled, m.flatten(0, 1)], 1))[:, :, None, None, None]) * filled
        body = masked_pool(x, filled)
        mean, mask = (t.view(steps, n, -1) for t in cell_means(self, self.actor(x), o, filled, body))
        summary = torch.cat([body, m.flatten(0, 1)], 1)
        return (mean, self.log_std.expand_as(mean), mask), summary, state

    def action_params(self, obs: torch.Tensor, actor_state: tuple[torch.Tensor, ...], episode_start: torch.Tensor
                      ) -> tuple[tuple[torch.Tensor, ...], tuple[torch.Tensor, ...]]:
        """The actor alone: ``obs [T, N, C, Bx, By, Bz]`` → ((mean, log σ, mask) ``[T, N, A]`` each, state)."""
        params, _, state = self._steps(obs, actor_state, episode_start)
        return params, state

    def forward(self, obs: torch.Tensor, state: tuple[torch.Tensor, ...], episode_start: torch.Tensor
                ) -> tuple[Any, ...]:
        """``obs [T, N, C, Bx, By, Bz]``, ``state``, ``episode_start [T, N]`` → (mean, log σ, mask ``[T, N, A]``,
        value ``[T, N]``, state)."""
        params, summary, state = self._steps(obs, state, episode_start)
        value = self.critic_out(torch.tanh(self.critic_fc(summary))).view(obs.shape[:2])
        return (*params, value, state)


CONTROLLERS: dict[str, type[nn.Module]] = {"conv": ConvController, "mlp": MLPController,
                                           "context": ContextConvController, "attention": VoxelAttentionController,
                                           "context_gru": RecurrentContextController,
                                           "attention_gru": RecurrentAttentionController,
                                           "attention_hyper": HyperAttentionController}
"""``control.controller`` → the controller's class. Each has ``for_env(env, hidden, log_std)`` and ``init_kwargs``;
``fits_any_box`` says whether one set of weights runs on any box, ``padding_invariant`` whether the padding around
a body changes nothing."""


CODESIGN_KINDS = tuple(k for k, c in CONTROLLERS.items() if c.fits_any_box and not issubclass(c, RecurrentPolicy))
"""The kinds a co-design policy's controller may be (``CodesignActorCritic``, ``control.controller`` with
``bodies=codesign``): feed-forward, one set of weights for every cell (each episode's body differs)."""


class PrivilegedCritic(nn.Module):
    """A controller whose critic also reads privileged state: for an env observing the groups ``{"policy": the
    cells' channels [N, C, Bx, By, Bz], "critic": [N, S]}`` (``ControlConfig.privileged_critic``). The actor is the
    controller's own, on ``obs["policy"]`` alone (what a deployed controller senses); the value is the controller's
    own value plus a small MLP of (that value, ``obs["critic"]``), whose last layer starts at zero, so training
    starts from the controller's critic and learns what the privileged state adds (e.g. the distance already
    covered, on which a ``headings="any"`` reward depends).

    kind, controller: the controller's registry name and ``init_kwargs``; critic_dim: S; hidden: the MLP's width.
    """

    def __init__(self, kind: str, controller: dict[str, Any], critic_dim: int, hidden: int = 64) -> None:
        super().__init__()
        if kind not in CONTROLLERS:
            raise ValueError(f"controller kind must be one of {list(CONTROLLERS)}, got {kind!r}")
        if not isinstance(critic_dim, int) or critic_dim < 1:
            raise ValueError(f"critic_dim must be a positive int, got {critic_dim!r}")
        self.controller = rebuild(CONTROLLERS[kind], controller)
        self.critic_head = nn.Sequential(nn.Linear(critic_dim + 1, hidden), nn.Tanh(), nn.Linear(hidden, 1))
        nn.init.zeros_(self.critic_head[-1].weight)
        nn.init.zeros_(self.critic_head[-1].bias)
        self.distribution = self.controller.distribution
        self.fits_any_box = self.controller.fits_any_box
        self.padding_invariant = self.controller.padding_invariant
        self.kind = kind
        self.init_kwargs = {"kind": kind, "controller": dict(self.controller.init_kwargs), "critic_dim": critic_dim,
                            "hidden": hidden}

    def action_params(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, ...]:
        """``obs["policy"]`` → (mean, log σ, mask): the controller's; the critic group is never read."""
        return tuple(self.controller(obs["policy"])[:-1])

    def value(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """Both groups → V ``[N]``."""
        return self._value(self.controller(obs["policy"])[-1], obs["critic"])

    def forward(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, ...]:
        """(mean, log σ, mask, value), as a controller's forward."""
        *params, own = self.controller(obs["policy"])
        return (*params, self._value(own, obs["critic"]))

    def _value(self, own: torch.Tensor, privileged: torch.Tensor) -> torch.Tensor:
        return own + self.critic_head(torch.cat([own[:, None], privileged.to(own.dtype)], 1)).squeeze(-1)


def controller_observe(net: nn.Module, state: tuple[torch.Tensor, ...] | None, reward: torch.Tensor
                       ) -> tuple[torch.Tensor, ...] | None:
    """``state`` after a step that earned ``reward`` ``[N]``: a controller that reads rewards (``observe``: a
    :class:`~freeform.agents.networks.gated.TrialGate`) is told; any other's state is as it was."""
    observe = getattr(net, "observe", None)
    return observe(state, reward) if observe is not None and state is not None else state


def controller_step(net: nn.Module, obs: torch.Tensor, state: tuple[torch.Tensor, ...] | None = None
                    ) -> tuple[tuple[torch.Tensor, ...], tuple[torch.Tensor, ...] | None]:
    """One control step of any controller: ``obs [N, C, Bx, By, Bz]`` → ((mean, log σ, mask, value), state). A
    recurrent one (``initial_state``, e.g. :class:`RecurrentContextController`) starts from its initial state where
    ``state`` is None and returns the state after the step; a feed-forward one returns None for it."""
    if not isinstance(net, RecurrentPolicy):
        return tuple(net(obs)), None
    if state is None:
        state = net.initial_state(obs.shape[0])
    *out, state = net(obs[None], state, torch.zeros(1, obs.shape[0], dtype=torch.bool, device=obs.device))
    return tuple(o[0] for o in out), state


def build_controller(kind: str, env: Any, hidden: int | None = None, log_std: float = 0.0,
                     head: str = "direct", wave: HandSetWave = DEFAULT_WAVE) -> nn.Module:
    """The controller of ``kind`` (a key of :data:`CONTROLLERS`) for a ``ControlEnv``, ``hidden`` wide (None: the
    kind's default; the MLP's two layers are each ``hidden`` wide), its log σ starting at ``log_std``, its actor's
    ``head`` (``controller_heads.HEADS``; ``rhythm`` and ``stroke`` for the kinds with a view of the whole body, :data:`~freeform.agents.networks.controller_heads.RHYTHM_KINDS`;
    ``wave`` for :data:`WAVE_KINDS`, starting from the hand-set ``wave``).
    An env observing the groups ``"policy"`` and ``"critic"`` (``ControlConfig.privileged_critic``) gets it inside
    a :class:`PrivilegedCritic`."""

    if kind == "gated":
        raise ValueError("controller kind 'gated' is made of trained controllers, not trained itself: "
                         "freeform-control gate CONTROLLERS... --out FILE")
    if kind not in CONTROLLERS:
        raise ValueError(f"controller kind must be one of {list(CONTROLLERS)}, got {kind!r}")
    shape = env.observation_shape
    if is_grouped(shape):
        if issubclass(CONTROLLERS[kind], RecurrentPolicy):
            raise ValueError(f"controller {kind!r} is recurrent, and PrivilegedCritic wraps feed-forward controllers "
                             "(its critic reads one step): set control.privileged_critic=false")
        view = _PolicyView(env, shape[POLICY])
        inner = build_controller(kind, view, hidden, log_std, head, wave)
        return PrivilegedCritic(kind, dict(inner.init_kwargs), int(math.prod(shape[CRITIC])))
    allowed = head_rule(kind, head, strokes=getattr(env, "action_channels", 1) == 2)
    if allowed is not None:
        raise ValueError(f"head must be {allowed}, got {head!r}")
    width = {} if hidden is None else {"hidden": hidden}
    options = {} if head == "direct" else {"head": head}
    if head == "wave":
        options["wave"] = wave
    return CONTROLLERS[kind].for_env(env, log_std=log_std, **width, **options)


class _PolicyView:
    """An env as its actor sees it: the ``"policy"`` group's shape, everything else the env's."""

    def __init__(self, env: Any, shape: tuple[int, ...]) -> None:
        self._env, self.observation_shape = env, tuple(shape)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._env, name)


def controller_kind(controller: nn.Module) -> str:
    """The registry's name for ``controller``'s class (a :class:`PrivilegedCritic`'s: its controller's)."""
    if isinstance(controller, PrivilegedCritic):
        return controller.kind
    for kind, cls in CONTROLLERS.items():
        if type(controller) is cls:
            return kind
    raise ValueError(f"{type(controller).__name__} is not one of the registered controllers {list(CONTROLLERS)}")


def with_wave_gain(controller: nn.Module, gain: float) -> nn.Module:
    """A copy of ``controller`` (a wave-head body controller, or a :class:`PrivilegedCritic` around one) whose wave
    plays at ``gain`` (``HandSetWave.gain``): the same weights, its mean command the hand-set wave's strokes plus
    ``gain`` × the head's change to them."""
    privileged = isinstance(controller, PrivilegedCritic)
    actor = controller.controller if privileged else controller
    if getattr(actor, "wave", None) is None:
        raise ValueError(f"a wave gain needs a wave head; this {type(actor).__name__}'s head is "
                         f"{getattr(actor, 'head', None)!r} (gain applies to controllers trained with "
                         "control.head=wave: evaluate this one without --wave-gain)")
    kwargs = actor.init_kwargs  # (the gain is checked where the head reads it, as the config's wave_gain is)
    kwargs = {**kwargs, "wave": wave_at_gain(kwargs["wave"], gain)}
    out = (rebuild(PrivilegedCritic, {**controller.init_kwargs, "controller": kwargs}) if privileged
           else rebuild(type(controller), kwargs))
    out.load_state_dict(controller.state_dict())
    return out


__all__ = ["CODESIGN_KINDS", "CONTROLLERS", "ContextConvController", "ConvController", "HyperAttentionController",
           "MLPController", "PrivilegedCritic", "RecurrentAttentionController", "RecurrentContextController",
           "VoxelAttentionController", "build_controller", "controller_kind", "controller_observe", "controller_step",
           "with_wave_gain"]
