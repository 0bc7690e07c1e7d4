"""The voxel-token controllers: attention over a body's filled cells (:class:`VoxelAttentionController`, kind
``attention``), the same with a memory of the episode (:class:`RecurrentAttentionController`, ``attention_gru``) and
with an actor that each body writes (:class:`HyperAttentionController`, ``attention_hyper``).
Registered by kind in :data:`freeform.agents.networks.controllers.CONTROLLERS`, which documents what every controller reads
and returns; the actor heads they share are :mod:`freeform.agents.networks.controller_heads`'.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import torch
import torch.nn as nn
import torch.nn.functional as F

from freeform.agents.networks.controller_heads import (
    DEFAULT_WAVE,
    ControlInputs,
    FromInputs,
    HandSetWave,
    body_controller_setup,
    cell_means,
    env_wave,
)
from freeform.agents.networks.recurrent import run_rnn


class _AttentionBlock(nn.Module):
    """A pre-norm transformer block over tokens ``[N, K, h]`` with a key mask ``valid [N, K]`` (True: a token):
    x + MultiHeadAttention(LN(x)), then + MLP(LN(x)) (h → 2h → h, ReLU). Masked keys get no weight, so a valid
    token's output does not depend on how many padding tokens follow."""

    written_out = False
    """Attention as matmuls and a softmax instead of the fused kernel (``VoxelAttentionController.fixed_shapes``)."""

    def __init__(self, width: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.norm1, self.norm2 = nn.LayerNorm(width), nn.LayerNorm(width)
        self.qkv = nn.Linear(width, 3 * width)
        self.out = nn.Linear(width, width)
        self.mlp = nn.Sequential(nn.Linear(width, 2 * width), nn.ReLU(), nn.Linear(2 * width, width))

    def forward(self, x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        n, k, h = x.shape
        q, key, v = self.qkv(self.norm1(x)).view(n, k, 3, self.heads, h // self.heads).permute(2, 0, 3, 1, 4)
        if self.written_out:  # (under torch.func.vmap — a TeacherBank —, which has no CPU batching rule for SDPA)
            scores = (q @ key.transpose(-1, -2)) / math.sqrt(h // self.heads)  # [N, heads, K, K]
            scores = scores.masked_fill(~valid[:, None, None, :], torch.finfo(scores.dtype).min)
            attended = scores.softmax(-1) @ v  # [N, heads, K, h/heads]
        else:
            attended = F.scaled_dot_product_attention(q, key, v, attn_mask=valid[:, None, None, :])
        x = x + self.out(attended.transpose(1, 2).reshape(n, k, h))
        return x + self.mlp(self.norm2(x))


def token_cells(obs: torch.Tensor, order: torch.Tensor) -> torch.Tensor:
    """The observation ``[N, C, Bx, By, Bz]`` at the tokens' cells ``order [N, K]`` (indices into the box, C
    order): ``[N, K, C]``."""
    cells = obs.flatten(2).transpose(1, 2)  # [N, A, C]
    return cells.gather(1, order[..., None].expand(-1, -1, cells.shape[2]))


class VoxelAttentionController(FromInputs, nn.Module):
    """Attention over a body's voxels: every filled cell is a token, every token attends to every other, and the
    padding (empty cells, a larger box) is no token at all.

    Observations ``[N, C, Bx, By, Bz]``. Tokens: each body's filled cells (channel ``filled_channel``), gathered in
    C order into ``[N, K, C]``, K = the batch's largest voxel count, the rest masked (``valid [N, K]``); a token's
    features are its cell's observation, whose ``rel_x/y/z`` channels place it relative to the centre of mass (its
    position: the network has no other). Embedding: Linear(C→h) → ReLU → Linear(h→h); ``layers`` pre-norm
    transformer blocks of ``heads`` heads (:class:`_AttentionBlock`); LayerNorm. Actor: Linear(h→1) per token (weights
    N(0, 0.01²), bias 0; ``head="rhythm"``: Linear(h→3), the token's rhythm, ``controller_heads.HEADS``), scattered back to its
    cell (0 elsewhere); one learned log σ. Critic: the mean of the valid
    tokens → Linear(h→h) → tanh → Linear(h→1). Gathering and scattering are tensor ops (no loop over bodies).
    ``head="wave"``: Linear(h→4) per token (amplitude change, phase offset, correction) and the body's wave vector
    from its tokens' mean and max (Linear(2h→3)), played as ``controller_heads``' travelling-wave strokes.
    """

    fits_any_box = True
    padding_invariant = True
    token_count: int | None = None
    """Tokens per body when set (:meth:`fixed_shapes`); otherwise the batch's largest voxel count."""
    hidden_cells: torch.Tensor | None = None
    """Cells ``[N, Bx·By·Bz]`` (bool) hidden from the body's other voxels when set (:meth:`hiding`)."""

    def __init__(self, inputs: ControlInputs, hidden: int = 32, heads: int = 4, layers: int = 2, log_std: float = 0.0,
                 head: str = "direct", wave: dict[str, Any] | None = None) -> None:
        super().__init__()
        if isinstance(hidden, int) and isinstance(heads, int) and hidden > 0 and heads > 0 and hidden % heads:
            raise ValueError(f"hidden ({hidden}) must be a multiple of heads ({heads})")
        outputs = body_controller_setup(self, inputs, head, log_std, wave, hidden=hidden, heads=heads, layers=layers)
        self.embed = nn.Sequential(nn.Linear(inputs.channels, hidden), nn.ReLU(), nn.Linear(hidden, hidden))
        self.blocks = nn.ModuleList(_AttentionBlock(hidden, heads) for _ in range(layers))
        self.norm = nn.LayerNorm(hidden)
        self.actor = nn.Linear(hidden, outputs)
        nn.init.normal_(self.actor.weight, std=0.01)  # the untrained controller commands ≈ 0 (or plays its wave)
        nn.init.zeros_(self.actor.bias)
        self.log_std = nn.Parameter(torch.tensor(float(log_std)))
        self.critic_fc = nn.Linear(hidden, hidden)
        self.critic_out = nn.Linear(hidden, 1)

    @classmethod
    def for_env(cls, env: Any, hidden: int = 32, log_std: float = 0.0, head: str = "direct",
                wave: HandSetWave = DEFAULT_WAVE) -> VoxelAttentionController:
        """The controller for a ``ControlEnv`` (its box, channels, mask and filled channels; a wave head's
        description of the observation and its hand-set wave)."""
        return cls(ControlInputs.of(env, head), hidden, log_std=log_std, head=head, wave=env_wave(env, head, wave))

    def tokens(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``[N, C, Bx, By, Bz]`` → the filled cells' features ``[N, K, C]``, their cells in the box ``[N, K]``
        (a padding token's is an empty cell, each cell at most once) and ``valid [N, K]``."""
        filled = obs[:, self.filled_channel].flatten(1) > 0.5  # [N, A]
        count = filled.sum(1)
        k = self.token_count or max(int(count.max()), 1)
        order = torch.argsort((~filled).to(torch.int32), dim=1, stable=True)[:, :k]  # the filled cells first, in C order
        valid = torch.arange(k, device=obs.device)[None] < count[:, None]
        return token_cells(obs, order), order, valid

    @contextmanager
    def fixed_shapes(self, obs: torch.Tensor) -> Iterator[None]:
        """Inside, every forward pads its bodies to the largest voxel count in ``obs [N, C, Bx, By, Bz]``, so that
        its shapes do not depend on the data it is given, and the attention is written out: what ``torch.func.vmap``
        needs to run it over a ``TeacherBank``'s blocks (the padding changes nothing: ``padding_invariant``). Every
        forward inside must be of bodies from ``obs`` (a larger body would lose voxels). Nests; restored on exit."""
        filled = obs[:, self.filled_channel].flatten(1) > 0.5
        before = self.token_count, [block.written_out for block in self.blocks]
        self.token_count = max(int(filled.sum(1).max()), 1) if len(obs) else 1
        for block in self.blocks:
            block.written_out = True
        try:
            yield
        finally:
            self.token_count = before[0]
            for block, was in zip(self.blocks, before[1], strict=True):
                block.written_out = was

    @contextmanager
    def hiding(self, cells: torch.Tensor) -> Iterator[None]:
        """Inside, every forward of ``N`` bodies hides the voxels at ``cells [N, Bx·By·Bz]`` (bool) from the rest of
        their body: a hidden voxel's token is no key of the attention and no part of the body's pooled summary (the
        wave vector's features, a hypernetwork's body code, the critic's input), yet it still reads the voxels it
        sees and commands its own cell (its place, ``rel_x/y/z``, is still from the whole body's centre of mass, and
        the heading every cell carries is read from all of them). A body whose voxels are all hidden is seen whole.
        Distillation's token dropout (``algo.token_dropout``): the student learns a body's gait from parts of it.
        Restored on exit."""
        before, self.hidden_cells = self.hidden_cells, cells
        try:
            yield
        finally:
            self.hidden_cells = before

    def seen(self, order: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """The tokens the others see, ``[N, K]``: ``valid`` less those :meth:`hiding` hides (all of a body's
        valid tokens where it would hide every one)."""
        if self.hidden_cells is None:
            return valid
        seen = valid & ~self.hidden_cells.gather(1, order)
        return torch.where(seen.any(1, keepdim=True), seen, valid)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``[N, C, Bx, By, Bz]`` → (mean, log_std, mask ``[N, Bx·By·Bz]``, value ``[N]``)."""
        features, order, valid = self.tokens(obs)
        seen = self.seen(order, valid)
        x = self.embed(features)
        for block in self.blocks:
            x = block(x, seen)
        return self._readout(obs, x, order, valid, seen)

    def token_actions(self, x: torch.Tensor, valid: torch.Tensor, obs: torch.Tensor, order: torch.Tensor
                      ) -> torch.Tensor:
        """The actor's outputs per token ``[N, outputs, K]`` (0 on padding) from the normed tokens ``x [N, K, h]``
        (this actor, one for every body, reads nothing else of the observation ``obs`` or the tokens' cells
        ``order``)."""
        return self.actor(x).transpose(1, 2) * valid[:, None]

    def _readout(self, obs: torch.Tensor, x: torch.Tensor, order: torch.Tensor, valid: torch.Tensor,
                 seen: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:
        """The tokens after the blocks ``x [N, K, h]`` → (mean, log_std, mask, value), as :meth:`forward`; the
        body's summaries pool the ``seen`` tokens (default: every valid one)."""
        n, seen = obs.shape[0], valid if seen is None else seen
        x = self.norm(x) * valid[..., None]
        pooled = (x * seen[..., None]).sum(1) / seen.sum(1, keepdim=True).clamp_min(1)
        per_token = self.token_actions(x, valid, obs, order)  # [N, outputs, K]
        cells = per_token.new_zeros(n, per_token.shape[1], math.prod(obs.shape[2:]))
        cells = cells.scatter(2, order[:, None].expand(-1, per_token.shape[1], -1), per_token)
        body = pooled  # (a wave head's: the tokens' mean and max, as the context controllers pool their cells)
        if self.wave is not None:
            body = torch.cat([pooled, x.masked_fill(~seen[..., None], float("-inf")).amax(1).nan_to_num(neginf=0.0)], 1)
        filled = obs[:, self.filled_channel: self.filled_channel + 1]
        mean, mask = cell_means(self, cells.view(n, -1, *obs.shape[2:]), obs, filled, body)
        value = self.critic_out(torch.tanh(self.critic_fc(pooled))).squeeze(-1)
        return mean, self.log_std.expand_as(mean), mask, value


class HyperAttentionController(VoxelAttentionController):
    """:class:`VoxelAttentionController` whose actor each body writes from what it is: a morphology-conditioned
    hypernetwork (HyperDistill, Xiong et al. 2024), the student kind issue 56 names beside the transformer.

    The body's code: each token's body channels — the first ``body_channels`` of the observation, the control env's
    ``filled, material, actuated, rel_x, rel_y, rel_z`` (its voxel, material, muscle and place relative to the centre
    of mass; no velocity, strain, contact, heading, clock or open-loop channel) — embedded (Linear(b → h) → ReLU →
    Linear(h → h)) and averaged over the body's tokens (:meth:`body_code`, ``[N, h]``). From it ``generator``
    (Linear(h → (h+1)·outputs)) writes a matrix ``W [N, h, outputs]`` and a bias, and a token's outputs are the shared
    actor's plus ``x_token · W + b``: the same token features read through a head of the body's own, set by its
    shape and materials rather than by the moment's state (the places move a little as the body deforms).

    The generator starts at 0, so the untrained controller is the attention controller it holds, and one started
    from a trained ``attention`` controller (``control.controller_init``, :attr:`grows_from`) gives its commands
    exactly until training moves the generator. Padding changes nothing, as there (the code is a mean over the
    body's tokens)."""

    grows_from = "attention"
    grown_prefixes = ("body_embed.", "generator.")
    """The weights this kind adds to :attr:`grows_from`'s, silent at the start."""

    def __init__(self, inputs: ControlInputs, hidden: int = 32, heads: int = 4, layers: int = 2, log_std: float = 0.0,
                 head: str = "direct", wave: dict[str, Any] | None = None, body_channels: int = 6) -> None:
        super().__init__(inputs, hidden, heads, layers, log_std, head, wave)
        if not (isinstance(body_channels, int) and 1 <= body_channels <= inputs.channels):
            raise ValueError(f"body_channels must be an int in 1 … {inputs.channels} (the observation's channels), "
                             f"got {body_channels!r}")
        self.init_kwargs["body_channels"] = self.body_channels = body_channels
        self.body_embed = nn.Sequential(nn.Linear(body_channels, hidden), nn.ReLU(), nn.Linear(hidden, hidden))
        self.generator = nn.Linear(hidden, (hidden + 1) * self.actor.out_features)
        nn.init.zeros_(self.generator.weight)
        nn.init.zeros_(self.generator.bias)

    def body_code(self, obs: torch.Tensor, order: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """``[N, h]``: the mean over each body's tokens (cells ``order [N, K]``, ``valid``) of its body channels'
        embedding."""
        embedded = self.body_embed(token_cells(obs[:, : self.body_channels], order)) * valid[..., None]
        return embedded.sum(1) / valid.sum(1, keepdim=True).clamp_min(1)

    def token_actions(self, x: torch.Tensor, valid: torch.Tensor, obs: torch.Tensor, order: torch.Tensor
                      ) -> torch.Tensor:
        """The shared actor's outputs plus the body's own head's, ``[N, outputs, K]`` (0 on padding)."""
        written = self.generator(self.body_code(obs, order, self.seen(order, valid))).view(len(x), -1,
                                                                                           self.actor.out_features)
        own = torch.einsum("nkh,nho->nok", x, written[:, :-1]) + written[:, -1, :, None]  # (written: [N, h+1, out])
        return super().token_actions(x, valid, obs, order) + own * valid[:, None]


class RecurrentAttentionController(VoxelAttentionController):
    """:class:`VoxelAttentionController` with a memory of how this body has moved: a GRU over the body's tokens
    after the first block, step after step of the episode, recalled into every token before the other blocks — so
    that a controller meeting a body it never saw can read, from the body's answers to its last commands, what its
    voxels alone do not say (the implicit system identification of :class:`RecurrentContextController`).

    A recurrent policy (``freeform.agents.networks.recurrent``): observations ``[T, N, C, Bx, By, Bz]``, the state ``(m [N,
    1, M],)`` (zeros at an episode's start; the critic reads the tokens it shaped), ``episode_start [T, N]``::

        x = block_1(embed(tokens))                       (all T·N observations at once)
        m_t = GRU(mean over the body's tokens of x, m_{t−1})     (M wide: ``memory``)
        x = blocks_2..L(x + Linear(M→h)(m_t))            (the recall)

    then the attention controller's norm, actor, wave head and critic. The recall starts at zero, so the untrained
    memory changes nothing: started from a feed-forward ``attention`` controller of the same sizes
    (``control.controller_init``, :attr:`grows_from`) it gives that controller's commands exactly, and training
    (distillation over sequences) learns what memory adds to it. Padding changes nothing, as there.
    """

    actor_state_size = 1
    grows_from = "attention"
    """The feed-forward kind whose weights this one starts from: all but :attr:`grown_prefixes`'."""
    grown_prefixes = ("gru.", "recall.")

    def __init__(self, inputs: ControlInputs, hidden: int = 32, heads: int = 4, layers: int = 2, log_std: float = 0.0,
                 head: str = "direct", wave: dict[str, Any] | None = None, memory: int = 32) -> None:
        super().__init__(inputs, hidden, heads, layers, log_std, head, wave)
        if not (isinstance(memory, int) and memory >= 1) or layers < 2:
            raise ValueError(f"memory must be a positive int and layers >= 2 (the recall enters between blocks), "
                             f"got memory={memory!r}, layers={layers!r}")
        self.init_kwargs["memory"] = self.memory = memory
        self.gru = nn.GRU(hidden, memory)
        self.recall = nn.Linear(memory, hidden)
        nn.init.zeros_(self.recall.weight)
        nn.init.zeros_(self.recall.bias)

    def initial_state(self, num_envs: int) -> tuple[torch.Tensor, ...]:
        """``(zeros [N, 1, memory],)``: the GRU's state at an episode's start."""
        return (self.log_std.new_zeros(num_envs, 1, self.memory),)

    def _steps(self, obs: torch.Tensor, state: tuple[torch.Tensor, ...], episode_start: torch.Tensor
               ) -> tuple[tuple[torch.Tensor, ...], tuple[torch.Tensor, ...]]:
        """→ ((mean, log σ, mask ``[T, N, A]``, value ``[T, N]``), the state after the last step)."""
        steps, n = obs.shape[:2]
        o = obs.flatten(0, 1)
        features, order, valid = self.tokens(o)
        x = self.blocks[0](self.embed(features), valid)
        pooled = (x * valid[..., None]).sum(1) / valid.sum(1, keepdim=True).clamp_min(1)
        m, state = run_rnn(self.gru, pooled.view(steps, n, -1), state, episode_start)
        x = x + self.recall(m.flatten(0, 1))[:, None]
        for block in self.blocks[1:]:
            x = block(x, valid)
        out = self._readout(o, x, order, valid)
        return tuple(t.view(steps, n, *t.shape[1:]) for t in out), state

    def action_params(self, obs: torch.Tensor, actor_state: tuple[torch.Tensor, ...], episode_start: torch.Tensor
                      ) -> tuple[tuple[torch.Tensor, ...], tuple[torch.Tensor, ...]]:
        """The actor alone: ``obs [T, N, C, Bx, By, Bz]`` → ((mean, log σ, mask) ``[T, N, A]`` each, state)."""
        (*params, _), state = self._steps(obs, actor_state, episode_start)
        return tuple(params), state

    def forward(self, obs: torch.Tensor, state: tuple[torch.Tensor, ...], episode_start: torch.Tensor
                ) -> tuple[Any, ...]:
        """``obs [T, N, C, Bx, By, Bz]``, ``state``, ``episode_start [T, N]`` → (mean, log σ, mask ``[T, N, A]``,
        value ``[T, N]``, state)."""
        out, state = self._steps(obs, state, episode_start)
        return (*out, state)


__all__ = ["HyperAttentionController", "RecurrentAttentionController", "VoxelAttentionController"]
