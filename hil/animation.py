"""Animations of a run (`hil run --animate`): which recorded rows become frames, and writing the
frames as a GIF (matplotlib's PillowWriter) or an MP4 (its FFMpegWriter, with ffmpeg on PATH).

What a frame shows is the robot kind's business (`Rig.animation`); this module knows no robot.
Invariants: frames are evenly spaced, at least 1 / MAX_FPS apart in simulated time and at most
MAX_FRAMES in all, so any run renders in seconds; the playback runs at the simulated speed (the
frames' spacing in simulated time is their spacing on screen), so a time stamp in the frame reads
true; the file is written whole or not at all (`hil.results.write_file`); the figure is drawn by
Agg, never by an interactive backend.
"""

from __future__ import annotations

import contextlib
import math
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hil.errors import HilError
from hil.results import write_file

if TYPE_CHECKING:
    from matplotlib.artist import Artist
    from matplotlib.figure import Figure

FORMATS = ("gif", "mp4")
MAX_FPS = 15.0  # [1/s of simulated time]: finer steps are invisible at a GIF's frame rate
MAX_FRAMES = 300  # any duration: a 20 s run at 15 fps fits, a longer one is subsampled
DPI = 80
FIGURE_WIDTH = 6.4  # [in] at DPI: 512 pixels


def check_format(fmt: str) -> None:
    """HilError (one line) for a format this machine cannot write: unknown, or MP4 without
    ffmpeg on PATH."""
    if fmt not in FORMATS:
        raise HilError(f"--animate: unknown format {fmt!r} (known: {', '.join(FORMATS)})")
    if fmt == "mp4":
        from matplotlib.animation import FFMpegWriter

        if not FFMpegWriter.isAvailable():
            raise HilError("--animate mp4: ffmpeg is not on PATH; install it, or use gif")


def frame_rows(
    time: np.ndarray, max_fps: float = MAX_FPS, max_frames: int = MAX_FRAMES
) -> np.ndarray:
    """The recorded rows drawn as frames: every `stride`-th row from the first, the stride the
    smallest whole number of rows that keeps frames at least 1 / `max_fps` apart in simulated
    time and at most `max_frames` in all. A whole stride keeps the frames evenly spaced, so the
    animation plays at one frame rate; the last frame is less than a stride before the end.

    Parameters
    ----------
    time : ndarray, shape (rows,)
        Recorded times [s], increasing and evenly spaced (one row per SYNC).
    max_fps : float
        Most frames per second of simulated time [1/s].
    max_frames : int
        Most frames, for any duration.

    Returns
    -------
    ndarray of int, shape (frames,)
        Row indices, increasing, the first 0.
    """
    rows = int(np.asarray(time).size)
    if rows < 2:
        return np.arange(rows)
    step = float(time[-1] - time[0]) / (rows - 1)
    by_rate = math.ceil(1.0 / (max_fps * step) - 1e-9) if step > 0 else 1
    by_count = math.ceil((rows - 1) / max(max_frames - 1, 1) - 1e-9)
    return np.arange(0, rows, max(1, by_rate, by_count))


def playback_fps(time: np.ndarray, rows: np.ndarray) -> float:
    """Frames per second of wall clock that play the frames at the simulated speed."""
    if rows.size < 2:
        return 1.0
    return float((rows.size - 1) / (time[rows[-1]] - time[rows[0]]))


def figure_size(low: np.ndarray, high: np.ndarray) -> tuple[float, float]:
    """Width and height [in] of a figure showing the box from `low` to `high` (x, y [m]) at
    equal scales, with room for the axes' labels and a legend below: FIGURE_WIDTH wide for a
    wide box, as tall for a tall one."""
    aspect = float((high[1] - low[1]) / (high[0] - low[0]))  # height to width
    width = FIGURE_WIDTH if aspect <= 1.0 else max(3.5, FIGURE_WIDTH / aspect + 1.0)
    height = min(FIGURE_WIDTH + 1.5, max(2.4, (width - 1.0) * aspect + 1.5))
    return width, height


