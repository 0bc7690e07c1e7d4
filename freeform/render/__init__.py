"""Seeing the robots: shaded images of voxel designs, videos of simulated gaits, and their TensorBoard summaries.

Everything here is a small orthographic rasteriser on top of Pillow (already installed as a dependency of
TensorBoard): the visible faces of the voxels are built as one numpy array of quads, sorted back to front
(painter's algorithm — exact enough for unit cubes on a grid, and for the slightly rotated cubes of a gait), shaded
with one directional light, and filled with Pillow's C polygon filler at twice the size, then box-filtered down
(anti-aliasing): cheap enough to log a few images every few epochs (``python -m benchmarks render``,
docs/rendering.md).

Colours are the paper's (its figures 1-2): passive tissue blue, muscle A green, muscle B red; the voxels of the
final grid that are *not* in the body (the largest connected component) are drawn translucent grey, as in the
paper's "body after a_100" panel.

Modules, by concern (this package re-exports their public names):
- ``raster`` — :class:`RenderConfig` and the rasteriser itself (camera, Lambert shading, the Pillow canvas).
- ``designs`` — :func:`render_grid` / :func:`render_grids` (design grids ``[ρ, ρ, ρ]`` / ``[N, ρ, ρ, ρ]`` uint8 →
  RGB ``[H, W, 3]`` / ``[N, H, W, 3]`` uint8) and :func:`contact_sheet` (many images → one sheet).
- ``gait`` — :func:`render_recording` (a ``freeform.sim.Recording`` → frames ``[F, H, W, 3]`` uint8),
  :func:`simulate_gait`, :class:`VideoConfig`, and :func:`gait_simulator` over the :class:`SimulatorCache`.
- ``video`` — :func:`encode_gif`, :func:`write_video` (``.gif`` with Pillow, ``.mp4`` with the optional ``video``
  extra), :func:`write_png`.
- ``tensorboard`` — :func:`add_gif` (an animated GIF into an event file, no moviepy needed) and
  :func:`log_epoch_renders`, what the training loop calls every ``trainer.render_every`` epochs;
  :func:`log_bodies` is the same behind the trainer's ``(writer, final_grids, rewards, step, cfg)`` hook;
  :func:`log_controlled_gait` a control run's GIF of its controller driving the epoch's best body.
The face geometry and the material colours are shared with ``freeform.io`` through ``freeform.surface``.
"""

from freeform.render.designs import contact_sheet, render_grid, render_grids
from freeform.render.gait import (
    GAIT_SIMULATORS,
    SimulatorCache,
    VideoConfig,
    com_trajectory,
    gait_simulator,
    ground_quads,
    quat_to_matrix,
    render_recording,
    simulate_gait,
)
from freeform.render.raster import RenderConfig
from freeform.render.tensorboard import (
    add_gif,
    log_bodies,
    log_controlled_gait,
    log_epoch_renders,
    pick_bodies,
)
from freeform.render.video import encode_gif, write_png, write_video
from freeform.surface import FACE_CORNERS, FACE_NORMALS, PAPER_COLORS, RGB

__all__ = [
    "FACE_CORNERS",
    "FACE_NORMALS",
    "GAIT_SIMULATORS",
    "PAPER_COLORS",
    "RGB",
    "RenderConfig",
    "SimulatorCache",
    "VideoConfig",
    "add_gif",
    "com_trajectory",
    "contact_sheet",
    "encode_gif",
    "gait_simulator",
    "log_bodies",
    "log_controlled_gait",
    "log_epoch_renders",
    "pick_bodies",
    "quat_to_matrix",
    "render_grid",
    "render_grids",
    "ground_quads",
    "render_recording",
    "simulate_gait",
    "write_png",
    "write_video",
]
