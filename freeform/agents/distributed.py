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
  *sums* by M; the gradients, summed over ranks in one flat buffer (:meth:`DataParallel.all_reduce_grads`), are
  then the gradient of the global minibatch's mean loss. M never needs to divide by R; a rank holding none of a
  minibatch contributes zeros.
- **Statistics over the global batch**: advantages, returns, values and σ are all-gathered once per epoch (a few
  floats per sample) so standardisation, explained variance and the logged means are the single process's
  formulas on the same numbers; the loss/KL sums are all-reduced once per epoch, so the adaptive-KL rule sees the
  same mean KL — and sets the same β — on every rank.

With the same seed, R ranks and one process therefore differ only by floating-point summation order.

State (checkpoints) is kept global: :func:`gather_per_env` concatenates per-environment tensors over ranks and
:func:`shard_per_env` slices them back, so a checkpoint written with R ranks resumes with any other R. The
convention: inside a state or ``info`` mapping, a tensor whose first dimension is the local environment count is
per-environment; an int under the key ``num_envs`` is the environment count.

:func:`init_from_env` creates the process group from ``torchrun``'s (or a SLURM job's) environment variables.
"""

from __future__ import annotations

import atexit
import datetime
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist
import torch.nn as nn

ENV_COUNT_KEY = "num_envs"
"""Key of an environment count inside an env's ``state_dict()`` (gathered -> global, sharded -> local)."""


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
# The data-parallel layer PPO uses.
# ---------------------------------------------------------------------------------------------------------------


def _wire(x: torch.Tensor) -> torch.Tensor:
    """What goes through a collective: bool as uint8 (not every backend reduces or gathers bool)."""
    return x.to(torch.uint8) if x.dtype == torch.bool else x


