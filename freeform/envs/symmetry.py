"""The ground's symmetries on a control env's box: what a body turned about the vertical or mirrored sees and does.

Gravity points along −z and the ground is the plane z = 0, so a body turned about z or mirrored through a vertical
plane and driven by its commands turned the same way moves as the body did, turned (the muscles are per-cell
scalars): exactly, bit for bit in f64, for the mirror that swaps x and y; to a few per cent for the others, which
reverse the links along an axis, and the link model (Voxelyze's, oriented from its first voxel to its second) is not
exactly symmetric under that (``tests/test_symmetry.py``: the distance moved in 0.075 s within 0.1–2 %). A distance
reward in the plane (``headings="any"``) does not change, nor does a reward along a heading that turns with it. So
one labelled sample of a body is eight: the observation's cells moved by the turn, its planar vectors (the
position from the centre of mass, the velocity, the heading) turned, and the action's cells moved the same way.
:class:`PlanarSymmetry` does that to batches, each sample by its own element of the group (``freeform.agents
.distill``'s ``algo.symmetry``).

The elements that map a box ``(Bx, By, Bz)`` onto itself: the mirrors of x and of y and their product (the half
turn) always, and where ``Bx == By`` the four more that swap x and y (the quarter turns and the diagonal mirrors):
8 elements for a square footprint, 4 otherwise. Element g = (swap, flip x, flip y) in bits ``4·swap + 2·fx + fy``;
a vector (x, y) goes to (x, y) swapped if ``swap``, then each component negated where flipped.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import torch

PLANAR_VECTORS = (("rel_x", "rel_y"), ("vel_x", "vel_y"), ("heading_cos", "heading_sin"), ("resp_x_sin", "resp_y_sin"),
                  ("resp_x_cos", "resp_y_cos"))
"""The channel pairs that are vectors in the ground plane: turned with the body."""
GROUPS = ("ground", "mirror")
"""``ground``: every turn and mirror that maps the box onto itself (8 or 4); ``mirror``: the identity and the mirror
y → −y alone, the elements that keep a direction along x (a wave head's hand-set wave travels along x when no
heading turns it: the other elements would ask its per-cell outputs to undo and redo the wave)."""


@dataclass(frozen=True)
class PlanarSymmetry:
    """The ground's symmetries on observations ``[N, C, Bx, By, Bz]`` and per-cell actions ``[N, c·Bx·By·Bz]``
    (C order, c blocks of the box's cells: a stroke's every a then every b). ``vectors``: the channel index pairs
    (x, y) of the planar vectors; ``group``: which elements (:data:`GROUPS`)."""

    box: tuple[int, int, int]
    vectors: tuple[tuple[int, int], ...]
    group: str = "ground"

    def __post_init__(self) -> None:
        if len(self.box) != 3 or min(self.box) < 1:
            raise ValueError(f"box must be three positive ints (Bx, By, Bz), got {self.box!r}")
        if self.group not in GROUPS:
            raise ValueError(f"symmetry group must be one of {GROUPS}, got {self.group!r}")

    @classmethod
    def of(cls, env: Any, group: str = "ground") -> PlanarSymmetry:
        """A control env's (its ``box`` and ``channels``). Refused for an env with a privileged critic (its state is
        a vector in the body's frame, which this does not turn)."""
        channels, box = getattr(env, "channels", None), getattr(env, "box", None)
        if channels is None or box is None:
            raise ValueError(f"the ground's symmetries need a control env (its box and channels); "
                             f"{type(env).__name__} has none")
        shape = env.observation_shape
        if isinstance(shape, Mapping) and "critic" in shape:
            raise ValueError("the ground's symmetries do not turn a privileged critic's state: set "
                             "control.privileged_critic=false to use algo.symmetry")
        vectors = tuple((channels.index(x), channels.index(y)) for x, y in PLANAR_VECTORS
                        if x in channels and y in channels)
        return cls(tuple(int(b) for b in box), vectors, group)

    @property
    def size(self) -> int:
        """The number of elements (``ground``: 8 for a square footprint, else 4; ``mirror``: 2); element 0 is the
        identity."""
        return 2 if self.group == "mirror" else 8 if self.box[0] == self.box[1] else 4

    def element(self, g: int) -> tuple[bool, bool, bool]:
        """Element ``g`` as (swap x and y, flip x, flip y)."""
        if not 0 <= g < self.size:
            raise ValueError(f"element must be in [0, {self.size}), got {g!r}")
        return bool(g & 4), bool(g & 2), bool(g & 1)  # (without a swap: 0..3 in both group sizes; mirror: 0, 1)

    def inverse(self, g: int) -> int:
        """The element that undoes element ``g``: a mirror or the half turn is its own; a swap followed by flips
        (a quarter turn, a diagonal mirror) is undone by the swap followed by the other axis' flips."""
        swap, fx, fy = self.element(g)
        return 4 * swap + 2 * (fy if swap else fx) + (fx if swap else fy)

    def matrix(self, g: int) -> torch.Tensor:
        """Element g's 2×2 matrix on planar vectors (float64)."""
        swap, fx, fy = self.element(g)
        m = torch.tensor([[0.0, 1.0], [1.0, 0.0]] if swap else [[1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
        return torch.diag(torch.tensor([-1.0 if fx else 1.0, -1.0 if fy else 1.0], dtype=torch.float64)) @ m

    def source_cells(self, g: int) -> torch.Tensor:
        """``[Bx·By·Bz]`` int64: for each cell of the turned box (C order), the cell of the original it comes from."""
        bx, by, bz = self.box
        i, j, k = torch.meshgrid(torch.arange(bx), torch.arange(by), torch.arange(bz), indexing="ij")
        swap, fx, fy = self.element(g)
        # forward: a cell (i, j) goes to (j, i) if swapped, then each axis reversed where flipped
        ni, nj = (j, i) if swap else (i, j)
        ni, nj = (bx - 1 - ni) if fx else ni, (by - 1 - nj) if fy else nj
        dest = (ni * by + nj) * bz + k
        source = torch.empty(bx * by * bz, dtype=torch.long)
        source[dest.reshape(-1)] = torch.arange(bx * by * bz)
        return source

    def tables(self, device: Any = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Every element's ``source_cells`` ``[G, cells]`` and ``matrix`` ``[G, 2, 2]`` (float32) on ``device``."""
        key = str(torch.device(device) if device is not None else torch.device("cpu"))
        if key not in self._tables:  # (made once per device: a minibatch's turns copy nothing to it)
            self._tables[key] = (torch.stack([self.source_cells(g) for g in range(self.size)]).to(device),
                                 torch.stack([self.matrix(g) for g in range(self.size)]).float().to(device))
        return self._tables[key]

    @cached_property
    def _tables(self) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
        return {}

    def observations(self, obs: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        """``obs [N, C, Bx, By, Bz]`` with sample n turned by element ``g[n]`` (``g [N]`` int64)."""
        n, c = obs.shape[:2]
        if tuple(obs.shape[2:]) != self.box:
            raise ValueError(f"observations must be [N, C, *{self.box}], got {tuple(obs.shape)}")
        sources, matrices = self.tables(obs.device)
        flat = obs.reshape(n, c, -1)
        moved = torch.gather(flat, 2, sources[g][:, None, :].expand(n, c, -1))
        if self.vectors:
            xs, ys = [x for x, _ in self.vectors], [y for _, y in self.vectors]
            vx, vy, m = moved[:, xs], moved[:, ys], matrices[g].to(obs.dtype)  # (copies: the writes below are safe)
            moved[:, xs] = m[:, 0, 0, None, None] * vx + m[:, 0, 1, None, None] * vy
            moved[:, ys] = m[:, 1, 0, None, None] * vx + m[:, 1, 1, None, None] * vy
        return moved.reshape(obs.shape)

    def cells(self, x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        """Per-cell values ``x [N, c·Bx·By·Bz]`` (c blocks of the box's cells, C order) with sample n's cells moved
        by element ``g[n]``."""
        cells = self.box[0] * self.box[1] * self.box[2]
        if x.dim() != 2 or x.shape[1] % cells:
            raise ValueError(f"per-cell values must be [N, c·{cells}] (c blocks of the box {self.box}'s cells), got "
                             f"{tuple(x.shape)}")
        n, blocks = x.shape[0], x.shape[1] // cells
        sources, _ = self.tables(x.device)
        index = sources[g][:, None, :].expand(n, blocks, cells)
        return torch.gather(x.reshape(n, blocks, cells), 2, index).reshape(x.shape)


__all__ = ["PLANAR_VECTORS", "PlanarSymmetry"]
