"""freeform.io: VXD round trips and layer order, the VXA's settings, watertight meshes with the right face count
and volume, STL/OBJ/.vox parsed back (the .vox also from hand-built bytes), and .history parsed back into the
recorded poses."""

from __future__ import annotations

import struct
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import torch

from freeform.body import largest_component
from freeform.io import (
    export_body,
    history_string,
    read_history,
    read_stl,
    read_vox,
    read_vxd,
    voxel_mesh,
    vxa_string,
    vxd_string,
    write_history,
    write_obj,
    write_stl,
    write_vox,
    write_vxa,
    write_vxd,
)
from freeform.sim import Recording, SimConfig


def random_grid(seed: int, shape=(7, 6, 5), fill: float = 0.35) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return ((rng.random(shape) < fill) * rng.integers(1, 4, shape)).astype(np.uint8)


def edge_counts(faces: np.ndarray) -> np.ndarray:
    """How many triangles use each undirected edge."""
    edges = np.sort(np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1), axis=-1).reshape(-1, 2)
    return np.unique(edges, axis=0, return_counts=True)[1]


def directed_edges_unique(faces: np.ndarray) -> bool:
    """Consistent orientation: each directed edge appears once (its twin runs the other way)."""
    directed = np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2)
    return len(np.unique(directed, axis=0)) == len(directed)


# ------------------------------------------------------------------------------------------------ VXD / VXA


def test_vxd_round_trip_gives_the_same_grid(tmp_path) -> None:
    for seed in range(3):
        grid = random_grid(seed)
        path = write_vxd(tmp_path / f"b{seed}.vxd", grid, crop=False)
        np.testing.assert_array_equal(read_vxd(path), grid)


def test_vxd_crops_to_the_bounding_box(tmp_path) -> None:
    grid = np.zeros((6, 6, 6), dtype=np.uint8)
    grid[2, 3, 1] = 1
    grid[4, 3, 2] = 3
    path = write_vxd(tmp_path / "b.vxd", torch.from_numpy(grid))  # torch input is accepted too
    np.testing.assert_array_equal(read_vxd(path), grid[2:5, 3:4, 1:3])


def test_vxd_layers_are_x_fastest_then_y_one_per_z_with_phase_offsets() -> None:
    grid = np.zeros((2, 2, 2), dtype=np.uint8)
    grid[1, 0, 0] = 3  # muscle B (phase 0.5 cycles)
    grid[0, 1, 1] = 2  # muscle A (phase 0)
    grid[1, 1, 1] = 1
    root = ET.fromstring(vxd_string(grid, crop=False))
    structure = root.find("Structure")
    assert structure.get("replace") == "VXA.VXC.Structure"
    assert structure.get("Compression") == "ASCII_READABLE"
    assert [structure.findtext(t) for t in ("X_Voxels", "Y_Voxels", "Z_Voxels")] == ["2", "2", "2"]
    # cells (x, y) in the order (0,0), (1,0), (0,1), (1,1)
    assert [layer.text for layer in structure.findall("Data/Layer")] == ["0300", "0021"]
    phases = [[float(v) for v in layer.text.split(",")] for layer in structure.findall("PhaseOffset/Layer")]
    assert phases == [[0, 0.5, 0, 0], [0, 0, 0, 0]]


def test_vxd_rejects_empty_bodies_and_unknown_materials() -> None:
    with pytest.raises(ValueError, match="empty"):
        vxd_string(np.zeros((3, 3, 3), np.uint8))
    with pytest.raises(ValueError, match="materials 1..3"):
        vxd_string(np.full((1, 1, 1), 4, np.uint8))
    with pytest.raises(ValueError, match="body"):
        vxd_string(np.zeros((3, 3), np.uint8))


