"""What the controllers of :mod:`freeform.agents.networks.controllers` share: the input checks, the body's pooled
features, and the actor heads (:data:`HEADS`) that turn each cell's features into its mean action — a command, a
rhythm on the actuation clock, a stroke's (a, b), or a travelling wave's stroke."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import torch
import torch.nn as nn

from freeform.distributions import MaskedDiagGaussian


@dataclass(frozen=True)
class ControlInputs:
    """What a controller reads of a control env's observation ``[N, C, Bx, By, Bz]``: its ``channels`` C, the
    ``box`` (Bx, By, Bz), the ``mask_channel`` (the actuated cells, whose command acts), the ``filled_channel`` (the
    body's cells) and a rhythm head's ``clock_channels`` (clock_sin, clock_cos). A controller's ``init_kwargs`` hold
    them by these names, beside its own sizes."""

    channels: int
    box: Any
    mask_channel: int
    filled_channel: int = 0
    clock_channels: Any = None

    @classmethod
    def of(cls, env: Any, head: str = "direct") -> ControlInputs:
        """A ``ControlEnv``'s (its box, channels, mask and filled channels; the clock for a ``rhythm`` head)."""
        return cls(env.observation_shape[0], env.observation_shape[1:], env.mask_channel, env.filled_channel,
                   _env_clock(env, head))

    @staticmethod
    def split(init_kwargs: dict[str, Any]) -> tuple[ControlInputs, dict[str, Any]]:
        """A controller's ``init_kwargs`` as (its inputs, the rest: its own constructor arguments)."""
        names = {f.name for f in fields(ControlInputs)}
        inputs = ControlInputs(**{k: v for k, v in init_kwargs.items() if k in names})
        return inputs, {k: v for k, v in init_kwargs.items() if k not in names}


class FromInputs:
    """A controller built from :class:`ControlInputs` and its own sizes: :meth:`from_init_kwargs` rebuilds it from
    its (flat) ``init_kwargs`` (``freeform.agents.networks.rebuild``)."""

    @classmethod
    def from_init_kwargs(cls, init_kwargs: dict[str, Any]) -> Any:
        inputs, rest = ControlInputs.split(init_kwargs)
        return cls(inputs, **rest)


def check_control_input(channels: int, box: Any, **channel_indices: int) -> tuple[int, int, int]:
    """A controller's observation ``[C, Bx, By, Bz]`` checked: the box as three positive ints, each named index a
    channel."""
    if not isinstance(channels, int) or channels < 1:
        raise ValueError(f"channels must be a positive int, got {channels!r}")
    box = tuple(int(b) for b in box)
    if len(box) != 3 or min(box) < 1:
        raise ValueError(f"box must be three positive ints (Bx, By, Bz), got {box!r}")
    for name, index in channel_indices.items():
        if not isinstance(index, int) or not 0 <= index < channels:
            raise ValueError(f"{name} must be a channel index in [0, {channels}), got {index!r}")
    return box  # type: ignore[return-value]


RHYTHM_KINDS = ("context", "attention", "context_gru", "attention_gru", "attention_hyper")
"""The kinds whose actor may have a ``rhythm`` head (:data:`HEADS`): those with a view of the whole body."""

WAVE_KINDS = RHYTHM_KINDS
"""The kinds whose actor may have a ``wave`` head (it reads the body's pooled features): the same kinds, one list, so
that a new kind is added once."""


def masked_pool(x: torch.Tensor, filled: torch.Tensor) -> torch.Tensor:
    """Features ``x [N, h, Bx, By, Bz]`` (≥ 0, zero outside the body) pooled over the body's cells (``filled
    [N, 1, Bx, By, Bz]``): their mean and max ``[N, 2h]``. The max over the whole box is the body's, since every
    feature is ≥ 0 and the padding's are 0."""
    count = filled.sum((2, 3, 4)).clamp_min(1.0)
    return torch.cat([x.sum((2, 3, 4)) / count, x.amax((2, 3, 4))], dim=1)


HEADS = ("direct", "rhythm", "stroke", "wave")
"""What a controller's actor head gives each cell: ``direct`` — its mean command, one number from its features;
``rhythm`` — three numbers (u, v, w) and the mean command u·sin(2πt/T) + v·cos(2πt/T) + w, t/T the actuation
clock's phase the observation carries (``clock_sin``, ``clock_cos``): a rhythm at the open-loop sine's frequency
whose amplitude and phase each voxel's features set (a travelling wave when they vary with the voxel's place
in the body), and a slow offset w for feedback. The network then learns smooth functions of a voxel's place and
state instead of products of them with the clock. ``stroke`` — two numbers (a, b), the action itself of an env
whose actions are strokes (``ControlConfig.stroke_periods``: the env plays a·sin + b·cos of each voxel's own phase
over several periods); the mean is ``[N, 2·cells]``, every a then every b, the mask repeated. ``wave`` — a stroke
whose mean is a travelling wave (:func:`_wave_strokes`): the body's wave vector k (from its pooled features, starting
at ``wave_k`` along x, or along the heading where the env has one: :func:`_wave_vector`), each cell's amplitude and
phase offset, and a free (a, b) correction; a voxel at x relative
to the centre of mass then receives A·sin(2πt/T − k·x − ψ), the rule that moves bodies of every kind
(``docs/control.md``) with the wave's direction, length and shape learnt per body."""

STROKE_HEADS = ("stroke", "wave")
"""The heads whose actions are strokes (``ControlConfig.stroke_periods`` >= 1): two numbers a cell."""


def head_rule(kind: str, head: str, strokes: bool) -> str | None:
    """The one rule for an actor head, checked by the config and by ``build_controller``: what ``head`` must be
    for a ``kind`` controller on an env whose actions are strokes (``strokes``: ``stroke_periods >= 1``) or not, as
    the ``allowed`` of ``<key> must be <allowed>, got <head>``; None where ``head`` is allowed."""
    if head not in HEADS:
        return f"one of {list(HEADS)}"
    if head == "wave" and kind not in WAVE_KINDS:
        return f"not 'wave' for controller {kind!r} (head='wave' is for the controllers {list(WAVE_KINDS)})"
    if head != "direct" and kind not in RHYTHM_KINDS:
        return f"'direct' for controller {kind!r} (head={head!r} is for the controllers {list(RHYTHM_KINDS)})"
    if strokes != (head in STROKE_HEADS):
        return (f"one of {list(STROKE_HEADS)} exactly when control.stroke_periods >= 1 (the env's actions are then "
                "strokes)")
    return None


def _head_outputs(head: str) -> int:
    if head not in HEADS:
        raise ValueError(f"head must be one of {HEADS}, got {head!r}")
    return {"direct": 1, "rhythm": 3, "stroke": 2, "wave": 4}[head]


def _per_cell_mean(out: torch.Tensor, mask: torch.Tensor, head: str) -> tuple[torch.Tensor, torch.Tensor]:
    """A head's per-cell outputs ``[N, c, cells]`` (c = 1, or 2 for a stroke) and the actuated cells ``[N, cells]``
    → (the mean ``[N, c·cells]``, the mask ``[N, c·cells]``)."""
    n = out.shape[0]
    return out.reshape(n, -1), (mask.repeat(1, 2) if head in STROKE_HEADS else mask)


@dataclass(frozen=True)
class HandSetWave:
    """The travelling wave a ``wave`` head plays untrained (its per-cell outputs and wave-vector layer then add to
    it): every voxel receives ``amplitude``·sin(2πt/T − ``k``·x), x its place from the centre of mass along x, or
    along the heading where the env has one. ``k`` in rad per voxel length (0: every voxel in one phase);
    ``amplitude`` > 1 asks more than a muscle's range, so what it receives (clipped to [−1, 1], at most its
    bandwidth's change) is a fuller stroke than the sine: ``docs/control.md``, "Steering"."""

    k: float = 1.0
    amplitude: float = 1.0
    gain: float = 1.0
    """How far a trained head's mean command goes from this wave: the wave's strokes plus ``gain`` × the head's
    change to them (1: the head as trained; 0: the wave itself; > 1 extrapolates what the head learnt, as a
    student distilled from many teachers learns a shrunk change: ``docs/control.md``, "Steering")."""

    def __post_init__(self) -> None:
        if not math.isfinite(float(self.k)):
            raise ValueError(f"wave k (rad per voxel length) must be finite, got {self.k!r}")
        if not (math.isfinite(float(self.amplitude)) and self.amplitude > 0):
            raise ValueError(f"wave amplitude must be finite and > 0, got {self.amplitude!r}")
        if not (math.isfinite(float(self.gain)) and self.gain >= 0):
            raise ValueError(f"wave gain must be finite and >= 0, got {self.gain!r}")


DEFAULT_WAVE = HandSetWave()
"""k = 1 at the open-loop sine's amplitude: ``ControlConfig``'s defaults."""


def _wave_setup(channels: int, head: str, wave: Any) -> dict[str, Any] | None:
    """A ``wave`` head's description of the observation, checked: ``pos_channels`` (rel_x, rel_y, rel_z: voxel
    lengths from the centre of mass), ``material_channel`` (material index / (len(phases) − 1)), ``phases`` (each
    material index's open-loop phase in cycles, index 0 empty), ``residual`` (the env adds the open-loop sine to
    the action), ``k`` (the wave number the untrained head starts from, rad per voxel length, along x) and
    optionally ``amplitude`` (its amplitude, 1 where absent: the files from before) and ``heading_channels``."""
    if head != "wave":
        return None
    keys = {"pos_channels", "material_channel", "phases", "residual", "k"}
    if not isinstance(wave, dict) or not keys <= set(wave) <= keys | {"heading_channels", "amplitude", "gain"}:
        raise ValueError(f"a wave head needs wave = a dict with the keys {sorted(keys)} and optionally "
                         f"heading_channels, amplitude and gain (build_controller fills it from the env), got {wave!r}")
    pos = tuple(int(c) for c in wave["pos_channels"])
    if len(pos) != 3:
        raise ValueError(f"wave pos_channels must be the 3 channels rel_x, rel_y, rel_z, got {wave['pos_channels']!r}")
    check_control_input(channels, (1, 1, 1), rel_x=pos[0], rel_y=pos[1], rel_z=pos[2],
                        material=int(wave["material_channel"]))
    phases = tuple(float(p) for p in wave["phases"])
    if len(phases) < 2 or not all(math.isfinite(p) for p in phases):
        raise ValueError(f"wave phases must be finite, one per material index (index 0 empty), got {wave['phases']!r}")
    start = HandSetWave(float(wave["k"]), float(wave.get("amplitude", 1.0)), float(wave.get("gain", 1.0)))
    setup = dict(pos_channels=pos, material_channel=int(wave["material_channel"]), phases=phases,
                 residual=bool(wave["residual"]), k=start.k, amplitude=start.amplitude, gain=start.gain)
    if wave.get("heading_channels") is not None:  # (a file from before steering has no key: its wave stays along x)
        heading = tuple(int(c) for c in wave["heading_channels"])
        if len(heading) != 2:
            raise ValueError(f"wave heading_channels must be the 2 channels heading_cos, heading_sin, got "
                             f"{wave['heading_channels']!r}")
        check_control_input(channels, (1, 1, 1), heading_cos=heading[0], heading_sin=heading[1])
        setup["heading_channels"] = heading
    return setup


def wave_at_gain(wave: dict[str, Any], gain: float) -> dict[str, Any]:
    """A wave head's ``wave`` (its ``init_kwargs["wave"]``) playing at ``gain``, in a file's form: no gain key at 1, so
    files, and the teacher banks' kwargs that pooling compares, read as they did before the gain."""
    rest = {k: v for k, v in wave.items() if k != "gain"}
    return rest if gain == 1.0 else {**rest, "gain": float(gain)}


def wave_follows_heading(control: Any) -> bool:
    """Whether a wave head for an env of ``control`` (a ``ControlConfig``) turns its wave with the observation's
    heading channels: where there is a heading and the observation is in the world's frame (in the heading's frame
    the wave runs along x, which is the heading, and the heading channels are 0)."""
    return control.headings != "any" and control.frame == "world"


def env_wave(env: Any, head: str, start: HandSetWave) -> dict[str, Any] | None:
    if head != "wave":
        return None
    wave = dict(pos_channels=tuple(env.channels.index(c) for c in ("rel_x", "rel_y", "rel_z")),
                material_channel=env.channels.index("material"), phases=tuple(env.material_phases),
                residual=bool(env.control.residual), k=float(start.k), amplitude=float(start.amplitude),
                **({"gain": float(start.gain)} if start.gain != 1.0 else {}))
    if wave_follows_heading(env.control):
        wave["heading_channels"] = (env.channels.index("heading_cos"), env.channels.index("heading_sin"))
    return wave


def _wave_vector(k: torch.Tensor, obs: torch.Tensor, filled: torch.Tensor, wave: dict[str, Any]) -> torch.Tensor:
    """The body's wave vector ``[N, 3]`` in the world's frame from ``k [N, 3]`` in the heading's frame (x along
    the heading; the identity without ``heading_channels``): turned about z by the heading the observation carries
    (every filled cell holds its cos and sin; their mean over the body). A body's learnt wave then follows any
    heading, and the untrained wave travels along it — the direction in which the hand-set wave moves bodies of
    every kind (``docs/control.md``, "Steering")."""
    if "heading_channels" not in wave:
        return k
    count = filled.sum((1, 2, 3, 4)).clamp_min(1.0)
    c, s = ((obs[:, i] * filled[:, 0]).sum((1, 2, 3)) / count for i in wave["heading_channels"])
    return torch.stack([c * k[:, 0] - s * k[:, 1], s * k[:, 0] + c * k[:, 1], k[:, 2]], 1)


def _wave_strokes(out: torch.Tensor, k: torch.Tensor, obs: torch.Tensor, wave: dict[str, Any],
                  phases: torch.Tensor) -> torch.Tensor:
    """A ``wave`` head's strokes ``[N, 2, *box]`` (a, b) from its per-cell outputs ``out [N, 4, *box]`` (amplitude
    change α, phase offset ψ, correction (ca, cb)), the body's wave vector ``k [N, 3]``, ``obs`` and each material
    index's phase ``phases`` (cycles, index 0 empty).

    The stroke env plays a·sin θ + b·cos θ, θ = 2π(t/T + φ) a voxel's own phase (φ its material's), added under
    residual control to its sine sin θ. For the voxel to receive A·sin(2πt/T − δ'), δ' = k·x + ψ (x its
    place relative to the centre of mass), write 2πt/T − δ' = θ − δ, δ = 2πφ + δ': then (1 + a) = A cos δ and
    b = −A sin δ under residual control (1 + a → a without), plus the corrections. A = the hand-set wave's
    amplitude + α (:class:`HandSetWave`)."""
    index = torch.round(obs[:, wave["material_channel"]] * (len(phases) - 1)).long().clamp(0, len(phases) - 1)
    place = (k[:, :, None, None, None] * obs[:, list(wave["pos_channels"])]).sum(1)
    delta = 2 * math.pi * phases[index] + place + out[:, 1]
    amplitude = wave["amplitude"] + out[:, 0]
    a = amplitude * torch.cos(delta) - (1.0 if wave["residual"] else 0.0) + out[:, 2]
    b = -amplitude * torch.sin(delta) + out[:, 3]
    return torch.stack([a, b], 1)


def _clock_channels(channels: int, head: str, clock_channels: Any) -> tuple[int, int] | None:
    """The observation's (clock_sin, clock_cos) channels, needed by a ``rhythm`` head."""
    if head != "rhythm":
        return None
    if clock_channels is None or len(clock_channels) != 2:
        raise ValueError(f"a rhythm head needs clock_channels = (clock_sin, clock_cos) channel indices, got "
                         f"{clock_channels!r}")
    check_control_input(channels, (1, 1, 1), clock_sin=int(clock_channels[0]), clock_cos=int(clock_channels[1]))
    return int(clock_channels[0]), int(clock_channels[1])


def _env_clock(env: Any, head: str) -> tuple[int, int] | None:
    return (env.channels.index("clock_sin"), env.channels.index("clock_cos")) if head == "rhythm" else None


def _rhythm(out: torch.Tensor, clock: torch.Tensor) -> torch.Tensor:
    """``out [..., 3, *cells]`` (u, v, w) and ``clock [..., 2, *cells]`` (sin, cos) → u·sin + v·cos + w."""
    return out[:, 0] * clock[:, 0] + out[:, 1] * clock[:, 1] + out[:, 2]


def body_controller_setup(net: nn.Module, inputs: ControlInputs, head: str, log_std: float, wave: Any = None,
                          **sizes: int) -> int:
    """What the body controllers (context, context_gru, attention) share at construction: the input checks (``sizes``: positive ints), the box,
    channels and head, ``init_kwargs``, the masked distribution (two entries a cell for strokes), a wave head's
    body-wide wave vector (``net.wave_k``: Linear(2h→3) of the pooled features, starting near 0, added to the
    wave's initial k along x, ``net.wave_k0``) and the materials' phases (``net.wave_phases``; both buffers, out of
    the state dict, made once so that a forward pass copies nothing to the device: a CUDA graph can capture it).
    Returns the actor head's outputs per cell."""
    channels, mask_channel, filled_channel = inputs.channels, inputs.mask_channel, inputs.filled_channel
    box = check_control_input(channels, inputs.box, mask_channel=mask_channel, filled_channel=filled_channel)
    for name, value in sizes.items():
        if not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    outputs, net.clock = _head_outputs(head), _clock_channels(channels, head, inputs.clock_channels)
    net.wave = _wave_setup(channels, head, wave)
    net.init_kwargs = dict(channels=channels, box=box, mask_channel=mask_channel, filled_channel=filled_channel,
                           **sizes, log_std=log_std, head=head, clock_channels=net.clock)
    if net.wave is not None:  # (absent otherwise: the files of the other heads stay as they were)
        net.init_kwargs["wave"] = wave_at_gain(net.wave, net.wave["gain"])
        net.wave_k = nn.Linear(2 * sizes["hidden"], 3)
        nn.init.normal_(net.wave_k.weight, std=0.01)
        nn.init.zeros_(net.wave_k.bias)
        net.register_buffer("wave_k0", torch.tensor([net.wave["k"], 0.0, 0.0]), persistent=False)
        net.register_buffer("wave_phases", torch.tensor(net.wave["phases"]), persistent=False)
    net.box, net.mask_channel, net.filled_channel, net.head = box, mask_channel, filled_channel, head
    net.distribution = MaskedDiagGaussian(math.prod(box) * (2 if head in STROKE_HEADS else 1))
    return outputs


def cell_means(net: nn.Module, out: torch.Tensor, obs: torch.Tensor, filled: torch.Tensor, pooled: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """The actor head's per-cell outputs ``out [N, outputs, *box]`` on observations ``obs [N, C, *box]`` →
    (mean, mask) ``[N, A]``: a rhythm head played on the observation's clock, a wave head's strokes with the body's
    wave vector from ``pooled`` (the body's features, ``[N, 2h]``); zero outside the body."""
    if net.clock is not None:
        out = _rhythm(out, obs[:, list(net.clock)])[:, None]
    if net.wave is not None:
        k = _wave_vector(net.wave_k(pooled) + net.wave_k0, obs, filled, net.wave)
        strokes = _wave_strokes(out, k, obs, net.wave, net.wave_phases)
        if net.wave["gain"] != 1.0:  # (the hand-set wave's strokes, then gain × the head's change to them)
            still = _wave_vector(net.wave_k0.expand(len(obs), 3), obs, filled, net.wave)
            hand = _wave_strokes(torch.zeros_like(out), still, obs, net.wave, net.wave_phases)
            strokes = hand + net.wave["gain"] * (strokes - hand)
        out = strokes
    return _per_cell_mean((out * filled).flatten(2), obs[:, net.mask_channel].flatten(1), net.head)
