"""The kernels' three buffers: where each table sits (packing.py, pure numpy) and that the engine's region reads and
writes move exactly one table (through the device)."""

from __future__ import annotations

import numpy as np
import pytest

from freeform.sim import SimConfig, Simulator
from freeform.sim.packing import Packing, buffer_dtype
from freeform.sim.state import BUFFERS, HDR, SUMMARY, TABLES, VR

CAPACITY = {"voxels": 37, "links": 90, "robots": 5, "materials": 4, "material_pairs": 16, "cells": 12}


@pytest.mark.parametrize("order", ["soa", "aos"])
def test_regions_tile_each_buffer_without_overlap(order):
    p = Packing(CAPACITY, order, trace_frames=3, trace_robots=5)
    for buffer, names in BUFFERS.items():
        spans = sorted((p.regions[n].at, p.regions[n].at + p.regions[n].size) for n in names)
        assert spans[0][0] == 0 and spans[-1][1] == p.lengths[buffer]
        assert all(a[1] == b[0] for a, b in zip(spans, spans[1:], strict=False)), spans  # back to back: no gap, no overlap
    for name, table in TABLES.items():
        assert p.regions[name].size == table.width * CAPACITY[table.items]
    assert p.regions["tr"].size == 3 * SUMMARY.width * 5
    assert p.regions["hdr"].at == 0  # the kernels find everything else through it


@pytest.mark.parametrize("order", ["soa", "aos"])
def test_an_element_sits_where_the_memory_order_says(order):
    """Column c of item i: numpy's own C-order index of [c, i] in a [width, stride] block (soa) or of [i, c] in a
    [stride, width] block (aos), offset by the region's start."""
    p = Packing(CAPACITY, order)
    rng = np.random.default_rng(0)
    for name in ("vr", "li", "rt"):
        region, table = p.regions[name], TABLES[name]
        items = CAPACITY[table.items] - 2
        host = rng.random((table.width, items))
        image = p.image(region.buffer, {name: host}, np.dtype(np.float64), p.lengths[region.buffer])
        for c, i in ((0, 0), (table.width - 1, items - 1), (1, items // 2)):
            if order == "soa":
                k = np.ravel_multi_index((c, i), (table.width, region.stride))
            else:
                k = np.ravel_multi_index((i, c), (region.stride, table.width))
            assert image[region.at + k] == host[c, i]
        np.testing.assert_array_equal(region.unflat(image[region.at:], items), host)


def test_header_names_every_region_and_the_counts():
    p = Packing(CAPACITY, "aos", trace_frames=4, trace_robots=5)
    counts = {"voxels": 30, "links": 70, "robots": 4}
    h = p.header(counts, trace_steps=7)[:, 0]
    for name, region in p.regions.items():
        assert h[getattr(HDR, f"{name.upper()}_AT")] == region.at
        assert h[getattr(HDR, f"{name.upper()}_STRIDE")] == region.stride
    assert (h[HDR.N_VOXELS], h[HDR.N_LINKS], h[HDR.N_ROBOTS]) == (30, 70, 4)
    assert (h[HDR.TRACE_STEPS], h[HDR.TRACE_FRAMES]) == (7, 4)


def test_room_for_a_trace_moves_nothing_but_the_trace():
    p = Packing(CAPACITY, "soa")
    q = p.with_trace(frames=9, robots=5)
    assert all(q.regions[n] == p.regions[n] for n in p.regions if n != "tr")
    assert q.lengths["f64s"] > p.lengths["f64s"] and q.regions["tr"].at == p.regions["tr"].at


def test_a_batch_beyond_int32_indices_is_refused_with_the_reason():
    with pytest.raises(ValueError, match="int32"):
        Packing({**CAPACITY, "links": 2**27}, "soa")


def test_bad_region_shapes_are_refused():
    p = Packing(CAPACITY, "soa")
    with pytest.raises(ValueError, match="region vr"):
        p.regions["vr"].flat(np.zeros((VR.width, CAPACITY["voxels"] + 1)))
    with pytest.raises(ValueError, match="lives in"):
        p.image("ints", {"vr": np.zeros((VR.width, 1))}, np.dtype(np.int32), p.lengths["ints"])


def test_buffer_dtypes_follow_the_precision_for_reals_only():
    assert buffer_dtype("reals", "f32") == np.float32 and buffer_dtype("reals", "f64") == np.float64
    assert buffer_dtype("f64s", "f32") == np.float64 and buffer_dtype("ints", "f32") == np.int32


@pytest.mark.parametrize("schedule", ["robots", "flat"])
def test_engine_writes_and_reads_one_region_without_touching_its_neighbours(schedule):
    """A region written through the device (staging array + copy kernel) reads back to the bit, and every other
    region of the same buffer is as it was."""
    g = np.zeros((3, 3, 2, 2), np.uint8)
    g[:, :, :, 0] = 1
    g[1, 0, 0, 1] = 3
    sim = Simulator(SimConfig(burn_in=0.0, duration=0.01), arch="cpu", schedule=schedule)
    eng = sim.engine(sim.layout(g))
    before = {name: eng._table(name).copy() for name in ("vi", "li", "ri")}
    vr = np.random.default_rng(1).random(eng._table("vr").shape).astype(eng.np_real)
    eng._upload("vr", vr)
    np.testing.assert_array_equal(eng._table("vr"), vr)
    ri = before["ri"].copy()
    ri[0] += 5  # a region of the int buffer, after the header and the voxel and link ints
    eng._upload("ri", ri)
    np.testing.assert_array_equal(eng._table("ri"), ri)
    for name in ("vi", "li"):
        np.testing.assert_array_equal(eng._table(name), before[name])