def test_vxa_carries_the_simulation_settings(tmp_path) -> None:
    path = write_vxa(tmp_path / "base.vxa", SimConfig())
    root = ET.parse(path).getroot()
    assert root.tag == "VXA"
    assert float(root.findtext("VXC/Lattice/Lattice_Dim")) == pytest.approx(0.01)
    materials = root.findall("VXC/Palette/Material")
    assert [m.get("ID") for m in materials] == ["1", "2", "3"]
    assert [float(m.findtext("Mechanical/CTE")) for m in materials] == [0, 0.01, 0.01]
    assert [float(m.findtext("Mechanical/MaterialTempPhase")) for m in materials] == [0, 0, 0.5]
    assert [float(m.findtext("Mechanical/Elastic_Mod")) for m in materials] == [1e5] * 3
    assert float(materials[0].findtext("Mechanical/Poissons_Ratio")) == pytest.approx(0.35)
    assert float(root.findtext("Environment/Thermal/TempPeriod")) == pytest.approx(0.25)
    assert float(root.findtext("Environment/Thermal/TempAmplitude")) == pytest.approx(10)
    assert float(root.findtext("Environment/Gravity/GravAcc")) == pytest.approx(-9.81)
    assert root.findtext("Environment/Gravity/FloorEnabled") == "1"
    assert float(root.findtext("Simulator/Damping/SlowDampingZ")) == pytest.approx(0.03)
    assert float(root.findtext("Simulator/StopCondition/StopConditionFormula/mtSUB/mtCONST")) == pytest.approx(10)
    # a VXA's own (placeholder) structure reads like a VXD's
    assert read_vxd(path).shape == (1, 1, 1)
    assert "semantics=voxelyze" in vxa_string(SimConfig())


# ------------------------------------------------------------------------------------------------ meshes


def test_hollow_cube_mesh_is_watertight_with_the_right_faces_and_volume() -> None:
    """4³ cube with a 2³ cavity: 6·16 outer + 6·4 cavity faces = 120 squares = 240 triangles, volume 64 − 8,
    and two closed surfaces (outside and cavity wall): Euler characteristic V − E + F = 2 + 2."""
    grid = np.ones((4, 4, 4), dtype=np.uint8)
    grid[1:3, 1:3, 1:3] = 0
    mesh = voxel_mesh(grid, voxel_size=0.01)
    assert mesh.faces.shape == (240, 3)
    counts = edge_counts(mesh.faces)
    assert np.all(counts == 2)
    assert directed_edges_unique(mesh.faces)
    assert mesh.signed_volume() == pytest.approx(56 * 0.01**3, rel=1e-12)
    n_vertices = len(np.unique(mesh.faces))
    assert n_vertices == len(mesh.vertices)  # welded: no unused or duplicated vertices
    assert n_vertices - len(counts) + len(mesh.faces) == 4
    # the cavity's walls face into the cavity: their normals point towards the cube's centre
    v = mesh.vertices[mesh.faces] / 0.01
    centroid = v.mean(axis=1)
    normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    inner = np.all((centroid >= 1) & (centroid <= 3), axis=1)
    assert inner.sum() == 48
    assert np.all(np.einsum("ti,ti->t", normal[inner], 2.0 - centroid[inner]) > 0)
    assert np.all(np.einsum("ti,ti->t", normal[~inner], centroid[~inner] - 2.0) > 0)


def test_voxels_touching_along_an_edge_still_give_a_two_faces_per_edge_mesh() -> None:
    grid = np.zeros((2, 2, 1), dtype=np.uint8)
    grid[0, 0, 0] = 1
    grid[1, 1, 0] = 2  # shares only the vertical edge x = y = 1 with the first voxel
    mesh = voxel_mesh(grid)
    assert np.all(edge_counts(mesh.faces) == 2)
    assert directed_edges_unique(mesh.faces)
    assert mesh.signed_volume() == pytest.approx(2.0)
    assert set(mesh.materials.tolist()) == {1, 2}


def test_random_bodies_are_watertight_and_enclose_their_voxel_count() -> None:
    for seed in range(4):
        body = largest_component(torch.from_numpy(random_grid(seed, (8, 8, 8), 0.45))[None])[0].numpy()
        mesh = voxel_mesh(body)
        assert np.all(edge_counts(mesh.faces) == 2)
        assert directed_edges_unique(mesh.faces)
        assert mesh.signed_volume() == pytest.approx(float((body > 0).sum()))
        # surface area = exposed unit faces, counted the slow way
        exposed = 0
        for x, y, z in np.argwhere(body > 0):
            for d in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)):
                n = (x + d[0], y + d[1], z + d[2])
                inside = all(0 <= n[i] < body.shape[i] for i in range(3))
                exposed += not (inside and body[n] > 0)
        v = mesh.vertices[mesh.faces]
        area = np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum() / 2
        assert area == pytest.approx(exposed)


