"""freeform.render: colours in the right places (hand-worked camera and Lambert shading), translucency, gait frames,
GIFs that really land in a TensorBoard event file, and the per-epoch logging."""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from freeform.render import (
    RenderConfig,
    VideoConfig,
    add_gif,
    contact_sheet,
    encode_gif,
    log_epoch_renders,
    pick_bodies,
    quat_to_matrix,
    render_grid,
    render_grids,
    render_recording,
    write_video,
)
from freeform.sim import Recording

BLUE, GREEN, RED = (0.13, 0.42, 0.93), (0.33, 0.78, 0.16), (0.89, 0.16, 0.13)
LIGHT = np.array([0.3, -0.6, 1.0]) / np.linalg.norm([0.3, -0.6, 1.0])


def lambert(rgb: tuple[float, float, float], normal: tuple[int, int, int]) -> np.ndarray:
    """The expected 8-bit colour of a face: ambient 0.45 + diffuse 0.6 · max(0, n·l) (RenderConfig defaults)."""
    k = 0.45 + 0.6 * max(0.0, float(np.dot(normal, LIGHT)))
    return np.clip(np.asarray(rgb) * k, 0, 1) * 255


def close(pixel: np.ndarray, expected: np.ndarray, tol: float = 4.0) -> bool:
    return bool(np.all(np.abs(pixel.astype(float) - expected) <= tol))


# A camera looking straight down (azimuth −90°: screen x = world x, screen y = world y), so where a voxel lands is
# plain arithmetic: with frame="grid" and no margin the ρ×ρ footprint fills the image, cell (i, j) has its centre at
# pixel column (i + 0.5)·size/ρ and row size − (j + 0.5)·size/ρ. Elevation 89.99° (not 90°) keeps the right vector
# defined; the box's vertical edges then project to well under a pixel.
PLAN = RenderConfig(size=160, azimuth=-90.0, elevation=89.99, margin=0.0, show_panes=False)


def plan_pixel(image: np.ndarray, i: float, j: float, rho: int) -> np.ndarray:
    s = image.shape[0]
    return image[int(s - (j + 0.5) * s / rho), int((i + 0.5) * s / rho)]


def test_plan_view_puts_each_material_colour_over_its_cell() -> None:
    grid = np.zeros((4, 4, 4), dtype=np.uint8)
    grid[0, 0, 0] = 1  # passive: blue, bottom-left
    grid[3, 0, 0] = 2  # muscle A: green, bottom-right
    grid[3, 3, 0] = 3  # muscle B: red, top-right
    image = render_grid(grid, config=PLAN)
    assert image.shape == (160, 160, 3) and image.dtype == np.uint8
    up = (0, 0, 1)
    assert close(plan_pixel(image, 0, 0, 4), lambert(BLUE, up))
    assert close(plan_pixel(image, 3, 0, 4), lambert(GREEN, up))
    assert close(plan_pixel(image, 3, 3, 4), lambert(RED, up))
    assert close(plan_pixel(image, 0, 3, 4), np.array([255, 255, 255]), tol=0)  # empty cell: background
    assert close(plan_pixel(image, 1.5, 1.5, 4), np.array([255, 255, 255]), tol=0)


def test_removed_voxels_are_translucent_grey_over_what_lies_behind() -> None:
    final = np.zeros((4, 4, 4), dtype=np.uint8)
    final[1, 1, 0] = 1  # the body
    final[1, 1, 2] = 1  # not connected to it: removed, drawn translucent above the body voxel
    final[2, 3, 3] = 2  # removed, over the empty background
    body = np.zeros_like(final)
    body[1, 1, 0] = 1
    image = render_grid(final, body, PLAN)
    grey = lambert((0.55, 0.55, 0.55), (0, 0, 1))
    # "over" compositing with alpha 0.28 (RenderConfig.removed_alpha), worked by hand
    assert close(plan_pixel(image, 1, 1, 4), 0.28 * grey + 0.72 * lambert(BLUE, (0, 0, 1)))
    assert close(plan_pixel(image, 2, 3, 4), 0.28 * grey + 0.72 * np.array([255.0, 255, 255]))
    # a removed muscle is still grey: its material is not shown
    r, g, b = plan_pixel(image, 2, 3, 4).astype(int)
    assert abs(r - g) <= 2 and abs(g - b) <= 2


