"""freeform.body against independent truth: scipy.ndimage (test-only oracle), numpy re-implementations of the spec's
formulas, and small bodies worked by hand."""

from __future__ import annotations

import zlib

import numpy as np
import pytest
import scipy.ndimage as ndi
import torch

from freeform.body import (
    METRIC_NAMES,
    _OccupiedGraph,
    bodies_and_metrics,
    bounding_box,
    component_labels,
    crop,
    largest_component,
    metrics,
    serial_on_cpu,
)

FACES = ndi.generate_binary_structure(3, 1)  # 6-connectivity


# ----------------------------------------------------------------------------------------------------- oracles
def random_grids(
    n: int, shape: tuple[int, int, int], density: float, materials: int, seed: int
) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    occupied = rng.random((n, *shape)) < density
    return torch.from_numpy((occupied * rng.integers(1, materials, (n, *shape))).astype(np.uint8))


def bundle_grids(n: int, materials: int, seed: int, rho: int = 20, steps: int = 100) -> torch.Tensor:
    """Grids built the way the design env builds them (2³ bundles from N(0, 1) actions), in plain numpy."""
    rng = np.random.default_rng(seed)
    grids = np.zeros((n, rho, rho, rho), np.uint8)
    for _ in range(steps):
        a = rng.standard_normal((n, 3 + materials)).astype(np.float32)
        f = np.float32(0.5) + np.clip(a, -2, 2) / np.float32(4)
        first = np.ceil(np.float32(rho) * f[:, :3]).astype(int) - 1
        mat = np.argmax(f[:, 3:], axis=1)
        for i in range(n):
            lo = np.maximum(first[i], 0)
            hi = np.minimum(first[i] + 2, rho)
            grids[i, lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = mat[i]
    return torch.from_numpy(grids)


def oracle_body(grid: np.ndarray) -> np.ndarray:
    labels, count = ndi.label(grid != 0, structure=FACES)
    if count == 0:
        return np.zeros_like(grid)
    sizes = np.bincount(labels.ravel())[1:]
    # scipy numbers components in raster (C) order of their first voxel, and argmax takes the first maximum:
    # together exactly the spec's tie rule.
    return np.where(labels == 1 + int(np.argmax(sizes)), grid, 0)


def oracle_metrics(grid: np.ndarray) -> dict[str, float]:
    body = oracle_body(grid)
    occupied = body != 0
    volume = int(occupied.sum())
    padded = np.pad(occupied, 1)
    inner = tuple(slice(1, -1) for _ in range(3))
    all_neighbours = np.ones_like(occupied)
    for axis in range(3):
        for shift in (-1, 1):
            all_neighbours &= np.roll(padded, shift, axis=axis)[inner]
    surface = int((occupied & ~all_neighbours).sum())
    regions = 0
    for value in np.unique(body):
        regions += ndi.label(body == value, structure=FACES)[1]
    scores = []
    for axis in range(3):
        half = body.shape[axis] // 2
        left = np.take(body, range(half), axis=axis)
        right = np.flip(np.take(body, range(body.shape[axis] - half, body.shape[axis]), axis=axis), axis=axis)
        s = np.sum((left == right) & (left != 0))
        den = np.sum(left != 0) + np.sum(right != 0)
        scores.append(2 * s / den if den else 0.0)
    nonempty = int((grid != 0).sum())
    return {
        "volume": volume,
        "surface_ratio": surface / volume if volume else 0.0,
        "passive_ratio": float((body == 1).sum()) / volume if volume else 0.0,
        "lcc_ratio": volume / nonempty if nonempty else 0.0,
        "substructures": regions,
        "symmetry": float(np.mean(scores)),
        "compressibility": len(zlib.compress(body.astype(np.uint8).tobytes())) / body.size,
    }


def assert_metrics_match(grids: torch.Tensor) -> None:
    got = metrics(grids)
    assert set(got) == set(METRIC_NAMES)
    for i, grid in enumerate(grids.numpy()):
        want = oracle_metrics(grid)
        for name in METRIC_NAMES:
            assert got[name][i].item() == pytest.approx(want[name], abs=1e-6), (i, name)


# ------------------------------------------------------------------------------------- components against scipy
@pytest.mark.parametrize(
    ("shape", "density", "seed"),
    [
        ((20, 20, 20), 0.05, 0),
        ((20, 20, 20), 0.25, 1),
        ((20, 20, 20), 0.33, 2),
        ((7, 11, 5), 0.4, 3),
        ((1, 1, 9), 0.5, 4),
    ],
)
def test_component_labels_match_scipy(shape, density, seed):
    grids = random_grids(24, shape, density, materials=4, seed=seed)
    labels = component_labels(grids).numpy()
    for i, grid in enumerate(grids.numpy()):
        want, _ = ndi.label(grid != 0, structure=FACES)
        np.testing.assert_array_equal(labels[i], want)


@pytest.mark.parametrize(("density", "seed"), [(0.03, 5), (0.2, 6), (0.31, 7), (0.6, 8)])
def test_largest_component_matches_scipy(density, seed):
    grids = random_grids(32, (20, 20, 20), density, materials=4, seed=seed)
    bodies = largest_component(grids).numpy()
    for i, grid in enumerate(grids.numpy()):
        np.testing.assert_array_equal(bodies[i], oracle_body(grid))


def test_largest_component_of_design_env_grids_matches_scipy():
    grids = bundle_grids(48, materials=4, seed=9)
    bodies = largest_component(grids).numpy()
    for i, grid in enumerate(grids.numpy()):
        np.testing.assert_array_equal(bodies[i], oracle_body(grid))


def test_largest_component_tie_goes_to_first_voxel_in_c_order():
    grid = torch.zeros(1, 6, 6, 6, dtype=torch.uint8)
    grid[0, 3, 0, 0] = 2  # first component in C order (x slowest): x = 3
    grid[0, 3, 0, 1] = 2
    grid[0, 0, 5, 4] = 1  # ... but this one, at x = 0, comes first
    grid[0, 0, 5, 5] = 3
    body = largest_component(grid)
    assert body[0, 0, 5, 4] == 1 and body[0, 0, 5, 5] == 3
    assert int((body != 0).sum()) == 2
    # A larger component wins regardless of order.
    grid[0, 3, 0, 2] = 1
    body = largest_component(grid)
    assert body[0, 3].sum() == 5 and int((body != 0).sum()) == 3


def test_components_are_six_connected_not_edge_or_corner_connected():
    grid = torch.zeros(1, 4, 4, 4, dtype=torch.uint8)
    grid[0, 0, 0, 0] = 1
    grid[0, 1, 1, 0] = 1  # shares an edge only
    grid[0, 2, 2, 1] = 1  # shares a corner only with the previous
    labels = component_labels(grid)
    assert sorted(labels[labels > 0].tolist()) == [1, 2, 3]


def snake(rho: int) -> torch.Tensor:
    """A single 6-connected path through a ρ³ grid that visits half its rows: the worst case for label
    propagation (its length is ~ρ³/4 voxels, and its node ids run back and forth)."""
    grid = np.zeros((rho, rho, rho), np.uint8)
    rows = [
        (x, y)
        for x in range(0, rho, 2)
        for y in (range(0, rho, 2) if (x // 2) % 2 == 0 else range(rho - 2, -1, -2))
    ]
    for i, (x, y) in enumerate(rows):
        grid[x, y, :] = 1 + i % 3
        z = rho - 1 if i % 2 == 0 else 0  # join this row to the next at alternating ends
        if i + 1 < len(rows):
            nx, ny = rows[i + 1]
            grid[min(x, nx) : max(x, nx) + 1, min(y, ny) : max(y, ny) + 1, z] = 1
    return torch.from_numpy(grid)[None]


def test_snake_is_one_component_found_in_few_rounds():
    grid = snake(20)
    assert ndi.label(grid[0].numpy() != 0, structure=FACES)[1] == 1
    body = largest_component(grid)
    assert torch.equal(body, grid)
    # Plain min-label propagation would need a round per voxel of the path (~2,100); hooking with pointer jumping
    # needs a handful.
    assert _OccupiedGraph(grid).rounds <= 12
    # Cut the path in the middle: two components, and the larger half survives.
    cut = grid.clone()
    rows = (cut[0] != 0).nonzero()
    cut[0, 10, :, :] = 0
    labels = component_labels(cut)[0].numpy()
    np.testing.assert_array_equal(labels, ndi.label(cut[0].numpy() != 0, structure=FACES)[0])
    np.testing.assert_array_equal(largest_component(cut)[0].numpy(), oracle_body(cut[0].numpy()))
    assert len(rows) > 1000


def test_results_do_not_depend_on_batch_size_or_position():
    grids = random_grids(13, (20, 20, 20), 0.3, materials=4, seed=10)
    together = largest_component(grids)
    together_metrics = metrics(grids)
    for i in (0, 5, 12):
        alone = largest_component(grids[i : i + 1])
        assert torch.equal(alone[0], together[i])
        alone_metrics = metrics(grids[i : i + 1])
        for name in METRIC_NAMES:
            assert alone_metrics[name][0].item() == together_metrics[name][i].item()
    # Permuting the batch permutes the results.
    perm = torch.randperm(13, generator=torch.Generator().manual_seed(0))
    assert torch.equal(largest_component(grids[perm]), together[perm])


def test_empty_and_zero_batches():
    empty = torch.zeros(3, 5, 5, 5, dtype=torch.uint8)
    assert int(largest_component(empty).sum()) == 0
    assert int(component_labels(empty).sum()) == 0
    got = metrics(empty)
    for name in ("volume", "surface_ratio", "passive_ratio", "lcc_ratio", "symmetry"):
        assert got[name].tolist() == [0.0, 0.0, 0.0], name
    assert got["substructures"].tolist() == [1.0, 1.0, 1.0]  # the empty grid is one region
    want = len(zlib.compress(bytes(125))) / 125
    assert got["compressibility"].tolist() == pytest.approx([want] * 3)
    for value in got.values():
        assert not torch.isnan(value).any()
    none = torch.zeros(0, 4, 4, 4, dtype=torch.uint8)
    assert largest_component(none).shape == (0, 4, 4, 4)
    assert all(v.shape == (0,) for v in metrics(none).values())


# ---------------------------------------------------------------------------------------- metrics against truth
@pytest.mark.parametrize(("density", "seed"), [(0.1, 11), (0.3, 12), (0.5, 13)])
def test_metrics_match_numpy_oracle_on_random_grids(density, seed):
    assert_metrics_match(random_grids(16, (20, 20, 20), density, materials=4, seed=seed))


def test_metrics_match_numpy_oracle_on_design_env_grids():
    assert_metrics_match(bundle_grids(24, materials=4, seed=14))
    assert_metrics_match(bundle_grids(8, materials=2, seed=15))


def test_metrics_on_odd_and_non_cubic_grids():
    assert_metrics_match(random_grids(8, (9, 6, 7), 0.45, materials=3, seed=16))


def test_hollow_cube_by_hand():
    """An 8³ passive cube with a 2³ cavity, centred in a 10³ grid."""
    grid = torch.zeros(1, 10, 10, 10, dtype=torch.uint8)
    grid[0, 1:9, 1:9, 1:9] = 1
    grid[0, 4:6, 4:6, 4:6] = 0
    m = metrics(grid)
    assert m["volume"].item() == 8**3 - 2**3
    # Outer shell 8³ - 6³ = 296 voxels, plus the 6 faces × 4 voxels lining the cavity.
    assert m["surface_ratio"].item() == pytest.approx((296 + 24) / 504)
    assert m["passive_ratio"].item() == 1.0
    assert m["lcc_ratio"].item() == 1.0
    assert m["substructures"].item() == 3  # the material, the outside, the cavity
    assert m["symmetry"].item() == pytest.approx(1.0)
    # The cavity counts even when the body touches the grid's border.
    grid = torch.zeros(1, 5, 5, 5, dtype=torch.uint8)
    grid[0, 0:3, 0:3, 0:3] = 2
    grid[0, 1, 1, 1] = 0
    assert metrics(grid)["substructures"].item() == 3
    assert metrics(grid)["surface_ratio"].item() == pytest.approx(26 / 26)


def test_substructures_by_hand():
    grid = torch.zeros(1, 6, 6, 6, dtype=torch.uint8)
    grid[0, 2, 2, 0:5] = torch.tensor([1, 1, 2, 2, 1], dtype=torch.uint8)
    assert metrics(grid)["substructures"].item() == 3 + 1  # three material runs, one empty region
    grid[0, 3, 2, 2:4] = 2  # joins the 2-run; still 3 material regions
    assert metrics(grid)["substructures"].item() == 4
    # A wall across the whole grid splits the empty space in two (counted within the grid, as cc3d does).
    wall = torch.zeros(1, 6, 6, 6, dtype=torch.uint8)
    wall[0, 3] = 1
    assert metrics(wall)["substructures"].item() == 3
    wall[0, 0, 0, 0] = 1  # a disconnected voxel is not part of the body
    assert metrics(wall)["substructures"].item() == 3
    assert metrics(wall)["lcc_ratio"].item() == pytest.approx(36 / 37)


def test_symmetry_by_hand():
    grid = torch.zeros(1, 6, 6, 6, dtype=torch.uint8)
    grid[0, 1:5, 2:4, 0:6] = 1  # mirror-symmetric about all three centre planes
    assert metrics(grid)["symmetry"].item() == pytest.approx(1.0)
    grid[0, 1, 2, 0] = 2  # one voxel changes material: it no longer matches its mirror image on x and z
    # x: L has 24 voxels, 23 match; R 24 -> 2·23/48. y: the change is mirrored across y? no: (1,2,0) <-> (1,3,0)
    # differs too -> 2·23/48. z: (1,2,0) <-> (1,2,5) differs -> 2·23/48.
    assert metrics(grid)["symmetry"].item() == pytest.approx(46 / 48)
    single = torch.zeros(1, 6, 6, 6, dtype=torch.uint8)
    single[0, 0, 0, 0] = 1  # one voxel at a corner: nothing mirrors it
    assert metrics(single)["symmetry"].item() == 0.0
    centre = torch.zeros(1, 5, 5, 5, dtype=torch.uint8)
    centre[0, 2, 2, 2] = 1  # on the middle slice of an odd grid: in neither half
    assert metrics(centre)["symmetry"].item() == 0.0


def test_compressibility_is_zlib_of_the_body_grid():
    grids = bundle_grids(4, materials=4, seed=17)
    bodies = largest_component(grids).numpy()
    got = metrics(grids)["compressibility"]
    for i in range(4):
        assert got[i].item() == pytest.approx(len(zlib.compress(bodies[i].tobytes())) / 8000)


def test_bodies_and_metrics_agree_with_the_separate_functions():
    grids = random_grids(6, (10, 10, 10), 0.3, materials=4, seed=18)
    bodies, m = bodies_and_metrics(grids)
    assert torch.equal(bodies, largest_component(grids))
    for name, value in metrics(grids).items():
        assert torch.equal(m[name], value)


# ----------------------------------------------------------------------------------------- bounding box, crop
def test_bounding_box_and_crop():
    grid = torch.zeros(2, 8, 9, 10, dtype=torch.uint8)
    grid[0, 2, 3, 4] = 1
    grid[0, 5, 3, 9] = 3
    lo, hi = bounding_box(grid)
    assert lo.tolist() == [[2, 3, 4], [0, 0, 0]]
    assert hi.tolist() == [[6, 4, 10], [0, 0, 0]]
    cropped = crop(grid[0])
    assert cropped.shape == (4, 1, 6)
    assert cropped[0, 0, 0] == 1 and cropped[3, 0, 5] == 3 and int((cropped != 0).sum()) == 2
    assert crop(grid[1]).shape == (0, 0, 0)


def test_bounding_box_matches_numpy():
    grids = random_grids(20, (12, 12, 12), 0.004, materials=3, seed=19)
    lo, hi = bounding_box(grids)
    for i, grid in enumerate(grids.numpy()):
        idx = np.argwhere(grid != 0)
        if len(idx) == 0:
            assert lo[i].tolist() == hi[i].tolist() == [0, 0, 0]
            continue
        assert lo[i].tolist() == idx.min(0).tolist()
        assert hi[i].tolist() == (idx.max(0) + 1).tolist()
        assert int((crop(grids[i]) != 0).sum()) == len(idx)


# --------------------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "bad",
    [
        torch.zeros(2, 4, 4, 4, dtype=torch.int64),
        torch.zeros(4, 4, 4, dtype=torch.uint8),
        torch.zeros(1, 2, 4, 4, 4, dtype=torch.uint8),
        np.zeros((1, 4, 4, 4), np.uint8),
    ],
)
def test_bad_grids_raise(bad):
    for fn in (largest_component, component_labels, metrics, bounding_box):
        with pytest.raises(ValueError, match="grids"):
            fn(bad)


def test_material_index_out_of_range_raises():
    grid = torch.zeros(1, 4, 4, 4, dtype=torch.uint8)
    grid[0, 0, 0, 0] = 2
    with pytest.raises(ValueError, match="materials=2"):
        metrics(grid, materials=2)
    with pytest.raises(ValueError, match="materials"):
        metrics(grid, materials=1)
    metrics(grid, materials=3)
    with pytest.raises(ValueError, match="grid"):
        crop(grid)


def test_serial_on_cpu_restores_the_thread_count():
    before = torch.get_num_threads()
    with serial_on_cpu("cpu"):
        assert torch.get_num_threads() == 1
        largest_component(torch.zeros(1, 2, 2, 2, dtype=torch.uint8))  # nested use keeps it at 1
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with pytest.raises(RuntimeError), serial_on_cpu("cpu"):
        raise RuntimeError
    assert torch.get_num_threads() == before


def test_diversity_is_scipys_hamming_distance_of_the_bodies_moved_to_the_corner() -> None:
    """Truth: scipy's pdist on the bodies cropped by hand to the corner; a body placed elsewhere in its grid counts
    once; a set of one body repeated has distance 0 and one distinct body."""
    from scipy.spatial.distance import pdist

    from freeform.body import diversity

    rng = np.random.default_rng(3)
    grids = np.zeros((6, 5, 5, 5), dtype=np.uint8)
    for i in range(5):
        size = rng.integers(1, 4, 3)
        grids[i, 1: 1 + size[0], 2: 2 + size[1], : size[2]] = rng.integers(0, 4, tuple(size))
        grids[i, 1, 2, 0] = 2  # (the bounding box's corner is filled)
    grids[5] = np.roll(grids[4], (1, -1, 2), axis=(0, 1, 2))  # body 4 elsewhere in its grid
    corner = np.zeros_like(grids)
    for i, g in enumerate(grids):
        nz = np.argwhere(g)
        lo, hi = nz.min(0), nz.max(0) + 1
        box = g[lo[0]: hi[0], lo[1]: hi[1], lo[2]: hi[2]]
        corner[i, : box.shape[0], : box.shape[1], : box.shape[2]] = box
    d = diversity(torch.from_numpy(grids))
    assert abs(d["distance"] - pdist(corner.reshape(6, -1), "hamming").mean()) < 1e-12
    assert d["distinct"] == 5
    same = diversity(torch.from_numpy(np.repeat(grids[:1], 4, 0)))
    assert same == {"distance": 0.0, "distinct": 1}
    with pytest.raises(ValueError, match="at least 2 designs"):
        diversity(torch.from_numpy(grids[:1]))
