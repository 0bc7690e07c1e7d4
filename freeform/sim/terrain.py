"""The ground the robots stand on: ``Terrain`` (a plain dataclass, set as ``SimConfig.terrain`` or
``sim.terrain.*`` on the command line) and its compiled form, a height field the kernels read.

Every terrain is a surface z = S(x, y) over the robots' frame (metres; the flat floor is S = −L/2, spec section 1):

* ``flat``: today's floor. The kernels keep Voxelyze's own floor code for it (compile-time), so results are
  bit for bit those of a simulator without terrain.
* ``slope``: a plane rising at ``degrees`` towards +``axis``.
* ``rough``: smooth random bumps, a sum of cosines of one ``wavelength`` in random directions, peak ``amplitude``,
  sampled on a grid and interpolated bilinearly.
* ``steps``: a staircase of risers ``height`` and treads ``depth`` rising towards +``axis``, whose first riser is
  ``gap`` ahead of each body's front face.
* ``heightmap``: any height field ``heights[i][j]`` (m) on cells of ``cell_size`` starting at (x0, y0),
  interpolated bilinearly (``smooth``) or as flat-topped columns (``smooth=False``, the staircase's form).

Contact keeps Voxelyze's floor model measured along the local surface normal n: penetration = size/2 − d (d: the
voxel centre's distance to the surface), normal force k·pen − c·(v·n) along n, and the static/kinetic Coulomb
friction state machine on the tangential force and velocity (see ``voxels.terrain_contact``). A smooth surface's
distance is (z − S)·n_z, exact for planes; a columnar one's is the distance to the nearest column (its top, edge
or side), so a voxel meets a riser on its face. Beyond the grid the edge values continue.

Bodies start resting on the terrain under their footprint: each robot is lifted (and, on stairs, shifted along
the axis) so that its lowest contact is exactly touching (``placement``). Robots share one terrain and never meet.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from freeform.validation import require

KINDS = ("flat", "slope", "rough", "steps", "heightmap")
AXES = ("x", "y")
# compiled modes (a compile-time switch of the voxel kernel)
FLAT, SMOOTH, COLUMNS = 0, 1, 2
ROUGH_EXTENT = 1.0  # m: the rough field covers [-extent/2, extent/2]² around the robots' start (100 voxels)
ROUGH_WAVES = 8  # cosines summed for rough ground
STEPS_COUNT = 64  # treads built; beyond them the top tread goes on


@dataclass
class Terrain:
    """The ground (SI units). Build one with ``Terrain.flat()``, ``.slope(...)``, ``.rough(...)``, ``.steps(...)``,
    ``.heightmap(...)``; the fields are plain so that ``sim.terrain.kind=slope sim.terrain.degrees=5`` works.

    kind: one of ``KINDS``. degrees: slope angle (uphill towards +axis). axis: "x" | "y" (slope and steps).
    amplitude / wavelength / seed: rough ground (m, m, RNG seed). height / depth / gap: steps' riser, tread and the
    distance from each body's front face to the first riser (m). heights / cell_size / x0 / y0 / smooth: a
    height field ``heights[i][j]`` at x = x0 + i·cell_size, y = y0 + j·cell_size (m above the flat floor).
    """

    kind: str = "flat"
    degrees: float = 0.0
    axis: str = "x"
    amplitude: float = 0.0
    wavelength: float = 0.05
    seed: int = 0
    height: float = 0.0
    depth: float = 0.05
    gap: float = 0.01
    heights: list[list[float]] | None = None
    cell_size: float = 0.01
    x0: float = 0.0
    y0: float = 0.0
    smooth: bool = True

    # ------------------------------------------------------------------ constructors
    @classmethod
    def flat(cls) -> Terrain:
        """Today's floor: results bit for bit those of the simulator without terrain."""
        return cls()

    @classmethod
    def slope(cls, degrees: float, axis: str = "x") -> Terrain:
        """A plane rising at ``degrees`` towards +``axis``."""
        return cls(kind="slope", degrees=float(degrees), axis=axis)

    @classmethod
    def rough(cls, amplitude: float, wavelength: float, seed: int = 0) -> Terrain:
        """Smooth random bumps of peak height ``amplitude`` (m) and ``wavelength`` (m)."""
        return cls(kind="rough", amplitude=float(amplitude), wavelength=float(wavelength), seed=int(seed))

    @classmethod
    def steps(cls, height: float, depth: float, axis: str = "x", gap: float = 0.01) -> Terrain:
        """A staircase rising towards +``axis``: risers ``height``, treads ``depth`` (m); the first riser ``gap``
        ahead of each body's front face."""
        return cls(kind="steps", height=float(height), depth=float(depth), axis=axis, gap=float(gap))

    @classmethod
    def heightmap(cls, heights, cell_size: float, x0: float = 0.0, y0: float = 0.0, smooth: bool = True) -> Terrain:
        """Any height field: ``heights[i][j]`` (m above the flat floor) at (x0 + i·cell_size, y0 + j·cell_size)."""
        h = np.asarray(heights, dtype=np.float64)
        if h.ndim == 1:
            h = h[:, None]
        return cls(kind="heightmap", heights=h.tolist(), cell_size=float(cell_size), x0=float(x0), y0=float(y0),
                   smooth=bool(smooth))

    # ------------------------------------------------------------------ checks
    def validate(self, key: str = "terrain") -> None:
        require(self.kind in KINDS, f"{key}.kind", f"one of {KINDS}", self.kind)
        require(self.axis in AXES, f"{key}.axis", f"one of {AXES}", self.axis)
        if self.kind == "slope":
            require(-60 <= self.degrees <= 60, f"{key}.degrees", "in [-60, 60]", self.degrees)
        if self.kind == "rough":
            require(self.amplitude >= 0, f"{key}.amplitude", ">= 0", self.amplitude)
            require(self.wavelength > 0, f"{key}.wavelength", "> 0", self.wavelength)
        if self.kind == "steps":
            require(self.depth > 0, f"{key}.depth", "> 0", self.depth)
            require(self.gap >= 0, f"{key}.gap", ">= 0", self.gap)
        if self.kind == "heightmap":
            require(self.heights is not None and len(self.heights) > 0 and len(self.heights[0]) > 0,
                    f"{key}.heights", "a non-empty 2-D list of heights (m)", self.heights)
            require(self.cell_size > 0, f"{key}.cell_size", "> 0", self.cell_size)

    # ------------------------------------------------------------------ compiled form
    def field(self, voxel_size: float) -> HeightField:
        """The height field the kernels read (``HeightField``)."""
        L = voxel_size
        if self.kind == "flat":
            return HeightField(FLAT, -0.5 * L, 0.0, 0.0, np.zeros((2, 2)), 0.0, 0.0, 1.0)
        if self.kind == "slope":
            t = math.tan(math.radians(self.degrees))
            gx, gy = (t, 0.0) if self.axis == "x" else (0.0, t)
            return HeightField(SMOOTH, -0.5 * L, gx, gy, np.zeros((2, 2)), 0.0, 0.0, 1.0)
        if self.kind == "rough":
            cell = self.wavelength / 8
            n = int(math.ceil(ROUGH_EXTENT / cell)) + 1
            xs = -0.5 * ROUGH_EXTENT + cell * np.arange(n)
            rng = np.random.default_rng(self.seed)
            ang = rng.uniform(0, 2 * math.pi, ROUGH_WAVES)
            ph = rng.uniform(0, 2 * math.pi, ROUGH_WAVES)
            k = 2 * math.pi / self.wavelength
            X, Y = np.meshgrid(xs, xs, indexing="ij")
            h = sum(np.cos(k * (np.cos(a) * X + np.sin(a) * Y) + p) for a, p in zip(ang, ph, strict=True))
            h = self.amplitude * h / max(np.abs(h).max(), 1e-12)
            return HeightField(SMOOTH, -0.5 * L, 0.0, 0.0, h, xs[0], xs[0], cell)
        if self.kind == "steps":
            # column i covers [i·depth, (i+1)·depth) along the axis, height (i+1)·height; column 0 (all before the
            # first riser) is the flat floor, continued backwards by the clamped edge
            prof = self.height * np.arange(STEPS_COUNT + 1, dtype=np.float64)
            h = prof[:, None] if self.axis == "x" else prof[None, :]
            o = -self.depth  # column 0 starts one tread before the first riser at 0
            return HeightField(COLUMNS, -0.5 * L, 0.0, 0.0, h, o if self.axis == "x" else 0.0,
                               o if self.axis == "y" else 0.0, self.depth)
        h = np.asarray(self.heights, dtype=np.float64)
        return HeightField(SMOOTH if self.smooth else COLUMNS, -0.5 * L, 0.0, 0.0, h, self.x0, self.y0,
                           self.cell_size)