def test_default_isometric_view_shades_the_three_visible_faces() -> None:
    """One red voxel zoomed to fill the frame (camera az −60°, el 30°): the top face is above the image centre, the
    −y face lower left, the +x face lower right (screen right = (cos 30°, sin 30°, 0) in world), each with its
    own Lambert brightness."""
    grid = np.zeros((3, 3, 3), dtype=np.uint8)
    grid[1, 1, 1] = 3
    image = render_grid(grid, config=RenderConfig(size=200, frame="body"))
    c = 100
    assert close(image[c - 35, c], lambert(RED, (0, 0, 1)))
    assert close(image[c + 25, c - 40], lambert(RED, (0, -1, 0)))
    assert close(image[c + 25, c + 40], lambert(RED, (1, 0, 0)))
    assert close(image[3, 3], np.array([255, 255, 255]), tol=0)


def test_render_grids_batches_and_rejects_bad_input() -> None:
    rng = np.random.default_rng(0)
    grids = (rng.random((3, 6, 6, 6)) < 0.1).astype(np.uint8) * rng.integers(1, 4, (3, 6, 6, 6)).astype(np.uint8)
    images = render_grids(grids, config=RenderConfig(size=64), captions=["a", "b", "c"])
    assert images.shape == (3, 64, 64, 3)
    assert not np.array_equal(images[0], images[1])
    with pytest.raises(ValueError, match="grids"):
        render_grids(grids[0])
    with pytest.raises(ValueError, match="captions"):
        render_grids(grids, captions=["a"])
    with pytest.raises(ValueError, match="body"):
        render_grid(grids[0], grids[0][:3])
    with pytest.raises(ValueError, match="frame"):
        render_grid(grids[0], config=RenderConfig(frame="zoom"))
    with pytest.raises(ValueError, match="0..255"):
        render_grid(np.full((2, 2, 2), 300))


def test_contact_sheet_tiles_row_major() -> None:
    imgs = np.zeros((5, 10, 8, 3), dtype=np.uint8)
    for i in range(5):
        imgs[i] = 40 * i
    sheet = contact_sheet(imgs, columns=3, gap=2)
    assert sheet.shape == (2 * 10 + 3 * 2, 3 * 8 + 4 * 2, 3)
    assert sheet[2 + 10 + 2 + 5, 2 + 8 + 2 + 4, 0] == 40 * 4  # row 1, column 1 holds image 4
    assert sheet[2 + 10 + 2 + 5, 2 + 2 * (8 + 2) + 4, 0] == 255  # the unused sixth slot stays background


