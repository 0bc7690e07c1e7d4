"""Images and videos to files: PNG, looping GIF (Pillow), MP4 (H.264 through the optional ``video`` extra)."""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image


def check_frames(frames: np.ndarray | Sequence[np.ndarray]) -> np.ndarray:
    arr = np.asarray(frames)
    if arr.ndim != 4 or arr.shape[-1] != 3 or len(arr) == 0:
        raise ValueError(f"frames must be a non-empty [F, H, W, 3] uint8 array, got shape {arr.shape}")
    return arr.astype(np.uint8, copy=False)


def encode_gif(frames: np.ndarray | Sequence[np.ndarray], fps: float = 20.0) -> bytes:
    """Frames ``[F, H, W, 3]`` uint8 → the bytes of a looping animated GIF at ``fps`` frames per second."""
    arr = check_frames(frames)
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    # One shared palette (quantised from a strip of frames) keeps colours from flickering between frames.
    strip = Image.fromarray(np.concatenate(list(arr[:: max(1, len(arr) // 8)]), axis=0))
    palette = strip.quantize(colors=255, method=Image.Quantize.MEDIANCUT)
    images = [Image.fromarray(f).quantize(palette=palette, dither=Image.Dither.NONE) for f in arr]
    buf = io.BytesIO()
    images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], loop=0,
                   duration=max(20, int(round(1000.0 / fps))), disposal=1)
    return buf.getvalue()


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Write an RGB uint8 ``[H, W, 3]`` image as PNG; returns the path."""
    arr = np.asarray(image, dtype=np.uint8)
    if arr.ndim != 3 or arr.shape[-1] != 3:
        raise ValueError(f"image must be [H, W, 3] uint8, got shape {arr.shape}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(arr).save(path, format="PNG", optimize=True)
    return path


def write_video(path: str | Path, frames: np.ndarray | Sequence[np.ndarray], fps: float = 20.0) -> Path:
    """Write frames ``[F, H, W, 3]`` uint8 as ``.gif`` (Pillow) or ``.mp4`` (H.264 through imageio-ffmpeg, the
    optional extra ``pip install 'freeform[video]'``, which ships its own ffmpeg); returns the path."""
    path = Path(path)
    arr = check_frames(frames)
    suffix = path.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise ValueError(f"video path must end in .gif or .mp4, got {path.name!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".gif":
        path.write_bytes(encode_gif(arr, fps))
        return path
    try:
        import imageio_ffmpeg
    except ImportError as exc:
        raise ValueError(
            "writing .mp4 needs imageio-ffmpeg: pip install 'freeform[video]' (or write a .gif)"
        ) from exc
    h, w = arr.shape[1:3]
    # H.264 with yuv420p wants even sizes; pad by one row/column of background when needed.
    ph, pw = h + h % 2, w + w % 2
    if (ph, pw) != (h, w):
        arr = np.pad(arr, ((0, 0), (0, ph - h), (0, pw - w), (0, 0)), mode="edge")
    writer = imageio_ffmpeg.write_frames(str(path), (pw, ph), fps=fps, codec="libx264", pix_fmt_out="yuv420p",
                                         macro_block_size=1, output_params=["-loglevel", "error"])
    writer.send(None)  # prime the generator
    for f in arr:
        writer.send(np.ascontiguousarray(f))
    writer.close()
    return path


__all__ = ["check_frames", "encode_gif", "write_png", "write_video"]