def top_view(ax: Any, low: np.ndarray, high: np.ndarray, title: str, legend_columns: int) -> Any:
    """Frame `ax` as the scene seen from above (equal axes from `low` to `high` [m], grid,
    title, the legend under the figure); returns the time stamp's text artist."""
    stamp = ax.text(0.02, 0.97, "", transform=ax.transAxes, va="top", family="monospace")
    ax.set_xlim(low[0], high[0])
    ax.set_ylim(low[1], high[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.figure.legend(loc="outside lower center", ncols=legend_columns, fontsize=7)
    return stamp


def write_animation(
    fig: Figure,
    moving: Sequence[Artist],
    draw_frame: Callable[[int], None],
    frames: int,
    fps: float,
    path: Path,
    fmt: str,
) -> None:
    """Draw frame k = 0 .. frames - 1 with `draw_frame(k)` (it updates the `moving` artists of
    `fig`) and write them to `path` as `fmt` at `fps` frames per second; WriteError if the disk
    refuses.

    Everything but the moving artists is drawn once (blitting): a full draw of a figure costs
    about 70 ms, a blit of a few lines about 1 ms. The writer writes a temporary file outside
    the results folder, whose bytes then reach `path` atomically like every results file."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    check_format(fmt)
    canvas = FigureCanvasAgg(fig)  # Agg draws it, whatever pyplot's backend is
    for artist in moving:
        artist.set_animated(True)  # left out of the full draw: the background
    writer = _writer(fmt, fps, _colours(moving))
    with tempfile.TemporaryDirectory(prefix="softhil-animation-") as folder:
        temporary = Path(folder) / f"animation.{fmt}"
        with writer.saving(fig, str(temporary), fig.dpi):
            canvas.draw()  # after the writer's setup, which may round the size to even pixels
            background = canvas.copy_from_bbox(fig.bbox)
            for k in range(frames):
                draw_frame(k)
                canvas.restore_region(background)
                for artist in moving:
                    fig.draw_artist(artist)
                writer.grab_frame()
        data = temporary.read_bytes()
    write_file(path, data)


def _canvas_rgba(fig: Figure) -> np.ndarray:
    """The canvas's pixels as drawn so far, shape (height, width, 4), uint8 (a view)."""
    return np.asarray(fig.canvas.buffer_rgba())  # type: ignore[attr-defined]


def _writer(fmt: str, fps: float, colours: Sequence[tuple[float, float, float]]) -> Any:
    """matplotlib's writer for `fmt`, taking each frame from the canvas as blitted instead of
    drawing the whole figure again (what its own grab_frame does). The GIF's frames share one
    palette, made from the first frame and from `colours` (those of the moving artists, which the
    first frame may not show yet)."""
    from matplotlib.animation import FFMpegWriter, PillowWriter
    from PIL import Image

    # both keep matplotlib's own setup and finish; grab_frame hands them the canvas's pixels
    # where matplotlib's keeps them (PillowWriter._frames, MovieWriter._proc: matplotlib >= 3.1)
    class GifWriter(PillowWriter):
        palette: Any = None

        def grab_frame(self, **savefig_kwargs: Any) -> None:
            image = Image.fromarray(_canvas_rgba(self.fig)[:, :, :3])  # a copy, RGB
            if self.palette is None:  # one palette for every frame: 1 ms a frame, not 40
                self.palette = _palette(image, colours)
            frame = image.quantize(palette=self.palette, dither=Image.Dither.NONE)
            self._frames.append(frame)  # type: ignore[attr-defined]

    class Mp4Writer(FFMpegWriter):
        def grab_frame(self, **savefig_kwargs: Any) -> None:
            # frame_format "rgba", the bytes savefig would write
            self._proc.stdin.write(_canvas_rgba(self.fig).tobytes())  # type: ignore[attr-defined]

    # fps: a float plays at the simulated speed (matplotlib's stubs say int; both writers take
    # any rate: Pillow's frame duration 1000 / fps ms, ffmpeg's -r)
    if fmt == "gif":
        return GifWriter(fps=fps)  # type: ignore[arg-type]
    return Mp4Writer(fps=fps)  # type: ignore[arg-type]


def _colours(artists: Sequence[Artist]) -> list[tuple[float, float, float]]:
    """The colours the artists draw with (lines, markers, faces, edges, text), as RGB in [0, 1]."""
    from matplotlib.colors import to_rgb

    colours = []
    for artist in artists:
        for getter in ("get_color", "get_markerfacecolor", "get_facecolor", "get_edgecolor"):
            method = getattr(artist, getter, None)
            if method is not None:
                with contextlib.suppress(ValueError):
                    colours.append(to_rgb(method()))
    return colours


def _palette(first: Any, colours: Sequence[tuple[float, float, float]]) -> Any:
    """A GIF palette (a "P" image) for frames like `first`: its own colours, and ramps from each
    of `colours` to white and to black (what antialiasing blends them into)."""
    from PIL import Image

    steps = np.linspace(0.0, 1.0, 12)[:, None]
    ramps = [np.asarray(c) * (1.0 - steps) + end * steps for c in colours for end in (1.0, 0.0)]
    swatch = (255 * np.vstack([*ramps, np.ones((1, 3))])).round().astype(np.uint8)
    # a strip of the ramps, repeated so that the quantiser weighs them like drawn lines
    strip = np.resize(swatch, (8 * swatch.shape[0], 3))
    width = first.width
    rows = -(-strip.shape[0] // width)
    block = np.full((rows * width, 3), 255, dtype=np.uint8)
    block[: strip.shape[0]] = strip
    sample = Image.new("RGB", (width, first.height + rows))
    sample.paste(first, (0, 0))
    sample.paste(Image.fromarray(block.reshape(rows, width, 3)), (0, first.height))
    return sample.quantize(255, method=Image.Quantize.FASTOCTREE)