@dataclass
class HeightField:
    """S(x, y) = base + gx·x + gy·y + grid(x, y): ``mode`` FLAT | SMOOTH (bilinear grid) | COLUMNS (flat-topped
    cells). grid: float64 ``[nx, ny]`` at x0 + i·cell, y0 + j·cell (SMOOTH: the nodes; COLUMNS: the cells' low
    corners)."""

    mode: int
    base: float
    gx: float
    gy: float
    grid: np.ndarray
    x0: float
    y0: float
    cell: float

    def __post_init__(self) -> None:
        g = np.asarray(self.grid, dtype=np.float64)
        if self.mode == SMOOTH:  # bilinear interpolation needs two nodes along each axis
            g = np.repeat(g, 2, axis=0) if g.shape[0] == 1 else g
            g = np.repeat(g, 2, axis=1) if g.shape[1] == 1 else g
        self.grid = np.ascontiguousarray(g)

    @property
    def nx(self) -> int:
        return int(self.grid.shape[0])

    @property
    def ny(self) -> int:
        return int(self.grid.shape[1])

    # numpy twins of the kernel's surface functions (placement, traces, drawing)
    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """S(x, y) (m) at points ``x``, ``y`` (any equal shapes)."""
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        s = self.base + self.gx * x + self.gy * y
        if self.mode == FLAT:
            return s + 0 * x
        g = self.grid
        u, v = (x - self.x0) / self.cell, (y - self.y0) / self.cell
        if self.mode == COLUMNS:
            i = np.clip(np.floor(u), 0, self.nx - 1).astype(np.int64)
            j = np.clip(np.floor(v), 0, self.ny - 1).astype(np.int64)
            return s + g[i, j]
        i = np.clip(np.floor(u), 0, self.nx - 2).astype(np.int64)
        j = np.clip(np.floor(v), 0, self.ny - 2).astype(np.int64)
        fu, fv = np.clip(u - i, 0, 1), np.clip(v - j, 0, 1)
        return s + (g[i, j] * (1 - fu) * (1 - fv) + g[i + 1, j] * fu * (1 - fv) + g[i, j + 1] * (1 - fu) * fv
                    + g[i + 1, j + 1] * fu * fv)

    def normal_z(self, x: np.ndarray, y: np.ndarray, h: float = 1e-6) -> np.ndarray:
        """The z component of the unit upward normal (1 for FLAT and COLUMNS tops; central differences else)."""
        if self.mode != SMOOTH:
            return np.ones_like(np.asarray(x, dtype=np.float64))
        sx = (self.height(x + h, y) - self.height(x - h, y)) / (2 * h)
        sy = (self.height(x, y + h) - self.height(x, y - h)) / (2 * h)
        return 1.0 / np.sqrt(1.0 + sx * sx + sy * sy)

    def support(self, x: np.ndarray, y: np.ndarray, half: float) -> np.ndarray:
        """The least centre height at which a voxel of half-size ``half`` at (x, y) touches without penetrating."""
        if self.mode == COLUMNS:
            # the highest column under the voxel's footprint, plus the half size
            top = np.full(np.shape(x), -np.inf)
            for dx in (-half, half):
                for dy in (-half, half):
                    top = np.maximum(top, self.height(np.asarray(x) + 0.999 * dx, np.asarray(y) + 0.999 * dy))
            return top + half
        return self.height(x, y) + half / self.normal_z(x, y)

    def arrays(self) -> tuple[dict[str, float], np.ndarray]:
        """The kernel's parameters (``state.GP`` columns) and the flat grid ``[nx·ny]`` (row-major)."""
        params = {"TER_BASE": self.base, "TER_GX": self.gx, "TER_GY": self.gy, "TER_X0": self.x0,
                  "TER_Y0": self.y0, "TER_CELL": self.cell, "TER_NX": float(self.nx), "TER_NY": float(self.ny)}
        return params, self.grid.reshape(-1)


def placement(terrain: Terrain, field: HeightField, lattice: np.ndarray, voxel_robot: np.ndarray, num_robots: int,
              voxel_size: float) -> np.ndarray:
    """Each robot's offset from its lattice position (float64 ``[R, 3]``, m) so that it rests on the terrain under
    its footprint: zero on flat ground; on stairs first shifted so its front face is ``gap`` before the first riser."""
    off = np.zeros((num_robots, 3))
    if field.mode == FLAT or num_robots == 0:
        return off
    L = voxel_size
    pos = lattice.astype(np.float64) * L
    if terrain.kind == "steps":
        a = 0 if terrain.axis == "x" else 1
        front = np.full(num_robots, -np.inf)
        np.maximum.at(front, voxel_robot, pos[:, a] + 0.5 * L)
        off[:, a] = -terrain.gap - front
    p = pos + off[voxel_robot]
    need = field.support(p[:, 0], p[:, 1], 0.5 * L) - p[:, 2]
    lift = np.full(num_robots, -np.inf)
    np.maximum.at(lift, voxel_robot, need)
    off[:, 2] = lift
    return off
