"""Video files from RGB frames: GIF (one global palette, frame deltas) and MP4 (libx264 through imageio-ffmpeg).

Nothing here knows what is drawn: ``scg_jax.render`` makes the frames and passes the colours it draws with, so
the GIF palette keeps them exact. Both writers are atomic: the file is written beside ``path`` and renamed, so
it is whole or absent.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from matplotlib.colors import to_rgba

from scg_jax.files import replacing, write_atomic

__all__ = ["MAX_GIF_FPS", "SUFFIXES", "write_gif", "write_mp4"]

SUFFIXES = (".gif", ".mp4")
MAX_GIF_FPS = 50  # GIF frame delays are in 1/100 s and viewers slow down delays under 20 ms
_UNCHANGED = 255  # GIF palette index of "same as the previous frame" (transparent)


def _fixed_palette(key_colors: Sequence) -> np.ndarray:
    """(K, 3) uint8: ``key_colors`` blended over white at several opacities, and a grey ramp."""
    rgb = np.array([to_rgba(c)[:3] for c in key_colors])
    alphas = np.array([1.0, 0.75, 0.45, 0.2])[:, None, None]
    blends = (alphas * rgb[None] + (1 - alphas)).reshape(-1, 3)
    greys = np.repeat(np.linspace(0.0, 1.0, 17)[:, None], 3, axis=1)
    return np.round(255 * np.concatenate([blends, greys])).astype(np.uint8)


class _PaletteMap:
    """Exact nearest-colour mapping of RGB frames onto a fixed 256-colour palette, memoised per colour."""

    def __init__(self, entries: np.ndarray):
        self.entries = entries.astype(np.int32)  # (256, 3)
        self.lut = np.full(1 << 24, -1, dtype=np.int16)

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        rgb = frame.astype(np.int32)
        codes = (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]
        index = self.lut[codes]
        missing = index < 0
        if missing.any():
            new = np.unique(codes[missing])
            colors = np.stack([new >> 16, (new >> 8) & 255, new & 255], axis=-1)
            distance = ((colors[:, None, :] - self.entries[None, :, :]) ** 2).sum(axis=-1)
            self.lut[new] = np.argmin(distance, axis=1)
            index = self.lut[codes]
        return index.astype(np.uint8)


def write_gif(path: Path, frames: Iterable[np.ndarray], fps: float, sample: Sequence[np.ndarray], key_colors=()):
    """Write (H, W, 3) uint8 ``frames`` as a looping GIF at ``fps`` (delays rounded to 10 ms, at least 20 ms).

    ``sample``: a few frames the adaptive part of the palette is cut from; ``key_colors``: colours (any matplotlib
    spelling) kept exactly in the palette, with their blends over white, so that small bodies keep their colours.
    """
    from PIL import Image

    # One palette for the whole animation, no dithering: stable colours and small frame deltas. Part of it is
    # fixed (the key colours over white at a few opacities, and a grey ramp); the rest is a median cut of the
    # sample frames (backgrounds, panes, blends). Index 255 is kept free: it marks a pixel that did not change
    # since the previous frame (transparent, drawn over the previous frame), which compresses far better than
    # redrawing the box between the time label and the bodies.
    fixed = _fixed_palette(key_colors)
    count = _UNCHANGED - len(fixed)
    adaptive = Image.fromarray(np.concatenate(sample, axis=0)).quantize(colors=count, method=Image.Quantize.MEDIANCUT)
    entries = np.concatenate([fixed, np.asarray(adaptive.getpalette()[: 3 * count]).reshape(-1, 3)])
    entries = np.pad(entries, ((0, 256 - len(entries)), (0, 0)), mode="edge").astype(np.uint8)
    to_index = _PaletteMap(entries[:_UNCHANGED])
    palette = entries.ravel().tolist()
    images, previous = [], None
    for frame in frames:
        index = to_index(frame)
        encoded = index if previous is None else np.where(index == previous, np.uint8(_UNCHANGED), index)
        previous = index
        image = Image.frombytes("P", (frame.shape[1], frame.shape[0]), encoded.tobytes())
        image.putpalette(palette)
        if previous is not None and images:  # the first frame is whole and opaque (readers then give RGB)
            image.info["transparency"] = _UNCHANGED
        images.append(image)
    duration = max(20, round(1000.0 / fps / 10.0) * 10)
    options = dict(duration=duration, loop=0, optimize=False, disposal=1)
    write_atomic(
        path, lambda file: images[0].save(file, format="GIF", save_all=True, append_images=images[1:], **options)
    )


def write_mp4(path: Path, frames: Iterable[np.ndarray], fps: float, width: int, height: int) -> None:
    """Write (height, width, 3) uint8 ``frames`` as an H.264 MP4 (yuv420p; odd sizes padded white to even)."""
    import imageio_ffmpeg

    # libx264's yuv420p needs even sizes: pad odd frames with a white row/column rather than let ffmpeg rescale.
    pad_h, pad_w = height % 2, width % 2
    with replacing(path, ".mp4") as tmp:
        writer = imageio_ffmpeg.write_frames(
            str(tmp),
            (width + pad_w, height + pad_h),
            fps=fps,
            codec="libx264",
            quality=7,
            macro_block_size=2,
            ffmpeg_log_level="error",
            output_params=["-movflags", "+faststart"],
        )
        with warnings.catch_warnings():
            # Starting ffmpeg forks and immediately execs, which is safe; JAX warns about any fork.
            warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
            writer.send(None)
        for frame in frames:
            if pad_h or pad_w:
                frame = np.pad(frame, ((0, pad_h), (0, pad_w), (0, 0)), constant_values=255)
            writer.send(np.ascontiguousarray(frame))
        writer.close()
