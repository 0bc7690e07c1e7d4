"""Data-parallel PPO over ``torch.distributed``: one run across R processes, with the result of one process.

The model (``docs/scaling.md``): the global batch of N environments is cut into R contiguous slices, rank r holding
environments ``[lo_r, hi_r)`` (:func:`env_slice`: sizes differ by at most one). Each rank designs and scores its
slice on its own device; what the update needs from the other slices is exchanged with a few collectives:

- **Sampling noise** is drawn for the *global* batch ``[N, A]`` from PPO's generator on every rank (same seed, same
  draws) and each rank keeps its rows, so environment n gets the same action whatever R is; every rank's
  generator stays in the state a single process's would be in (checkpoints do not depend on R).
- **Minibatches** are the single process's: one global permutation of the ``T·N`` samples per pass, cut into
  minibatches of ``sgd_minibatch_size`` M (the tail dropped). Each rank computes the samples of a minibatch that
  it holds (:meth:`DataParallel.local_indices`: about M·n_r/N of them, a random number) and divides its loss
  *sums* by M; the gradients, summed over ranks as one flat buffer (PPO's ``FlatParameters.grad``,
  :meth:`DataParallel.all_reduce_grad_`), are
  then the gradient of the global minibatch's mean loss. M never needs to divide by R; a rank holding none of a
  minibatch contributes zeros.
- **Statistics over the global batch**: advantages, returns, values and σ are all-gathered once per epoch (a few
  floats per sample) so standardisation, explained variance and the logged means are the single process's
  formulas on the same numbers; the loss/KL sums are all-reduced once per epoch, so the adaptive-KL rule sees the
  same mean KL — and sets the same β — on every rank.

With the same seed, R ranks and one process therefore differ only by floating-point summation order.

State (checkpoints) is kept global: :meth:`Collectives.gather_state` concatenates the per-environment tensors over
ranks and :meth:`Collectives.shard_state` slices them back, so a checkpoint written with R ranks resumes with any
other R. Per-environment state is named: the tensors under a ``per_env`` key (:data:`PER_ENV`), nothing else —
never guessed from a shape. Every tensor of an env's ``info`` is per environment (the ``VecEnv`` protocol).

All of this sits behind one object, :class:`Collectives`: its single-process version (``Collectives.single``) is
the identity, :class:`DataParallel` the process-group version, :func:`collectives` picks one. PPO calls its
methods unconditionally and so reads as the single-process algorithm.

:func:`init_from_env` creates the process group from ``torchrun``'s (or a SLURM job's) environment variables.
"""

from __future__ import annotations

import atexit
import datetime
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.distributed as dist
import torch.nn as nn


def env_slice(num_envs: int, world_size: int, rank: int) -> tuple[int, int]:
    """The environments ``[lo, hi)`` of ``rank`` among ``world_size`` ranks: contiguous slices in rank order whose
    sizes differ by at most one (the first ``num_envs % world_size`` ranks hold one more)."""
    if not (isinstance(world_size, int) and world_size >= 1):
        raise ValueError(f"world_size must be an int >= 1, got {world_size!r}")
    if not (isinstance(rank, int) and 0 <= rank < world_size):
        raise ValueError(f"rank must be an int in [0, {world_size}), got {rank!r}")
    if not (isinstance(num_envs, int) and num_envs >= world_size):
        raise ValueError(f"num_envs must be an int >= world_size ({world_size}), got {num_envs!r}: every rank needs an env")
    base, extra = divmod(num_envs, world_size)
    lo = rank * base + min(rank, extra)
    return lo, lo + base + (1 if rank < extra else 0)


def is_distributed() -> bool:
    """True when a default process group with more than one rank exists (the data-parallel path is on)."""
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def rank() -> int:
    """This process's global rank (0 without a process group)."""
    return dist.get_rank() if dist.is_available() and dist.is_initialized() else 0


def world_size() -> int:
    """Number of ranks (1 without a process group)."""
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def is_main_process() -> bool:
    """Rank 0, the only one that writes logs, records and checkpoints."""
    return rank() == 0