@dataclass
class DataParallel:
    """The collectives of one data-parallel PPO run, for a rank holding environments ``[lo, hi)`` of ``num_envs``.

    Build it with :meth:`from_local` (every rank at once: it all-gathers the local counts). ``counts[r]`` is rank
    r's environment count; slices are contiguous in rank order.
    """

    rank: int
    world_size: int
    counts: tuple[int, ...]

    @classmethod
    def from_local(cls, local_envs: int, device: torch.device) -> DataParallel:
        """Collective: learn every rank's environment count from the local one."""
        size = dist.get_world_size()
        mine = torch.tensor([local_envs], dtype=torch.int64, device=device)
        counts = [torch.zeros_like(mine) for _ in range(size)]
        dist.all_gather(counts, mine)
        return cls(rank=dist.get_rank(), world_size=size, counts=tuple(int(c.item()) for c in counts))

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

    # -- minibatches -----------------------------------------------------------------------------------------------

    def local_indices(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Global flat sample indices ``idx [M]`` (into ``[T, N]`` flattened, ``g = t·N + n``) -> ``(mask [M] bool,
        local [m])``: which of them this rank holds, and their flat indices into its ``[T, n_r]`` rollout (in the
        minibatch's order)."""
        n = self.num_envs
        t, env = idx // n, idx % n
        mask = (env >= self.lo) & (env < self.hi)
        return mask, t[mask] * self.local_envs + (env[mask] - self.lo)

    # -- collectives -----------------------------------------------------------------------------------------------

    def all_reduce_sum_(self, x: torch.Tensor) -> torch.Tensor:
        """In-place sum over ranks; returns ``x``."""
        dist.all_reduce(x, op=dist.ReduceOp.SUM)
        return x

    def all_reduce_grads(self, params: Iterable[nn.Parameter], buffer: torch.Tensor | None = None) -> torch.Tensor:
        """Sum every parameter's gradient over ranks as **one** flat buffer (one collective per SGD step); a missing
        gradient counts as zeros. Returns the buffer (pass it back in to reuse its memory)."""
        params = list(params)
        total = sum(p.numel() for p in params)
        if buffer is None or buffer.numel() != total:
            buffer = torch.empty(total, dtype=params[0].dtype, device=params[0].device)
        offset = 0
        for p in params:
            part = buffer[offset : offset + p.numel()]
            if p.grad is None:
                part.zero_()
            else:
                part.copy_(p.grad.reshape(-1))
            offset += p.numel()
        dist.all_reduce(buffer, op=dist.ReduceOp.SUM)
        offset = 0
        for p in params:
            part = buffer[offset : offset + p.numel()].view_as(p)
            if p.grad is None:
                p.grad = part.clone()
            else:
                p.grad.copy_(part)
            offset += p.numel()
        return buffer

    def broadcast_module_(self, module: nn.Module, src: int = 0) -> None:
        """Copy rank ``src``'s parameters and buffers into every rank's ``module`` (identical starting weights)."""
        with torch.no_grad():
            for tensor in list(module.parameters()) + list(module.buffers()):
                dist.broadcast(tensor.data, src=src)

    def gather_envs(self, x: torch.Tensor, dim: int = 0) -> torch.Tensor:
        """Concatenate every rank's per-environment tensor along its environment dimension ``dim`` (``[.., n_r,
        ..]`` -> ``[.., N, ..]``), in rank order, on every rank. Uneven slices are padded on the wire."""
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
        """Concatenate every rank's 1-D tensor of any length, in rank order, on every rank."""
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

    def shard_envs(self, x: torch.Tensor, dim: int = 0) -> torch.Tensor:
        """This rank's slice ``[lo, hi)`` of a global per-environment tensor along ``dim``."""
        if x.shape[dim] != self.num_envs:
            raise ValueError(f"shard_envs: dim {dim} of a {list(x.shape)} tensor is not the global env count {self.num_envs}")
        return x.narrow(dim, self.lo, self.local_envs)


# ---------------------------------------------------------------------------------------------------------------
# Per-environment state: gather to global (checkpoints, records), shard back to local (resume).
# ---------------------------------------------------------------------------------------------------------------


def gather_per_env(obj: Any, dp: DataParallel) -> Any:
    """Collective: ``obj`` (nested dicts/lists/tuples of tensors and plain values) with every per-environment tensor
    (first dimension = the local env count) concatenated over ranks and ``num_envs`` counts made global. Every rank
    must pass structurally equal objects; plain values are rank 0's (they are the same on every rank)."""
    if isinstance(obj, torch.Tensor):
        if obj.dim() >= 1 and obj.shape[0] == dp.local_envs:
            device = obj.device
            # gloo moves CPU tensors only; NCCL CUDA ones: keep each tensor where it is.
            return dp.gather_envs(obj).to(device)
        return obj
    if isinstance(obj, Mapping):
        out = {}
        for key, value in obj.items():
            if key == ENV_COUNT_KEY and isinstance(value, int) and not isinstance(value, bool):
                out[key] = dp.num_envs
            else:
                out[key] = gather_per_env(value, dp)
        return out
    if isinstance(obj, (list, tuple)):
        items = [gather_per_env(v, dp) for v in obj]
        return type(obj)(items) if isinstance(obj, list) else tuple(items)
    return obj


def shard_per_env(obj: Any, dp: DataParallel) -> Any:
    """Inverse of :func:`gather_per_env`: this rank's slice of every global per-environment tensor (first dimension
    = the global env count) and ``num_envs`` counts made local. No communication."""
    if isinstance(obj, torch.Tensor):
        if obj.dim() >= 1 and obj.shape[0] == dp.num_envs:
            return dp.shard_envs(obj).clone()
        return obj
    if isinstance(obj, Mapping):
        out = {}
        for key, value in obj.items():
            if key == ENV_COUNT_KEY and isinstance(value, int) and not isinstance(value, bool):
                out[key] = dp.local_envs
            else:
                out[key] = shard_per_env(value, dp)
        return out
    if isinstance(obj, (list, tuple)):
        items = [shard_per_env(v, dp) for v in obj]
        return type(obj)(items) if isinstance(obj, list) else tuple(items)
    return obj


def gather_rollout(rollout: Any, episode_infos: list[dict[str, Any]], dp: DataParallel) -> tuple[dict[str, torch.Tensor], list[dict[str, Any]]]:
    """Collective: the global view of an epoch's rollout for records — ``actions [T, N, A]``, ``values``,
    ``rewards [T, N]``, ``dones [T, N]`` — and ``episode_infos`` with their per-environment entries gathered
    (``final_grids``, ``bodies``, ``metrics``). Environments must finish in lock-step across ranks (the design
    environment's episodes all end at step T), so every rank has the same number of infos."""
    count = torch.tensor([len(episode_infos)], dtype=torch.int64, device=rollout.rewards.device)
    low, high = count.clone(), count.clone()
    dist.all_reduce(low, op=dist.ReduceOp.MIN)
    dist.all_reduce(high, op=dist.ReduceOp.MAX)
    if int(low.item()) != int(high.item()):
        raise ValueError(
            "distributed records need environments that finish in lock-step on every rank; "
            f"ranks finished episodes at {int(low.item())}..{int(high.item())} steps of this rollout"
        )
    view = {name: dp.gather_envs(getattr(rollout, name), dim=1) for name in ("actions", "values", "rewards", "dones")}
    return view, [gather_per_env(info, dp) for info in episode_infos]


def reduce_task_stats(stats: Mapping[str, float], device: torch.device) -> dict[str, float]:
    """Collective: a task's per-rank figures over all ranks — times (``*seconds*``) by max (ranks run in
    parallel), everything else (counts, per-second rates) by sum. Every rank must report the same keys."""
    if not stats or not is_distributed():
        return dict(stats)
    keys = sorted(stats)
    values = torch.tensor([float(stats[k]) for k in keys], dtype=torch.float64, device=device)
    is_time = torch.tensor(["seconds" in k for k in keys], device=device)
    summed, maxed = values.clone(), values.clone()
    dist.all_reduce(summed, op=dist.ReduceOp.SUM)
    dist.all_reduce(maxed, op=dist.ReduceOp.MAX)
    return {k: float(v) for k, v in zip(keys, torch.where(is_time, maxed, summed).tolist(), strict=True)}


__all__ = [
    "DataParallel",
    "backend",
    "broadcast_object",
    "env_slice",
    "export_slurm_env",
    "gather_per_env",
    "gather_rollout",
    "init_from_env",
    "is_distributed",
    "is_main_process",
    "launch_env",
    "launch_rank",
    "pin_local_gpu",
    "rank",
    "reduce_task_stats",
    "shard_per_env",
    "shutdown",
    "world_size",
]
