"""Bodies: the largest 6-connected component of a design grid, its bounding box, and the paper's body metrics.

Everything here is batched over a leading grid axis ``N`` and written in pure torch, so it runs on whatever device
the grids live on (no scipy, no Python loop over grids or voxels — except the zlib call of ``compressibility``,
which has no tensor equivalent).

How components are found. A design grid is sparse (N(0, I) actions fill 4–6 % of a 20³ grid, and T = 100
bundles never fill more than 800 voxels), so the work is done on a *graph of the occupied voxels of all N grids at
once*: node ids are the occupied voxels in C order (grid-major, then x, y, z), edges join face neighbours.
Components are found by min-label hooking with pointer jumping (Shiloach–Vishkin style): each round, the parent
of the larger end of every edge is hooked under the smaller parent of the edge, then trees are flattened by
``parent = parent[parent]`` (twice). Parents only ever decrease, so it terminates; at the fixed point every tree
is a star whose root is the *smallest node id of its component*, i.e. its first voxel in C order — exactly the
spec's tie rule for the largest component. Hooking plus jumping needs a handful of rounds (5 on N(0, I) designs, 7
on a snake through half the rows of a 20³ grid, whose path is ~2,100 voxels long), where plain min-label
propagation needs one round per voxel of the longest path.

The substructure count needs the *empty* regions too, which are dense. It is computed on each body's bounding box
grown by one cell (clipped to the grid): every empty cell outside that box reaches the box's empty shell through
empty cells, and any path through the outside projects onto the shell, so the box holds exactly the same regions
as the whole grid (~10× fewer cells for an N(0, I) body). The box cells are further merged into runs along z
before labelling.
"""

from __future__ import annotations

import contextlib
import functools
import zlib
from collections.abc import Callable, Iterator
from typing import TypeVar

import numpy as np
import torch

__all__ = [
    "METRIC_NAMES",
    "PASSIVE_MATERIAL",
    "bounding_box",
    "check_grids",
    "component_labels",
    "crop",
    "diversity",
    "largest_component",
    "metrics",
    "bodies_and_metrics",
    "serial_on_cpu",
]

#: Keys of :func:`metrics`, in the paper's Fig. 4 order.
METRIC_NAMES: tuple[str, ...] = (
    "volume",
    "surface_ratio",
    "passive_ratio",
    "lcc_ratio",
    "substructures",
    "symmetry",
    "compressibility",
)

#: Material index of passive tissue (spec: index 0 is empty, 1 is passive).
PASSIVE_MATERIAL = 1


# ------------------------------------------------------------------------------------------------- threading
@contextlib.contextmanager
def serial_on_cpu(device: torch.device | str) -> Iterator[None]:
    """Run the enclosed torch ops single-threaded when ``device`` is the CPU; restore the thread count after.

    Why: the design env and the body functions issue many small, memory-bound ops (10⁴–10⁶ elements) where
    torch's intra-op threads gain little, and on a shared CPU they cost a lot — an OpenMP region waits for its
    slowest thread, and a descheduled one stalls it (measured: docs/design_env.md). The thread count is
    process-wide, so other Python threads running torch ops meanwhile also run serially.
    """
    if torch.device(device).type != "cpu" or torch.get_num_threads() == 1:
        yield
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


_F = TypeVar("_F", bound=Callable)


def _serial(fn: _F) -> _F:
    """Decorate a function whose first argument is a tensor: run it under :func:`serial_on_cpu`."""

    @functools.wraps(fn)
    def wrapper(grids, *args, **kwargs):
        device = grids.device if isinstance(grids, torch.Tensor) else "cpu"
        with serial_on_cpu(device):
            return fn(grids, *args, **kwargs)

    return wrapper  # type: ignore[return-value]


