"""Where each state table sits in the kernels' three buffers (``state.BUFFERS``): pure numpy, no Taichi.

A region is a table's ``[width, capacity]`` block inside its buffer, in the memory order the schedule reads best
(``access.py``): "soa" stores column c of item i at ``at + c·stride + i``, "aos" at ``at + i·width + c``. The
kernels find every region through the header (``state.HDR``, the first region of "ints"), so one compiled kernel
serves any capacities; the host packs and unpacks with the same arithmetic here. The trace is always "soa"
(``[frames, SUMMARY.width, robots]``, row-major), its width depending on the frames asked for.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from freeform.sim.state import BUFFERS, F64, GP, HDR, I32, REAL, SUMMARY, TABLES

# element type of each buffer (state.Table dtypes: REAL follows the simulation's precision)
BUFFER_DTYPE = {"reals": REAL, "ints": I32, "f64s": F64}
# what sizes each region that is not a per-item table: (width, the capacity key of its items)
VECTORS = {"hdr": (HDR.width, None), "gp": (GP.width, None), "hf": (1, "cells")}
INT32_MAX = np.iinfo(np.int32).max


def buffer_dtype(buffer: str, precision: str) -> np.dtype:
    """numpy dtype of ``buffer`` at ``precision`` ("f32" | "f64")."""
    kind = BUFFER_DTYPE[buffer]
    if kind == I32:
        return np.dtype(np.int32)
    return np.dtype(np.float64 if kind == F64 or precision == "f64" else np.float32)


@dataclass(frozen=True)
class Region:
    """One region: ``width`` columns of ``stride`` items from element ``at`` of ``buffer``."""

    name: str
    buffer: str
    at: int
    stride: int
    width: int
    aos: bool

    @property
    def size(self) -> int:
        return self.width * self.stride

    def flat(self, host: np.ndarray) -> np.ndarray:
        """The region's elements, in memory order, from host ``[width, items ≤ stride]`` (the tail is zeros)."""
        if host.ndim != 2 or host.shape[0] != self.width or host.shape[1] > self.stride:
            raise ValueError(f"region {self.name}: expected [{self.width}, ≤ {self.stride}], got {host.shape}")
        block = np.zeros((self.width, self.stride), dtype=host.dtype)
        block[:, : host.shape[1]] = host
        return (block.T if self.aos else block).ravel()

    def unflat(self, values: np.ndarray, items: int) -> np.ndarray:
        """Host ``[width, items]`` from the region's elements in memory order."""
        if self.aos:
            return values[: self.size].reshape(self.stride, self.width)[:items].T
        return values[: self.size].reshape(self.width, self.stride)[:, :items]


class Packing:
    """The regions of every buffer for the given capacities (items: ``state.ITEM_KINDS``, plus "cells" for the
    terrain's height grid) and memory ``order``, with room for a trace of ``trace_frames`` frames of
    ``trace_robots`` robots (1 × 1 while no trace is taken)."""

    def __init__(self, capacity: Mapping[str, int], order: str, trace_frames: int = 1, trace_robots: int = 1):
        self.capacity, self.order = dict(capacity), order
        self.trace_frames, self.trace_robots = trace_frames, trace_robots
        self.regions: dict[str, Region] = {}
        self.lengths: dict[str, int] = {}
        for buffer, names in BUFFERS.items():
            at = 0
            for name in names:
                if name in TABLES:
                    width, stride, aos = TABLES[name].width, self.capacity[TABLES[name].items], order == "aos"
                elif name == "tr":
                    width, stride, aos = trace_frames * SUMMARY.width, trace_robots, False
                else:
                    width, key = VECTORS[name]
                    stride, aos = (self.capacity[key] if key else 1), False
                self.regions[name] = Region(name, buffer, at, max(1, stride), width, aos)
                at += self.regions[name].size
            if at > INT32_MAX:
                raise ValueError(f"buffer {buffer!r} would hold {at} elements, more than the kernels' int32 "
                                 f"indices reach ({INT32_MAX}); simulate fewer or smaller bodies per batch")
            self.lengths[buffer] = at

    def with_trace(self, frames: int, robots: int) -> Packing:
        """The same packing with room for a trace of ``frames`` × ``robots`` (only "tr", last in "f64s", moves)."""
        return Packing(self.capacity, self.order, frames, robots)

    def header(self, counts: Mapping[str, int], trace_steps: int = 0) -> np.ndarray:
        """``HDR`` as int32 ``[HDR.width, 1]``: every region's place, the batch's counts and the trace's interval."""
        h = np.zeros((HDR.width, 1), dtype=np.int32)
        for name, region in self.regions.items():
            h[getattr(HDR, f"{name.upper()}_AT")] = region.at
            h[getattr(HDR, f"{name.upper()}_STRIDE")] = region.stride
        h[HDR.N_VOXELS], h[HDR.N_LINKS], h[HDR.N_ROBOTS] = counts["voxels"], counts["links"], counts["robots"]
        h[HDR.TRACE_STEPS], h[HDR.TRACE_FRAMES] = trace_steps, self.trace_frames
        return h

    def image(self, buffer: str, host: Mapping[str, np.ndarray], dtype: np.dtype, length: int) -> np.ndarray:
        """The whole of ``buffer`` (``length`` ≥ its packed length) with each region named in ``host``
        (``[width, items]``) in place; everything else zero."""
        out = np.zeros(max(length, self.lengths[buffer]), dtype=dtype)
        for name, values in host.items():
            region = self.regions[name]
            if region.buffer != buffer:
                raise ValueError(f"region {name!r} lives in {region.buffer!r}, not {buffer!r}")
            out[region.at: region.at + region.size] = region.flat(np.asarray(values, dtype=dtype))
        return out