def test_stl_and_obj_parse_back(tmp_path) -> None:
    grid = np.ones((2, 3, 1), dtype=np.uint8)
    grid[0, 0, 0] = 3
    mesh = voxel_mesh(grid, 0.01)
    tris = read_stl(write_stl(tmp_path / "b.stl", grid, 0.01))
    assert tris.shape == (len(mesh.faces), 3, 3)
    volume = np.einsum("ti,ti->t", tris[:, 0].astype(float), np.cross(tris[:, 1], tris[:, 2])).sum() / 6
    assert volume == pytest.approx(6 * 0.01**3, rel=1e-5)
    data = (tmp_path / "b.stl").read_bytes()
    assert len(data) == 84 + 50 * len(mesh.faces)

    obj = write_obj(tmp_path / "b.obj", grid, 0.01)
    verts, faces = [], []
    for line in obj.read_text().splitlines():
        if line.startswith("v "):
            verts.append([float(v) for v in line.split()[1:]])
        elif line.startswith("f "):
            faces.append([int(v) - 1 for v in line.split()[1:]])
    verts_a, faces_a = np.array(verts), np.array(faces)
    assert faces_a.shape == mesh.faces.shape and np.all(edge_counts(faces_a) == 2)
    t = verts_a[faces_a]
    assert np.einsum("ti,ti->t", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6 == pytest.approx(6e-6)
    mtl = (tmp_path / "b.mtl").read_text()
    assert "newmtl Passive" in mtl and "newmtl MuscleB" in mtl and "Kd 0.1300 0.4200 0.9300" in mtl


STL_RECORD = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])


def stl_facets(path) -> tuple[np.ndarray, np.ndarray]:
    """The stored facet normals ``[T, 3]`` and triangles ``[T, 3, 3]`` of a binary STL, read from the bytes (read_stl
    drops the normals, so it cannot be the one to check them)."""
    data = path.read_bytes()
    (n,) = struct.unpack_from("<I", data, 80)
    assert len(data) == 84 + STL_RECORD.itemsize * n
    record = np.frombuffer(data, dtype=STL_RECORD, count=n, offset=84)
    return record["normal"].astype(np.float64), record["v"].astype(np.float64)


def stl_bodies() -> list[np.ndarray]:
    """A hollow cube (its cavity walls face inwards), two voxels touching only along an edge (the fanned, pinched
    faces), and random bodies."""
    hollow = np.ones((4, 4, 4), dtype=np.uint8)
    hollow[1:3, 1:3, 1:3] = 0
    pinched = np.zeros((2, 2, 1), dtype=np.uint8)
    pinched[0, 0, 0], pinched[1, 1, 0] = 1, 2
    randoms = [largest_component(torch.from_numpy(random_grid(s, (7, 7, 7), 0.45))[None])[0].numpy() for s in (0, 1)]
    return [hollow, pinched, *randoms]


def test_stl_facet_normals_are_unit_and_follow_the_right_hand_winding(tmp_path) -> None:
    for i, body in enumerate(stl_bodies()):
        normal, v = stl_facets(write_stl(tmp_path / f"b{i}.stl", body, 0.01))
        np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-6)
        winding = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        winding /= np.linalg.norm(winding, axis=1, keepdims=True)
        assert np.all(np.einsum("ti,ti->t", normal, winding) > 1 - 1e-6)