# --------------------------------------------------------------------------------------------------- validation
def check_grids(grids: torch.Tensor, materials: int | None = None, name: str = "grids") -> None:
    """Raise ``ValueError`` unless ``grids`` is a uint8 ``[N, X, Y, Z]`` tensor with indices below ``materials``."""
    if not isinstance(grids, torch.Tensor):
        raise ValueError(
            f"{name} must be a torch.Tensor of dtype uint8 and shape [N, X, Y, Z], got {type(grids).__name__}"
        )
    if grids.dtype != torch.uint8:
        raise ValueError(f"{name} must have dtype torch.uint8 (material indices), got {grids.dtype}")
    if grids.dim() != 4:
        raise ValueError(f"{name} must have rank 4, shape [N, X, Y, Z], got shape {tuple(grids.shape)}")
    if materials is not None:
        if materials < 2:
            raise ValueError(
                f"materials must be an integer >= 2 (empty + at least one material), got {materials}"
            )
        if grids.numel() and int(grids.max()) >= materials:
            raise ValueError(
                f"{name} holds material index {int(grids.max())}, allowed values are 0 … {materials - 1} "
                f"(materials={materials})"
            )


def _check_single(grid: torch.Tensor, name: str = "grid") -> None:
    if not isinstance(grid, torch.Tensor) or grid.dtype != torch.uint8 or grid.dim() != 3:
        shape = tuple(grid.shape) if isinstance(grid, torch.Tensor) else type(grid).__name__
        dtype = grid.dtype if isinstance(grid, torch.Tensor) else None
        raise ValueError(f"{name} must be a uint8 tensor of shape [X, Y, Z], got {shape} {dtype}")


# ---------------------------------------------------------------------------------------- connected components
def _components(num_nodes: int, src: torch.Tensor, dst: torch.Tensor) -> tuple[torch.Tensor, int]:
    """Connected components of an undirected graph.

    Args:
        num_nodes: M, nodes are ``0 … M-1``.
        src, dst: ``[E] int64`` edge end points.

    Returns:
        ``(root, rounds)``: ``[M] int64``, for every node the smallest node id of its component; and the number
        of hook-and-jump rounds it took (the last one only confirms the fixed point).
    """
    parent = torch.arange(num_nodes, device=src.device)
    if src.numel() == 0:
        return parent, 0
    rounds = 0
    while True:
        rounds += 1
        ps, pd = parent.index_select(0, src), parent.index_select(0, dst)
        # Hook: the parent of the larger end moves under the smaller parent of the edge. Parents only ever
        # decrease and stay inside their component, so no cycle can form.
        hooked = parent.scatter_reduce(0, torch.maximum(ps, pd), torch.minimum(ps, pd), reduce="amin")
        # Pointer jumping, twice a round: it flattens the trees that hooking deepens.
        hooked = hooked.index_select(0, hooked)
        hooked = hooked.index_select(0, hooked)
        if torch.equal(hooked, parent):
            return parent, rounds
        parent = hooked