def launch_rank() -> int:
    """This process's rank as the launcher's environment states it, before any process group exists: ``RANK``
    (torchrun), else ``SLURM_PROCID`` in a SLURM step of several tasks, else 0."""
    if "RANK" in os.environ:
        return int(os.environ["RANK"])
    if int(os.environ.get("SLURM_NTASKS", "1")) > 1:
        return int(os.environ.get("SLURM_PROCID", "0"))
    return 0


def launch_env() -> dict[str, int] | None:
    """``RANK``/``WORLD_SIZE``/``LOCAL_RANK``/``LOCAL_WORLD_SIZE`` as ``torchrun`` sets them; None when this process
    was not launched as one of several (no ``WORLD_SIZE`` or ``WORLD_SIZE=1``)."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return None
    size = int(os.environ["WORLD_SIZE"])
    return {
        "rank": int(os.environ.get("RANK", "0")),
        "world_size": size,
        "local_rank": int(os.environ.get("LOCAL_RANK", "0")),
        "local_world_size": int(os.environ.get("LOCAL_WORLD_SIZE", str(size))),
    }


def export_slurm_env() -> bool:
    """In a SLURM job step of several tasks (e.g. ``hydra.launcher.tasks_per_node=4`` of the submitit launcher)
    without ``torchrun``'s variables: export ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``LOCAL_WORLD_SIZE``,
    ``MASTER_ADDR``, ``MASTER_PORT`` from SLURM's through ``submitit.helpers.TorchDistributedEnvironment``.
    Returns whether it did."""
    if "WORLD_SIZE" in os.environ or int(os.environ.get("SLURM_NTASKS", "1")) <= 1:
        return False
    try:
        from submitit.helpers import TorchDistributedEnvironment
    except ImportError as exc:  # pragma: no cover - the cluster extra is what brings submitit
        raise ValueError("a multi-task SLURM job needs submitit: pip install 'freeform[cluster]'") from exc
    TorchDistributedEnvironment().export(set_cuda_visible_devices=False)
    return True


def pin_local_gpu() -> None:
    """Make this rank see only GPU ``LOCAL_RANK`` (as ``cuda:0``), before anything initialises CUDA.

    Both torch and the Taichi simulator then run on the rank's own GPU (Taichi has no device index of its own: it
    takes the first visible device). A ``CUDA_VISIBLE_DEVICES`` list that the launcher set is indexed by the local
    rank; a single visible device (e.g. SLURM's ``--gpus-per-task=1``) is left alone.
    """
    launched = launch_env()
    if launched is None or launched["local_world_size"] <= 1:
        return
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        devices = [d for d in visible.split(",") if d.strip()]
        if len(devices) <= 1:
            return
        if launched["local_rank"] < len(devices):
            os.environ["CUDA_VISIBLE_DEVICES"] = devices[launched["local_rank"]]
        return
    os.environ["CUDA_VISIBLE_DEVICES"] = str(launched["local_rank"])


def backend() -> str:
    """``gloo`` for CPU tensors, and ``nccl`` for CUDA tensors when this torch has NCCL (one group serves both)."""
    if torch.cuda.is_available() and dist.is_nccl_available():
        return "cpu:gloo,cuda:nccl"
    return "gloo"


def init_from_env(timeout_s: float = 1800.0) -> bool:
    """Create the default process group from the launcher's environment (``torchrun``; a multi-task SLURM step)
    unless one exists. Returns True when this process is one of several ranks."""
    if dist.is_initialized():
        return is_distributed()
    export_slurm_env()
    if launch_env() is None:
        return False
    pin_local_gpu()
    dist.init_process_group(backend=backend(), timeout=datetime.timedelta(seconds=timeout_s))
    atexit.register(_destroy)
    return is_distributed()


def _destroy() -> None:
    if dist.is_initialized():
        dist.destroy_process_group()


def shutdown() -> None:
    """End a run's process group cleanly: wait until every rank is done with it, then destroy it (a rank that tears
    its backend down while another still talks to it can abort)."""
    if dist.is_available() and dist.is_initialized():
        if dist.get_world_size() > 1:
            dist.barrier()
        dist.destroy_process_group()


def broadcast_object(obj: Any, src: int = 0) -> Any:
    """``obj`` of rank ``src`` on every rank (identity without a process group)."""
    if not is_distributed():
        return obj
    box = [obj]
    dist.broadcast_object_list(box, src=src)
    return box[0]


# ---------------------------------------------------------------------------------------------------------------
# The collectives PPO and the trainer use: the identity in one process, torch.distributed across ranks.
# ---------------------------------------------------------------------------------------------------------------

PER_ENV = "per_env"
"""Key of the per-environment part of a state mapping: every tensor below it is ``[num_envs, ...]`` (local on a
rank, global in a checkpoint). Per-environment state is *named*: a tensor elsewhere is never split or stacked over
ranks, whatever its shape (policy weights and Adam moments can share their first dimension with the env count)."""


def _wire(x: torch.Tensor) -> torch.Tensor:
    """What goes through a collective: bool as uint8 (not every backend reduces or gathers bool)."""
    return x.to(torch.uint8) if x.dtype == torch.bool else x


def _map_per_env(obj: Any, fn: Callable[[torch.Tensor, str], torch.Tensor], path: str = "", inside: bool = False) -> Any:
    """``obj`` with ``fn(tensor, path)`` applied to every tensor under a :data:`PER_ENV` key (at any depth)."""
    if isinstance(obj, torch.Tensor):
        return fn(obj, path) if inside else obj
    if isinstance(obj, Mapping):
        return {k: _map_per_env(v, fn, f"{path}.{k}" if path else str(k), inside or k == PER_ENV) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        items = [_map_per_env(v, fn, f"{path}[{i}]", inside) for i, v in enumerate(obj)]
        return items if isinstance(obj, list) else tuple(items)
    return obj


@dataclass
class Collectives:
    """Every collective PPO and the trainer need, for a process holding environments ``[lo, hi)`` of ``num_envs``.

    This class is the single-process version: ``Collectives.single(n)`` holds all ``n`` environments and every
    method is the identity (or the plain single-process formula), so the algorithm reads as one process.
    :class:`DataParallel` implements the same methods over a ``torch.distributed`` process group; build the right
    one with :func:`collectives`. ``counts[r]`` is rank r's environment count; slices are contiguous in rank order.
    """

    rank: int
    world_size: int
    counts: tuple[int, ...]

    @classmethod
    def single(cls, num_envs: int) -> Collectives:
        return cls(rank=0, world_size=1, counts=(num_envs,))

    @property
    def num_envs(self) -> int:
        """N, environments over all ranks."""
        return sum(self.counts)

    @property
    def lo(self) -> int:
        return sum(self.counts[: self.rank])

    @property
    def hi(self) -> int:
        return self.lo + self.counts[self.rank]

    @property
    def local_envs(self) -> int:
        return self.counts[self.rank]

    @property
    def is_writer(self) -> bool:
        """Rank 0: the one process that writes files (checkpoints, logs, records)."""
        return self.rank == 0

    # -- acting ----------------------------------------------------------------------------------------------------

    def env_noise(self, like: torch.Tensor, generator: torch.Generator, kind: str = "normal") -> torch.Tensor:
        """Noise for this process's environments, shaped like ``like [..., n_local, A]`` (one step's ``[n_local, A]``,
        or a rollout's ``[T, n_local, A]``), from ``generator``: N(0, 1) (``kind="normal"``) or U[0, 1)
        (``"uniform"``), as the action distribution's ``noise_kind`` says."""
        return _draw(like.shape, generator, like, kind)

    def broadcast_module_(self, module: nn.Module, src: int = 0) -> None:
        """Give every rank rank ``src``'s parameters and buffers (identical starting weights)."""

    # -- update ----------------------------------------------------------------------------------------------------

    def local_share(self, idx: torch.Tensor, *per_sample: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Global flat sample indices ``idx [M]`` of a minibatch (into ``[T, N]`` flattened, ``g = t·N + n``) and
        tensors aligned with them -> this process's share: ``(local indices into its [T, n_local] rollout, *those
        tensors' matching entries)``, in minibatch order."""
        return (idx, *per_sample)

    def local_sequences(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """A recurrent policy's minibatch: global sequence indices ``idx [M]`` (``s = c·N + n``: env n's chunk c) ->
        ``(local indices c·n_local + n − lo of the ones this process holds, which of idx those are; None: all)``.
        Sequences are split between ranks whole, by their env, never by steps."""
        return idx, None

    def minibatch_mean(self, x: torch.Tensor, size: int) -> torch.Tensor:
        """This process's part of the mean of a per-sample quantity over a global minibatch of ``size`` samples."""
        return x.mean()

    def all_reduce_grad_(self, grad: torch.Tensor) -> None:
        """Sum the (flat, ``FlatParameters.grad``) gradient over ranks in place, after each backward."""

    def sum_(self, x: torch.Tensor) -> torch.Tensor:
        """In-place sum over ranks; returns ``x``."""
        return x

    # -- global views ----------------------------------------------------------------------------------------------

    def gather_envs(self, x: torch.Tensor, dim: int = 0) -> torch.Tensor:
        """Every rank's per-environment tensor concatenated along ``dim`` (``[.., n_r, ..]`` -> ``[.., N, ..]``)."""
        return x

    def gather_varlen(self, x: torch.Tensor) -> torch.Tensor:
        """Every rank's 1-D tensor of any length, concatenated in rank order."""
        return x

    def shard_envs(self, x: torch.Tensor, dim: int = 0) -> torch.Tensor:
        """This rank's slice ``[lo, hi)`` of a global per-environment tensor along ``dim``."""
        if x.shape[dim] != self.num_envs:
            raise ValueError(f"shard_envs: dim {dim} of a {list(x.shape)} tensor is not the global env count {self.num_envs}")
        return x.narrow(dim, self.lo, self.local_envs)

    def gather_state(self, state: Mapping[str, Any]) -> dict[str, Any]:
        """A state mapping with every tensor under a :data:`PER_ENV` key made global (concatenated over ranks);
        all else is rank 0's (the same on every rank). A collective: every rank passes an alike state."""
        return _map_per_env(state, self._gather_named)

    def shard_state(self, state: Mapping[str, Any]) -> dict[str, Any]:
        """Inverse of :meth:`gather_state`: this rank's slice of every tensor under a :data:`PER_ENV` key (each must
        hold the global env count; the error names the key). No communication."""
        return _map_per_env(state, self._shard_named)

    def gather_rollout(self, rollout: Any, episode_infos: list[dict[str, Any]]) -> tuple[dict[str, torch.Tensor], list[dict[str, Any]]]:
        """The global view of an epoch's rollout for records: ``actions [T, N, A]``, ``values``,
        ``episode_returns``, ``dones [T, N]``, and ``episode_infos`` whose tensors (per environment, by the ``VecEnv`` protocol) are
        gathered. Environments must finish in lock-step across ranks (the design env's episodes all end at T)."""
        view = {name: getattr(rollout, name) for name in ("actions", "values", "episode_returns", "dones")}
        return view, episode_infos

    def reduce_stats(self, stats: Mapping[str, float]) -> dict[str, float]:
        """A per-rank figure over all ranks: times (``*seconds*``) by max (ranks run in parallel), else by sum."""
        return dict(stats)

    def _gather_named(self, x: torch.Tensor, key: str) -> torch.Tensor:
        self._check_envs(x, key, self.local_envs, "local")
        return x

    def _shard_named(self, x: torch.Tensor, key: str) -> torch.Tensor:
        self._check_envs(x, key, self.num_envs, "global")
        return x

    @staticmethod
    def _check_envs(x: torch.Tensor, key: str, count: int, which: str) -> None:
        if x.dim() == 0 or x.shape[0] != count:
            raise ValueError(f"per-environment state {key!r} has shape {list(x.shape)}; its first dimension must be "
                             f"the {which} env count {count}")


@dataclass
class DataParallel(Collectives):
    """:class:`Collectives` over the ranks of a ``torch.distributed`` process group (the rules: module docstring).

    Build it with :meth:`from_local` (every rank at once: it all-gathers the local counts).
    """

    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    """Where this rank's collectives run (its PPO device)."""

    @classmethod
    def from_local(cls, local_envs: int, device: torch.device) -> DataParallel:
        """Collective: learn every rank's environment count from the local one."""
        size = dist.get_world_size()
        mine = torch.tensor([local_envs], dtype=torch.int64, device=device)
        counts = [torch.zeros_like(mine) for _ in range(size)]
        dist.all_gather(counts, mine)
        return cls(rank=dist.get_rank(), world_size=size, counts=tuple(int(c.item()) for c in counts), device=device)

    def env_noise(self, like: torch.Tensor, generator: torch.Generator, kind: str = "normal") -> torch.Tensor:
        """The global batch's noise ``[..., N, A]`` drawn on every rank, this rank's envs kept: env n gets the same draw
        whatever the rank count, and every rank's generator stays where a single process's would be."""
        if like.dim() < 2 or like.shape[-2] != self.local_envs:
            raise ValueError(f"in a data-parallel run, the noise's envs (dimension -2) must be this rank's "
                             f"{self.local_envs}, got shape {list(like.shape)}")
        shape = (*like.shape[:-2], self.num_envs, like.shape[-1])
        return _draw(shape, generator, like, kind)[..., self.lo : self.hi, :]

    def broadcast_module_(self, module: nn.Module, src: int = 0) -> None:
        with torch.no_grad():
            for tensor in list(module.parameters()) + list(module.buffers()):
                dist.broadcast(tensor.data, src=src)

    def local_indices(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Global flat sample indices ``idx [M]`` -> ``(mask [M] bool, local [m])``: which of them this rank holds,
        and their flat indices into its ``[T, n_r]`` rollout (in the minibatch's order)."""
        n = self.num_envs
        t, env = idx // n, idx % n
        mask = (env >= self.lo) & (env < self.hi)
        return mask, t[mask] * self.local_envs + (env[mask] - self.lo)

    def local_share(self, idx: torch.Tensor, *per_sample: torch.Tensor) -> tuple[torch.Tensor, ...]:
        mask, local = self.local_indices(idx)
        return (local, *(x[mask] for x in per_sample))

    def local_sequences(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        env, chunk = idx % self.num_envs, idx // self.num_envs
        mine = (env >= self.lo) & (env < self.hi)
        return chunk[mine] * self.local_envs + (env[mine] - self.lo), mine

    def minibatch_mean(self, x: torch.Tensor, size: int) -> torch.Tensor:
        # A rank's share of the global minibatch mean: the sum over its samples / the global minibatch size. Summed
        # over ranks (the gradient by all_reduce_grad_, the logged sums by sum_) it is the global mean.
        return x.sum() / size

    def all_reduce_grad_(self, grad: torch.Tensor) -> None:
        dist.all_reduce(grad, op=dist.ReduceOp.SUM)  # the policy's whole gradient is one buffer: one collective

    def sum_(self, x: torch.Tensor) -> torch.Tensor:
        dist.all_reduce(x, op=dist.ReduceOp.SUM)
        return x

    def gather_envs(self, x: torch.Tensor, dim: int = 0) -> torch.Tensor:
        """Uneven slices are padded on the wire; the result is on every rank, on ``x``'s device."""
        if x.shape[dim] != self.local_envs:
            raise ValueError(f"gather_envs: dim {dim} of a {list(x.shape)} tensor is not the local env count {self.local_envs}")
        moved = _wire(x).movedim(dim, 0)
        width = max(self.counts)
        if moved.shape[0] < width:
            moved = torch.cat([moved, moved.new_zeros((width - moved.shape[0], *moved.shape[1:]))])
        moved = moved.contiguous()
        parts = [torch.empty_like(moved) for _ in range(self.world_size)]
        dist.all_gather(parts, moved)
        out = torch.cat([p[:c] for p, c in zip(parts, self.counts, strict=True)]).movedim(0, dim)
        return out.to(x.dtype)

    def gather_varlen(self, x: torch.Tensor) -> torch.Tensor:
        length = torch.tensor([x.shape[0]], dtype=torch.int64, device=x.device)
        lengths = [torch.zeros_like(length) for _ in range(self.world_size)]
        dist.all_gather(lengths, length)
        sizes = [int(v.item()) for v in lengths]
        width = max(sizes)
        if width == 0:
            return x
        wire = _wire(x)
        padded = torch.cat([wire, wire.new_zeros((width - x.shape[0], *x.shape[1:]))]).contiguous()
        parts = [torch.empty_like(padded) for _ in range(self.world_size)]
        dist.all_gather(parts, padded)
        return torch.cat([p[:s] for p, s in zip(parts, sizes, strict=True)]).to(x.dtype)

    def _gather_named(self, x: torch.Tensor, key: str) -> torch.Tensor:
        self._check_envs(x, key, self.local_envs, "local")
        return self.gather_envs(x).to(x.device)  # gloo moves CPU tensors, NCCL CUDA ones: keep each where it is

    def _shard_named(self, x: torch.Tensor, key: str) -> torch.Tensor:
        self._check_envs(x, key, self.num_envs, "global")
        return self.shard_envs(x).clone()

    def gather_rollout(self, rollout: Any, episode_infos: list[dict[str, Any]]) -> tuple[dict[str, torch.Tensor], list[dict[str, Any]]]:
        count = torch.tensor([len(episode_infos)], dtype=torch.int64, device=rollout.dones.device)
        low, high = count.clone(), count.clone()
        dist.all_reduce(low, op=dist.ReduceOp.MIN)
        dist.all_reduce(high, op=dist.ReduceOp.MAX)
        if int(low.item()) != int(high.item()):
            raise ValueError(
                "distributed records need environments that finish in lock-step on every rank; "
                f"ranks finished episodes at {int(low.item())}..{int(high.item())} steps of this rollout"
            )
        view = {name: self.gather_envs(getattr(rollout, name), dim=1) for name in ("actions", "values", "episode_returns", "dones")}
        # By the VecEnv protocol every tensor of an info is per environment: the whole info is gathered.
        return view, [self.gather_state({PER_ENV: info})[PER_ENV] for info in episode_infos]

    def reduce_stats(self, stats: Mapping[str, float]) -> dict[str, float]:
        if not stats:
            return {}
        device = self.device
        keys = sorted(stats)
        values = torch.tensor([float(stats[k]) for k in keys], dtype=torch.float64, device=device)
        is_time = torch.tensor(["seconds" in k for k in keys], device=device)
        summed, maxed = values.clone(), values.clone()
        dist.all_reduce(summed, op=dist.ReduceOp.SUM)
        dist.all_reduce(maxed, op=dist.ReduceOp.MAX)
        return {k: float(v) for k, v in zip(keys, torch.where(is_time, maxed, summed).tolist(), strict=True)}


def _draw(shape: Sequence[int], generator: torch.Generator, like: torch.Tensor, kind: str) -> torch.Tensor:
    """``shape`` numbers from ``generator`` in ``like``'s dtype and device: N(0, 1) or U[0, 1)."""
    if kind not in ("normal", "uniform"):
        raise ValueError(f"noise kind must be 'normal' or 'uniform', got {kind!r}")
    draw = torch.randn if kind == "normal" else torch.rand
    return draw(tuple(shape), generator=generator, device=like.device, dtype=like.dtype)


def collectives(local_envs: int, device: torch.device) -> Collectives:
    """The collectives of this process: :class:`DataParallel` inside a process group of several ranks (a
    collective: every rank calls it), else the single-process identity."""
    if is_distributed():
        return DataParallel.from_local(local_envs, device)
    return Collectives.single(local_envs)


__all__ = [
    "PER_ENV",
    "Collectives",
    "DataParallel",
    "backend",
    "broadcast_object",
    "collectives",
    "env_slice",
    "export_slurm_env",
    "init_from_env",
    "is_distributed",
    "is_main_process",
    "launch_env",
    "launch_rank",
    "pin_local_gpu",
    "rank",
    "shutdown",
    "world_size",
]