def test_stl_facet_normals_point_out_of_the_solid(tmp_path) -> None:
    """A quarter voxel along the stored normal from a facet's centroid is empty space (or off the grid), a quarter
    voxel against it is a voxel of the body; and the divergence theorem with the stored normals,
    V = Σ area · (centroid · n) / 3, gives the voxel count."""
    L = 0.01
    for i, body in enumerate(stl_bodies()):
        normal, v = stl_facets(write_stl(tmp_path / f"b{i}.stl", body, L))
        centroid = v.mean(axis=1) / L  # voxel units: voxel (i, j, k) fills [i, i+1]×[j, j+1]×[k, k+1]
        padded = np.pad(body > 0, 1)  # off the grid is empty; indices shift by one
        outside = np.floor(centroid + 0.25 * normal).astype(np.int64) + 1
        inside = np.floor(centroid - 0.25 * normal).astype(np.int64) + 1
        assert not padded[tuple(outside.T)].any()
        assert padded[tuple(inside.T)].all()
        area = np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1) / 2
        volume = float(np.sum(area * np.einsum("ti,ti->t", v.mean(axis=1), normal)) / 3)
        assert volume == pytest.approx(float((body > 0).sum()) * L**3, rel=1e-5)


def test_stl_reads_in_trimesh_as_a_closed_volume_with_its_stored_normals(tmp_path) -> None:
    """trimesh as an independent reader: its STL parser's normals equal those it computes from the winding, and
    the welded triangles are a watertight, consistently wound mesh of positive volume (outward winding)."""
    trimesh = pytest.importorskip("trimesh")
    from trimesh.exchange.stl import load_stl

    L = 0.01
    for i, body in enumerate(stl_bodies()):
        with write_stl(tmp_path / f"b{i}.stl", body, L).open("rb") as f:
            parsed = load_stl(f)
        mesh = trimesh.Trimesh(vertices=parsed["vertices"], faces=parsed["faces"], process=True)
        assert len(mesh.faces) == len(parsed["faces"])
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.is_volume
        assert mesh.volume == pytest.approx(float((body > 0).sum()) * L**3, rel=1e-5)
        np.testing.assert_allclose(parsed["face_normals"], mesh.face_normals, atol=1e-6)


# ------------------------------------------------------------------------------------------------ .vox


def test_vox_round_trip_and_palette(tmp_path) -> None:
    grid = random_grid(5, (5, 4, 3))
    path = write_vox(tmp_path / "b.vox", grid)
    data = path.read_bytes()
    assert data[:4] == b"VOX " and struct.unpack_from("<i", data, 4)[0] == 150 and data[8:12] == b"MAIN"
    back, palette = read_vox(path)
    np.testing.assert_array_equal(back, grid)
    assert tuple(palette[0]) == (33, 107, 237, 255)  # colour index 1 = passive blue (0.13, 0.42, 0.93)
    assert tuple(palette[2, :3]) == (227, 41, 33)  # colour index 3 = muscle B red


def test_read_vox_parses_a_hand_built_file(tmp_path) -> None:
    """Bytes laid out by hand from the MagicaVoxel 150 spec (with an unknown chunk to skip)."""
    size = b"SIZE" + struct.pack("<ii", 12, 0) + struct.pack("<iii", 3, 2, 4)
    xyzi = b"XYZI" + struct.pack("<ii", 12, 0) + struct.pack("<i", 2) + bytes([0, 1, 3, 7, 2, 0, 0, 1])
    other = b"nTRN" + struct.pack("<ii", 4, 0) + b"\x00" * 4
    main = b"MAIN" + struct.pack("<ii", 0, len(size + xyzi + other)) + size + xyzi + other
    (tmp_path / "h.vox").write_bytes(b"VOX " + struct.pack("<i", 150) + main)
    grid, _ = read_vox(tmp_path / "h.vox")
    expected = np.zeros((3, 2, 4), np.uint8)
    expected[0, 1, 3] = 7
    expected[2, 0, 0] = 1
    np.testing.assert_array_equal(grid, expected)
    (tmp_path / "bad.vox").write_bytes(b"NOPE")
    with pytest.raises(ValueError, match="MagicaVoxel"):
        read_vox(tmp_path / "bad.vox")


# ------------------------------------------------------------------------------------------------ .history