class _OccupiedGraph:
    """The graph of the occupied voxels of a batch of grids (see the module docstring), labelled.

    Attributes:
        pos: ``[M] int64`` flat positions (``n·V + x·Y·Z + y·Z + z``) of the occupied voxels, ascending.
        values: ``[M] uint8`` their materials.
        grid: ``[M] int64`` the grid each node belongs to.
        coords: ``[3, M] int64`` (x, y, z) of each node.
        src, dst: ``[E] int64`` node ids of face-adjacent occupied pairs.
        root: ``[M] int64`` smallest node id of each node's component.
        rounds: hook-and-jump rounds the labelling took.
    """

    def __init__(self, grids: torch.Tensor) -> None:
        n, sx, sy, sz = grids.shape
        device = grids.device
        volume = sx * sy * sz
        flat = grids.reshape(-1)
        self.shape = (n, sx, sy, sz)
        self.pos = torch.nonzero(flat).squeeze(1)
        self.values = flat.index_select(0, self.pos)
        m = self.pos.numel()
        self.num_nodes = m
        self.grid = torch.div(self.pos, volume, rounding_mode="floor")
        local = self.pos - self.grid * volume
        x = torch.div(local, sy * sz, rounding_mode="floor")
        rest = local - x * (sy * sz)
        y = torch.div(rest, sz, rounding_mode="floor")
        self.coords = torch.stack((x, y, rest - y * sz))
        strides = torch.tensor((sy * sz, sz, 1), device=device)
        last = torch.tensor((sx - 1, sy - 1, sz - 1), device=device)
        # Dense map flat position -> node id (-1 where empty), padded so that +stride never leaves it; the only
        # pass over the whole grids besides nonzero(). int32 halves its memory traffic.
        node_of = torch.full((flat.numel() + sy * sz,), -1, dtype=torch.int32, device=device)
        node_of[self.pos] = torch.arange(m, dtype=torch.int32, device=device)
        neighbour = node_of.index_select(0, (self.pos + strides[:, None]).reshape(-1)).view(3, m)
        edge = torch.nonzero(((neighbour >= 0) & (self.coords < last[:, None])).view(-1)).squeeze(1)
        self.src = edge % m
        self.dst = neighbour.view(-1).index_select(0, edge).to(torch.int64)
        self.root, self.rounds = _components(m, self.src, self.dst)

    def per_grid(self, weights: torch.Tensor) -> torch.Tensor:
        """Sum ``[M]`` node weights (bool or float) per grid -> ``[N] float32``."""
        return torch.bincount(self.grid, weights=weights.to(torch.float32), minlength=self.shape[0])

    def largest_root(self) -> torch.Tensor:
        """``[N] int64``: the root node of each grid's largest component (ties: smallest root), -1 if empty."""
        n = self.shape[0]
        m = self.num_nodes
        device = self.pos.device
        size = torch.bincount(self.root, minlength=m)  # nonzero only at roots
        # One integer key orders by size, then by *smaller* root id: size·(M+1) + (M - root).
        key = torch.where(size > 0, size * (m + 1) + (m - torch.arange(m, device=device)), 0)
        best = torch.zeros(n, dtype=torch.int64, device=device).scatter_reduce_(
            0, self.grid, key, reduce="amax"
        )
        return torch.where(best > 0, m - best % (m + 1), -1)

    def body_mask(self) -> torch.Tensor:
        """``[M] bool``: the nodes in their grid's largest component."""
        return self.root == self.largest_root().index_select(0, self.grid)

    def bodies(self, in_body: torch.Tensor) -> torch.Tensor:
        """The dense bodies ``[N, X, Y, Z] uint8`` of the nodes ``in_body``."""
        bodies = torch.zeros(self.shape, dtype=torch.uint8, device=self.pos.device)
        kept = self.pos[in_body]
        bodies.view(-1)[kept] = self.values[in_body]
        return bodies


@_serial
def component_labels(grids: torch.Tensor) -> torch.Tensor:
    """Label the 6-connected components of the non-empty voxels of each grid.

    Args:
        grids: ``[N, X, Y, Z] uint8`` material indices (any non-zero value is occupied).

    Returns:
        ``[N, X, Y, Z] int64``: 0 for empty cells, components numbered ``1, 2, …`` per grid in the C order of their
        first voxel (the numbering ``scipy.ndimage.label`` uses).
    """
    check_grids(grids)
    graph = _OccupiedGraph(grids)
    n = grids.shape[0]
    device = grids.device
    is_root = graph.root == torch.arange(graph.num_nodes, device=device)
    rank = torch.cumsum(is_root, 0)  # 1-based rank of each root among all roots, in C order
    roots_per_grid = torch.bincount(graph.grid[is_root], minlength=n)
    offset = torch.cumsum(roots_per_grid, 0) - roots_per_grid
    labels = torch.zeros(grids.numel(), dtype=torch.int64, device=device)
    labels[graph.pos] = rank[graph.root] - offset[graph.grid]
    return labels.view(grids.shape)


@_serial
def largest_component(grids: torch.Tensor) -> torch.Tensor:
    """Keep only the largest 6-connected component of each grid (the robot body).

    Ties go to the component whose first voxel in C order (x slowest, z fastest) comes first. An empty grid stays
    empty.

    Args:
        grids: ``[N, X, Y, Z] uint8`` material indices.

    Returns:
        ``[N, X, Y, Z] uint8``: the bodies, materials kept, everything outside the largest component set to 0.
    """
    check_grids(grids)
    graph = _OccupiedGraph(grids)
    return graph.bodies(graph.body_mask())