def test_quat_to_matrix_matches_hand_worked_rotations() -> None:
    s = math.sqrt(0.5)
    rz90 = quat_to_matrix(np.array([s, 0, 0, s]))  # 90° about +z takes +x to +y
    np.testing.assert_allclose(rz90 @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    rx180 = quat_to_matrix(np.array([0, 1, 0, 0]))
    np.testing.assert_allclose(rx180 @ [0, 1, 0], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix(np.array([2.0, 0, 0, 0])), np.eye(3), atol=1e-12)  # normalised


def synthetic_recording(frames: int = 12, voxel_size: float = 0.01) -> Recording:
    """A 2×1×1 muscle-A bar sliding along +x by one voxel per frame, level on the floor (z = 0 centres)."""
    lattice = np.array([[0, 0, 0], [1, 0, 0]])
    base = lattice * voxel_size
    pos = np.stack([base + [f * voxel_size, 0.0, 0.0] for f in range(frames)]).astype(np.float32)
    ori = np.tile(np.array([1, 0, 0, 0], np.float32), (frames, 2, 1))
    return Recording(times=np.arange(frames) * 0.05, voxel_size=voxel_size, lattice=[lattice],
                     materials=[np.array([2, 2], np.uint8)], positions=[pos], orientations=[ori])


def green_mask(frame: np.ndarray) -> np.ndarray:
    r, g, b = (frame[..., i].astype(int) for i in range(3))
    return (g > 110) & (g > r + 40) & (g > b + 40)


def test_render_recording_moves_the_robot_and_draws_the_trace() -> None:
    rec = synthetic_recording()
    cfg = RenderConfig(size=128, follow=False)
    frames = render_recording(rec, config=cfg)
    assert frames.shape == (12, 128, 128, 3)
    first, last = green_mask(frames[0]), green_mask(frames[-1])
    assert first.sum() > 50 and last.sum() > 50
    # world +x points to screen right·cos30° (and up), so a fixed camera sees the robot move right
    assert np.argwhere(last)[:, 1].mean() > np.argwhere(first)[:, 1].mean() + 20
    orange = lambda f: ((f[..., 0] > 200) & (f[..., 1] > 80) & (f[..., 1] < 160) & (f[..., 2] < 60)).sum()
    assert orange(frames[-1]) > orange(frames[0])  # the centre of mass's path grows behind the robot
    sub = render_recording(rec, config=cfg, frames=[0, 11])
    np.testing.assert_array_equal(sub[1], frames[11])
    with pytest.raises(ValueError, match="robot"):
        render_recording(rec, robot=1)
    with pytest.raises(ValueError, match="frames"):
        render_recording(rec, frames=[12])


# The relief factor of a face with unit normal n against the flat floor's: shade(n) / shade(+z).
def relief(normal: tuple[float, float, float]) -> float:
    return (0.45 + 0.6 * max(0.0, float(np.dot(normal, LIGHT)))) / (0.45 + 0.6 * LIGHT[2])


def test_ground_quads_lie_on_slopes_and_bumps() -> None:
    from freeform.render import ground_quads
    from freeform.sim import Terrain

    L, cfg = 0.01, RenderConfig()
    lo, hi = np.array([-0.05, -0.04]), np.array([0.06, 0.05])
    theta = math.radians(5)
    corners, rgb = ground_quads(Terrain.slope(5).field(L), lo, hi, 2 * L, cfg)
    assert len(corners) == 6 * 5  # a plane needs no subdivision: the 2-voxel checker tiles covering the box
    np.testing.assert_allclose(corners[..., 2], math.tan(theta) * corners[..., 0] - 0.5 * L, atol=1e-15)
    tilted = (-math.sin(theta), 0.0, math.cos(theta))  # the slope's upward normal
    floor = np.asarray(cfg.floor_colors)
    assert all(np.allclose(c, floor[0] * relief(tilted)) or np.allclose(c, floor[1] * relief(tilted)) for c in rgb)
    rough = Terrain.rough(0.003, 0.04).field(L)
    corners, _ = ground_quads(rough, lo, hi, 2 * L, cfg)
    assert len(corners) == 6 * 5 * 8 * 8  # 4 cm bumps: tiles cut in 8 x 8 quads of 2.5 mm
    np.testing.assert_allclose(corners[..., 2], rough.height(corners[..., 0], corners[..., 1]), atol=1e-15)
    assert np.ptp(corners[..., 2]) > 0.003  # the bumps are there (peak 3 mm either way)


def test_ground_quads_build_a_staircase_with_its_risers_facing_the_camera() -> None:
    """Steps of 3 mm risers and 2 cm treads up +x: tops at the analytic heights, one riser per tread edge in view
    facing -x (seen from azimuth -120, hidden from -60), shaded as a face turned from the light."""
    from freeform.render import ground_quads
    from freeform.sim import Terrain

    L, h, d = 0.01, 0.003, 0.02
    field = Terrain.steps(h, d, gap=0.002).field(L)
    lo, hi = np.array([-0.05, -0.04]), np.array([0.07, 0.04])
    up_hill = RenderConfig(azimuth=-120.0)
    corners, rgb = ground_quads(field, lo, hi, 2 * L, up_hill)
    vertical = np.ptp(corners[..., 0], axis=1) == 0  # a riser spans one x
    tops, risers = corners[~vertical], corners[vertical]
    cx = tops[..., 0].mean(axis=1)
    expected = np.where(cx < 0, 0.0, h * (np.floor(cx / d) + 1)) - 0.5 * L  # the first riser stands at x = 0
    np.testing.assert_allclose(tops[..., 2], np.repeat(expected[:, None], 4, axis=1), atol=1e-15)
    edges = np.unique(np.round(risers[:, 0, 0] / d, 9))
    np.testing.assert_array_equal(edges, [0, 1, 2, 3])  # x = 0, 2, 4, 6 cm: every riser in the box
    np.testing.assert_allclose(np.ptp(risers[..., 2], axis=1), h, atol=1e-15)
    floor = np.asarray(up_hill.floor_colors)
    dark = [floor[0] * relief((-1.0, 0.0, 0.0)), floor[1] * relief((-1.0, 0.0, 0.0))]
    assert all(np.allclose(c, dark[0]) or np.allclose(c, dark[1]) for c in rgb[vertical])
    corners, _ = ground_quads(field, lo, hi, 2 * L, RenderConfig())  # azimuth -60 looks down the stairs
    assert not (np.ptp(corners[..., 0], axis=1) == 0).any()


def test_render_recording_draws_the_recordings_terrain() -> None:
    """The same recording on stairs: risers (the dark face colour) appear where the flat floor has none."""
    from dataclasses import replace

    from freeform.sim import Terrain

    rec = synthetic_recording(frames=2)
    cfg = RenderConfig(size=128, azimuth=-120.0, supersample=1)
    flat = render_recording(rec, config=cfg, caption=False)[0]
    stairs = replace(rec, ground=Terrain.steps(0.003, 0.02, gap=0.002).field(rec.voxel_size))
    drawn = render_recording(stairs, config=cfg, caption=False)[0]
    riser = np.rint(np.asarray(cfg.floor_colors) * relief((-1.0, 0.0, 0.0)) * 255)
    is_riser = lambda im: sum(np.all(np.abs(im.astype(float) - c) <= 1, axis=-1).sum() for c in riser)
    assert is_riser(flat) == 0 and is_riser(drawn) > 100


def test_gif_lands_in_a_tensorboard_event_file(tmp_path) -> None:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from torch.utils.tensorboard import SummaryWriter

    frames = render_recording(synthetic_recording(6), config=RenderConfig(size=48))
    writer = SummaryWriter(log_dir=str(tmp_path))
    add_gif(writer, "bodies/best_gait", frames, step=7, fps=10)
    writer.close()
    acc = EventAccumulator(str(tmp_path), size_guidance={"images": 0})
    acc.Reload()
    assert "bodies/best_gait" in acc.Tags()["images"]
    (event,) = acc.Images("bodies/best_gait")
    assert event.step == 7 and (event.width, event.height) == (48, 48)
    assert event.encoded_image_string[:6] == b"GIF89a"
    gif = Image.open(io.BytesIO(event.encoded_image_string))
    assert gif.n_frames == 6
    gif.seek(5)
    decoded = np.asarray(gif.convert("RGB"), dtype=float)
    assert np.abs(decoded - frames[5]).mean() < 6  # one shared palette of 255 colours: close to the original


def test_encode_gif_and_write_video(tmp_path) -> None:
    frames = np.zeros((3, 16, 20, 3), dtype=np.uint8)
    frames[1, :, :, 0] = 255
    frames[2, :, :, 2] = 255
    gif = Image.open(io.BytesIO(encode_gif(frames, fps=25)))
    assert gif.n_frames == 3 and gif.size == (20, 16) and gif.info["duration"] == 40
    gif.seek(1)
    assert tuple(np.asarray(gif.convert("RGB"))[0, 0]) == (255, 0, 0)
    path = write_video(tmp_path / "v.gif", frames, fps=25)
    assert path.read_bytes()[:6] == b"GIF89a"
    with pytest.raises(ValueError, match=r"\.gif or \.mp4"):
        write_video(tmp_path / "v.avi", frames)
    with pytest.raises(ValueError, match="frames"):
        encode_gif(frames[0])


def test_write_mp4_when_the_video_extra_is_installed(tmp_path) -> None:
    pytest.importorskip("imageio_ffmpeg")
    frames = np.zeros((5, 15, 17, 3), dtype=np.uint8)  # odd sizes: padded to even for yuv420p
    path = write_video(tmp_path / "v.mp4", frames, fps=10)
    assert path.stat().st_size > 0 and path.read_bytes()[4:8] == b"ftyp"


def test_pick_bodies_hand_worked() -> None:
    rng = np.random.default_rng(0)
    picked = pick_bodies(np.array([3.0, 1.0, 2.0, 5.0, 4.0]), rng)
    assert picked["best"] == 3 and picked["median"] == 0  # sorted 1,2,3,4,5: the middle value 3 is episode 0
    assert 0 <= picked["random"] < 5
    assert pick_bodies(np.array([1.0, 2.0]), rng)["median"] == 0  # even count: the lower middle
    with pytest.raises(ValueError, match="rewards"):
        pick_bodies(np.array([]), rng)


def test_log_epoch_renders_writes_best_median_random(tmp_path) -> None:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from torch.utils.tensorboard import SummaryWriter

    grids = np.zeros((4, 6, 6, 6), dtype=np.uint8)
    for i in range(4):
        grids[i, : i + 1, 0, 0] = 1  # body of volume i + 1
    grids[2, 5, 5, 5] = 3  # a removed voxel (not connected)
    rewards = np.array([1.0, 2.0, 3.0, 4.0])
    writer = SummaryWriter(log_dir=str(tmp_path))
    chosen = log_epoch_renders(writer, grids, rewards, step=3, rng=0, config=RenderConfig(size=64))
    writer.close()
    assert chosen["best"] == 3 and chosen["median"] == 1
    acc = EventAccumulator(str(tmp_path), size_guidance={"images": 0})
    acc.Reload()
    assert {"bodies/best", "bodies/median", "bodies/random"} <= set(acc.Tags()["images"])
    assert "bodies/best_gait" not in acc.Tags()["images"]  # no simulator given: no video
    best = np.asarray(Image.open(io.BytesIO(acc.Images("bodies/best")[0].encoded_image_string)).convert("RGB"))
    assert best.shape == (64, 64, 3)
    assert (best[..., 2].astype(int) - best[..., 0] > 100).sum() > 10  # the blue passive body is visible
    with pytest.raises(ValueError, match="rewards"):
        log_epoch_renders(writer, grids, rewards[:2], step=0)


def test_gait_video_from_the_simulator(tmp_path) -> None:
    """End to end with the physics engine: a short simulation of a two-muscle block, rendered and logged."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from torch.utils.tensorboard import SummaryWriter

    from freeform.sim import SimConfig, Simulator

    simulator = Simulator(SimConfig(burn_in=0.0, duration=0.3), arch="cpu")
    grids = np.zeros((2, 5, 5, 5), dtype=np.uint8)
    grids[0, :4, :2, 0] = 1
    grids[0, :2, :2, 1] = 2
    grids[0, 2:4, :2, 1] = 3
    grids[1, 0, 0, 0] = 1
    writer = SummaryWriter(log_dir=str(tmp_path))
    log_epoch_renders(writer, grids, np.array([2.0, 1.0]), step=1, rng=0, simulator=simulator,
                      config=RenderConfig(size=64), video=VideoConfig(fps=20, size=48))
    writer.close()
    acc = EventAccumulator(str(tmp_path), size_guidance={"images": 0})
    acc.Reload()
    gif = Image.open(io.BytesIO(acc.Images("bodies/best_gait")[0].encoded_image_string))
    assert gif.size == (48, 48) and gif.n_frames >= 6  # 0.3 s at 20 fps, plus the t = 0 frame


def test_simulator_cache_builds_one_short_simulator_per_settings_and_arch() -> None:
    from freeform.render import SimulatorCache
    from freeform.sim import SimConfig

    cache = SimulatorCache()
    base = SimConfig()
    short = cache.get(base, 1.5, "cpu")
    assert (short.config.burn_in, short.config.duration, short.arch) == (0.0, 1.5, "cpu")
    assert (base.burn_in, base.duration) == (SimConfig().burn_in, SimConfig().duration)  # the caller's is untouched
    assert cache.get(SimConfig(), 1.5, "cpu") is short  # equal settings in another object: the same simulator
    assert cache.get(base, 2.0, "cpu") is not short and cache.get(base, 1.5, "auto") is not short
    assert len(cache) == 3
    cache.clear()
    assert len(cache) == 0


def test_cli_renders_a_run_directory(tmp_path, capsys) -> None:
    """``freeform-render`` on a run with one design record: PNGs of the picks, a sheet, exports, a gait video."""
    from freeform.io import read_vxd
    from freeform.records import EpochRecord, write_record
    from freeform.render_cli import main

    grids = np.zeros((3, 6, 6, 6), dtype=np.uint8)
    grids[0, 0:2, 0:2, 0] = 1
    grids[1, 1:4, 1:3, 0] = 2
    grids[1, 1:3, 1:3, 1] = 3  # the best body: 10 voxels of both muscles
    grids[1, 5, 5, 5] = 1  # and a removed voxel
    grids[2, 2, 2, 0] = 1
    rewards = np.array([0.5, 2.5, 0.1], dtype=np.float32)
    write_record(tmp_path, EpochRecord(epoch=4, global_step=40, actions=np.zeros((3, 2, 7), np.float32),
                                       final_grids=grids, rewards=rewards, values=np.zeros((3, 2), np.float32)))
    out = tmp_path / "out"
    code = main([str(tmp_path), "--bodies", "best,worst,0", "--grid", "3", "--export", "vxd,stl", "--size", "64",
                 "--out", str(out), "--video", "--history", "--seconds", "0.1", "--arch", "cpu"])
    assert code == 0
    printed = set(capsys.readouterr().out.split())
    expected = {"best_1.png", "worst_2.png", "episode_0.png", "sheet.png", "best_1.vxd", "best_1.stl", "base.vxa",
                "best_1_gait.gif", "best_1.history"}
    assert expected <= {Path(p).name for p in printed}
    assert all((out / name).is_file() for name in expected)
    np.testing.assert_array_equal(read_vxd(out / "best_1.vxd"), grids[1, 1:4, 1:3, 0:2])  # body only, cropped
    assert Image.open(out / "best_1.png").size == (64, 64)
    # errors are reported, not raised
    assert main([str(tmp_path), "--epoch", "7"]) == 2
    assert main([str(tmp_path), "--bodies", "fastest"]) == 2
    assert main([str(tmp_path / "missing")]) == 2
    assert "error" in capsys.readouterr().err


def test_cli_sheet_of_several_runs_has_a_row_of_best_bodies_per_run(tmp_path, capsys) -> None:
    """Two runs (say two tasks): one sheet, row r = run r's best bodies in reward order, each tile the same picture
    ``render_grids`` draws of that design."""
    import json

    from freeform.records import EpochRecord, write_record
    from freeform.render import render_grids
    from freeform.render_cli import main

    runs = []
    for r, name in enumerate(("climb_cpu", "jump_cpu")):
        grids = np.zeros((3, 4, 4, 4), dtype=np.uint8)
        for e in range(3):
            grids[e, : e + 1, : r + 1, 0] = 1 + e  # a design per episode, different in every run
        run = tmp_path / name
        write_record(run, EpochRecord(epoch=2, global_step=6, actions=np.zeros((3, 1, 7), np.float32),
                                      final_grids=grids, rewards=np.array([0.2, 0.9, 0.5], np.float32),
                                      values=np.zeros((3, 1), np.float32)))
        (run / "run_info.json").write_text(json.dumps({"experiment": name}))
        runs.append((run, grids))
    out = tmp_path / "out"
    assert main([str(runs[0][0]), str(runs[1][0]), "--grid", "2", "--size", "96", "--out", str(out)]) == 0
    sheet = np.asarray(Image.open(out / "sheet.png"))
    gap = 4
    assert sheet.shape == (2 * 96 + 3 * gap, 2 * 96 + 3 * gap, 3)
    cfg = RenderConfig(size=96, caption_size=11)
    for row, (run, grids) in enumerate(runs):
        for col, episode in enumerate((1, 2)):  # rewards 0.9 then 0.5
            name = run.name
            tile = render_grids(grids[[episode]], grids[[episode]], cfg, [[name, f"reward {[0.2, 0.9, 0.5][episode]:.3g}"]])[0]
            y, x = gap + row * (96 + gap), gap + col * (96 + gap)
            np.testing.assert_array_equal(sheet[y:y + 96, x:x + 96], tile)
    capsys.readouterr()
    assert main([str(runs[0][0]), str(runs[1][0]), "--grid", "2"]) == 2  # no --out
    assert main([str(runs[0][0]), str(runs[1][0]), "--grid", "4", "--out", str(out)]) == 2  # 3 designs only
    assert main([str(runs[0][0]), str(runs[1][0]), "--grid", "2", "--out", str(out), "--video"]) == 2
    assert "several runs" in capsys.readouterr().err


def test_cli_random_policy_designs(tmp_path) -> None:
    from freeform.render_cli import main

    assert main(["--random", "4", "--resolution", "8", "--grid", "4", "--size", "48", "--out", str(tmp_path)]) == 0
    sheet = Image.open(tmp_path / "sheet.png")
    assert sheet.size[0] > 2 * 96  # a 2×2 sheet of at least 96-pixel tiles
    assert len(list(tmp_path.glob("best_*.png"))) == 1