def random_rotation_quats(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    q = rng.normal(size=shape + (4,))
    return (q / np.linalg.norm(q, axis=-1, keepdims=True)).astype(np.float32)


def test_history_parses_back_into_the_recorded_poses(tmp_path) -> None:
    rng = np.random.default_rng(1)
    lattice = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 1]])
    frames = 5
    positions = (lattice * 0.01 + rng.normal(scale=2e-3, size=(frames, 4, 3))).astype(np.float32)
    orientations = random_rotation_quats(rng, (frames, 4))
    orientations[0] = [1, 0, 0, 0]  # the identity, whose axis is arbitrary
    rec = Recording(times=np.linspace(0, 0.4, frames), voxel_size=0.01,
                    lattice=[np.zeros((0, 3), int), lattice], materials=[np.zeros(0, np.uint8),
                                                                         np.array([1, 2, 3, 3], np.uint8)],
                    positions=[np.zeros((frames, 0, 3), np.float32), positions],
                    orientations=[np.zeros((frames, 0, 4), np.float32), orientations])
    path = write_history(tmp_path / "r.history", rec, robot=1)
    history = read_history(path)
    np.testing.assert_allclose(history.times, rec.times, atol=1e-6)
    np.testing.assert_allclose(history.positions, positions, atol=1e-7)  # 4 decimals of mm
    # q and −q are one rotation: compare up to sign
    dots = np.abs(np.einsum("fni,fni->fn", history.orientations, orientations.astype(float)))
    np.testing.assert_allclose(dots, 1.0, atol=1e-6)
    np.testing.assert_array_equal(history.materials, [1, 2, 3, 3])
    assert history.voxel_size == pytest.approx(0.01)
    assert set(history.colors) == {1, 2, 3}

    # the exact layout voxcraft-viz reads: 15 fields per voxel, ';' separated, line closed by ';<<<>>>'
    text = path.read_text().splitlines()
    assert text[0] == "{{{setting}}}<rescale>0.001</rescale>"
    steps = [line for line in text if line.startswith("<<<Step")]
    assert len(steps) == frames and all(line.endswith(";<<<>>>") for line in steps)
    first = steps[0][steps[0].index(">>>") + 3:-len("<<<>>>")].split(";")[:-1]
    assert len(first) == 4 and all(len(r.split(",")) == 16 for r in first)  # 15 values and the trailing comma
    x, y, z, angle, ax, ay, az, *corners = (float(v) for v in first[0].split(",")[:13])
    assert (angle, ax, ay, az) == (0.0, 1.0, 0.0, 0.0)
    assert corners == [-5, -5, -5, 5, 5, 5]  # ± half a voxel, in mm

    with pytest.raises(ValueError, match="no voxels"):
        history_string(rec, robot=0)


def test_history_of_a_real_simulation(tmp_path) -> None:
    from freeform.sim import Simulator

    sim = Simulator(SimConfig(burn_in=0.0, duration=0.05), arch="cpu")
    grid = np.zeros((1, 3, 2, 2), np.uint8)
    grid[0, :, :, 0] = 1
    grid[0, 1, :, 1] = 3
    rec = sim.simulate(grid, record_every=100).recording
    history = read_history(write_history(tmp_path / "s.history", rec))
    np.testing.assert_allclose(history.positions, rec.positions[0], atol=1e-7)
    assert history.positions.shape[1] == 8


def test_export_body_dispatches_on_the_suffix(tmp_path) -> None:
    grid = np.zeros((5, 5, 5), np.uint8)
    grid[1:3, 2, 1:4] = 2
    for suffix in (".vxd", ".obj", ".stl", ".vox"):
        assert export_body(tmp_path / f"b{suffix}", grid).stat().st_size > 0
    np.testing.assert_array_equal(read_vxd(tmp_path / "b.vxd"), grid[1:3, 2:3, 1:4])
    np.testing.assert_array_equal(read_vox(tmp_path / "b.vox")[0], grid[1:3, 2:3, 1:4])
    assert read_stl(tmp_path / "b.stl").max() == pytest.approx(0.03)  # metres: 3 voxels of 1 cm
    with pytest.raises(ValueError, match="one of"):
        export_body(tmp_path / "b.ply", grid)