# ------------------------------------------------------------------------------------------------ bounding box
@_serial
def bounding_box(grids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-grid bounding box of the non-empty voxels.

    Args:
        grids: ``[N, X, Y, Z] uint8``.

    Returns:
        ``(lo, hi)``, each ``[N, 3] int64``: the box is ``grid[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]`` (``hi``
        exclusive). An empty grid gives ``lo = hi = 0`` (an empty box).
    """
    check_grids(grids)
    n = grids.shape[0]
    occupied = grids != 0
    lo, hi = [], []
    for axis in range(3):
        # Project the occupancy onto one axis; first/last occupied slice along it.
        other = tuple(a + 1 for a in range(3) if a != axis)
        line = occupied.any(dim=other)  # [N, size]
        size = line.shape[1]
        index = torch.arange(size, device=grids.device)
        lo.append(torch.where(line, index, size).amin(dim=1))
        hi.append(torch.where(line, index + 1, 0).amax(dim=1))
    lo_t = torch.stack(lo, dim=1)
    hi_t = torch.stack(hi, dim=1)
    empty = ~occupied.reshape(n, -1).any(dim=1, keepdim=True)
    return torch.where(empty, 0, lo_t), torch.where(empty, 0, hi_t)


def crop(grid: torch.Tensor) -> torch.Tensor:
    """Crop one grid ``[X, Y, Z] uint8`` to the bounding box of its non-empty voxels (a view; ``[0, 0, 0]`` if
    the grid is empty)."""
    _check_single(grid)
    lo, hi = bounding_box(grid.unsqueeze(0))
    (x0, y0, z0), (x1, y1, z1) = lo[0].tolist(), hi[0].tolist()
    return grid[x0:x1, y0:y1, z0:z1]


def at_corner(grids: torch.Tensor) -> torch.Tensor:
    """Each grid ``[N, X, Y, Z] uint8`` moved so that its bounding box starts at cell (0, 0, 0) (the rest empty):
    a body placed elsewhere in its grid becomes the same array."""
    lo, _ = bounding_box(grids)
    n, *size = grids.shape
    moved = grids
    for axis in range(3):
        index = torch.arange(size[axis], device=grids.device)[None] + lo[:, axis: axis + 1]  # [N, size]
        inside = index < size[axis]
        shape = [n, 1, 1, 1]
        shape[axis + 1] = size[axis]
        gather = index.clamp_max(size[axis] - 1).view(shape).expand_as(moved)
        moved = torch.gather(moved, axis + 1, gather) * inside.view(shape)
    return moved


def diversity(grids: torch.Tensor) -> dict[str, float | int]:
    """How different a set of designs is (a co-design that collapses onto one body shows here), each moved to its
    grid's corner (:func:`at_corner`: where a body sits is not what it is): ``distance``, the mean over pairs of the
    fraction of cells whose material differs (scipy's ``pdist(..., "hamming")``), and ``distinct``, the number of
    different bodies. ``grids``: ``[N, X, Y, Z] uint8``, N >= 2."""
    check_grids(grids)
    if grids.shape[0] < 2:
        raise ValueError(f"diversity needs at least 2 designs, got {grids.shape[0]}")
    flat = at_corner(grids).reshape(grids.shape[0], -1).long()
    n, cells = flat.shape
    # pairs (i, j) agreeing at a cell, summed over the pairs: the square of how many designs hold each material there
    holders = torch.nn.functional.one_hot(flat).sum(0).double()  # [cells, k]
    distance = (n * n * cells - holders.pow(2).sum()) / (n * (n - 1) * cells)  # (a design agrees with itself: n·cells)
    return {"distance": float(distance), "distinct": int(torch.unique(flat, dim=0).shape[0])}


# ------------------------------------------------------------------------------------------------------ metrics
@_serial
def metrics(grids: torch.Tensor, materials: int | None = None) -> dict[str, torch.Tensor]:
    """The paper's body metrics (Fig. 4) of each final grid; the body is the grid's largest component.

    Args:
        grids: ``[N, X, Y, Z] uint8`` final design grids (the whole grid, disconnected parts included).
        materials: k; if given, every index must be below it.

    Returns:
        ``{name: [N] float32}`` for the names of :data:`METRIC_NAMES`, on the grids' device:

        - ``volume``: voxels in the body.
        - ``surface_ratio``: body voxels with at least one empty face neighbour (outside the grid and cavity
          walls count) / volume.
        - ``passive_ratio``: passive voxels (material 1) / volume.
        - ``lcc_ratio``: volume / non-empty voxels of the whole grid.
        - ``substructures``: 6-connected regions of equal material index in the body's grid, empty regions
          (outside and each cavity, within the grid) included.
        - ``symmetry``: mean over the 3 axes of 2·#(L == R ∧ L ≠ 0) / (#(L ≠ 0) + #(R ≠ 0)), where L is the first
          ⌊size/2⌋ slices and R the last ⌊size/2⌋ slices mirrored (0 when both are empty).
        - ``compressibility``: ``len(zlib.compress(body.tobytes())) / (X·Y·Z)`` (default level, C order).

        An empty body gives 0 for volume and for every ratio (never NaN, no division by zero); its substructure
        count is 1 (the empty grid is one region) and its compressibility is that of an all-empty grid.
    """
    return bodies_and_metrics(grids, materials)[1]


@_serial
def bodies_and_metrics(
    grids: torch.Tensor, materials: int | None = None
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """``(largest_component(grids), metrics(grids))`` from one labelling: what the design env needs at the end of
    an episode. Shapes as in those two functions."""
    check_grids(grids, materials)
    graph = _OccupiedGraph(grids)
    in_body = graph.body_mask()
    bodies = graph.bodies(in_body)

    def ratio(num: torch.Tensor, den: torch.Tensor) -> torch.Tensor:
        return torch.where(den > 0, num / den.clamp(min=1), 0.0)

    volume = graph.per_grid(in_body)
    nonempty = graph.per_grid(torch.ones_like(in_body))
    # Surface: a body voxel with fewer than 6 occupied face neighbours. Every occupied neighbour of a body voxel
    # is in the body (same component), so the occupied graph's degree is the body degree.
    m = graph.num_nodes
    degree = torch.bincount(graph.src, minlength=m) + torch.bincount(graph.dst, minlength=m)
    surface = graph.per_grid(in_body & (degree < 6))
    passive = graph.per_grid(in_body & (graph.values == PASSIVE_MATERIAL))
    body = _BodyVoxels(graph, in_body)
    return bodies, {
        "volume": volume,
        "surface_ratio": ratio(surface, volume),
        "passive_ratio": ratio(passive, volume),
        "lcc_ratio": ratio(volume, nonempty),
        "substructures": _substructures(bodies, body),
        "symmetry": _symmetry(bodies, body),
        "compressibility": _compressibility(bodies),
    }


class _BodyVoxels:
    """The body voxels alone (a typical body is ~15 % of the occupied voxels): ``pos``, ``values``, ``grid``
    ``[B]`` and ``coords`` ``[3, B]``, as in :class:`_OccupiedGraph`."""

    def __init__(self, graph: _OccupiedGraph, in_body: torch.Tensor) -> None:
        self.num_grids = graph.shape[0]
        self.pos = graph.pos[in_body]
        self.values = graph.values[in_body]
        self.grid = graph.grid[in_body]
        self.coords = graph.coords[:, in_body]

    def per_grid(self, weights: torch.Tensor) -> torch.Tensor:
        """Sum ``[B]`` weights per grid -> ``[N] float32``."""
        return torch.bincount(self.grid, weights=weights.to(torch.float32), minlength=self.num_grids)


def _symmetry(bodies: torch.Tensor, body: _BodyVoxels) -> torch.Tensor:
    """Reflection symmetry ``[N] float32`` (see :func:`metrics`), from the body voxels alone."""
    n, sx, sy, sz = bodies.shape
    flat = bodies.view(-1)
    scores = torch.zeros(n, dtype=torch.float32, device=bodies.device)
    for axis, (size, stride) in enumerate(((sx, sy * sz), (sy, sz), (sz, 1))):
        half = size // 2
        c = body.coords[axis]
        left = c < half
        mirror = body.pos + (size - 1 - 2 * c) * stride  # the cell reflected through the centre plane
        same = left & (flat.index_select(0, mirror) == body.values)
        count = body.per_grid(left) + body.per_grid(c >= size - half)
        scores += torch.where(count > 0, 2 * body.per_grid(same) / count.clamp(min=1), 0.0)
    return scores / 3


def _substructures(bodies: torch.Tensor, body: _BodyVoxels) -> torch.Tensor:
    """Equal-label 6-connected regions of each body grid ``[N] float32``, counted on the grown bounding box.

    The box cells are grouped into runs along z (maximal stretches of one label in a box row; the empty space of
    a box is mostly a few long runs), and components are found on the runs: an x or y edge joins two runs of
    equal label where their z-overlap begins, i.e. where one of the two cells starts its run — one edge per
    overlapping pair.
    """
    n, sx, sy, sz = bodies.shape
    device = bodies.device
    last = torch.tensor((sx - 1, sy - 1, sz - 1), device=device)
    # Bounding box of each body, grown by one cell and clipped to the grid.
    index = body.grid[None, :].expand(3, -1)
    lo = torch.full((3, n), max(sx, sy, sz), dtype=torch.int64, device=device)
    lo.scatter_reduce_(1, index, body.coords, reduce="amin")
    hi = torch.full((3, n), -1, dtype=torch.int64, device=device)
    hi.scatter_reduce_(1, index, body.coords, reduce="amax")
    has_body = hi[0] >= 0
    lo = (lo - 1).clamp(min=0)
    hi = torch.minimum(hi + 1, last[:, None])
    dims = torch.where(has_body, hi - lo + 1, 0)  # [3, N]; an empty body gets no cells
    cells = dims.prod(dim=0)
    total = int(cells.sum())
    # Enumerate every box cell of every grid: cell t is cell `local` (C order) of grid `box_grid`'s box.
    box_grid = torch.repeat_interleave(torch.arange(n, device=device), cells, output_size=total)
    nodes = torch.arange(total, device=device)
    local = nodes - (torch.cumsum(cells, 0) - cells).index_select(0, box_grid)
    d = dims.index_select(1, box_grid)  # [3, T]
    plane = d[1] * d[2]
    lx = torch.div(local, plane, rounding_mode="floor")
    rest = local - lx * plane
    ly = torch.div(rest, d[2], rounding_mode="floor")
    lz = rest - ly * d[2]
    o = lo.index_select(1, box_grid)
    pos = box_grid * (sx * sy * sz) + (o[0] + lx) * (sy * sz) + (o[1] + ly) * sz + (o[2] + lz)
    values = bodies.view(-1).index_select(0, pos)
    # Runs along z.
    starts = (lz == 0) | (values != torch.roll(values, 1))
    run = torch.cumsum(starts, 0) - 1
    srcs, dsts = [], []
    for coord, size, stride in ((lx, d[0], plane), (ly, d[1], d[2])):
        inside = coord < size - 1
        neighbour = torch.where(inside, nodes + stride, nodes)
        keep = (
            inside
            & (values.index_select(0, neighbour) == values)
            & (starts | starts.index_select(0, neighbour))
        )
        cell = torch.nonzero(keep).squeeze(1)
        srcs.append(run.index_select(0, cell))
        dsts.append(run.index_select(0, neighbour.index_select(0, cell)))
    num_runs = int(run[-1]) + 1 if total else 0
    root, _ = _components(num_runs, torch.cat(srcs), torch.cat(dsts))
    run_grid = box_grid[starts]
    regions = torch.bincount(
        run_grid, weights=(root == torch.arange(num_runs, device=device)).float(), minlength=n
    )
    # An empty body grid is a single empty region.
    return torch.where(has_body, regions, 1.0)


def _compressibility(bodies: torch.Tensor) -> torch.Tensor:
    """``len(zlib.compress(body bytes)) / cells`` per grid ``[N] float32`` (zlib runs on the CPU, one call a grid)."""
    n, sx, sy, sz = bodies.shape
    cells = sx * sy * sz
    host = bodies.reshape(n, cells).cpu().numpy()
    sizes = np.fromiter((len(zlib.compress(row.tobytes())) for row in host), dtype=np.float64, count=n)
    return torch.from_numpy(sizes / cells).to(device=bodies.device, dtype=torch.float32)
