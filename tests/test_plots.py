"""The animations' GIF writer (diffgcl.viz.plots.write_gif): its frames against full renders."""

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from PIL import Image, ImageSequence  # noqa: E402

from diffgcl.viz.plots import write_gif  # noqa: E402

FRAMES = 6


def scene():
    """A static background (axes, patches, a line, an image of many colours) and two moving
    artists: a line, a title."""
    fig, ax = plt.subplots(figsize=(3, 2), dpi=60)
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.add_patch(plt.Circle((0.8, 0.8), 0.1, color="tab:orange"))
    ax.add_patch(plt.Circle((0.3, 0.8), 0.015, color="tab:green"))  # a few pixels
    # Hundreds of colours over large areas: more than a GIF's 256.
    shades = np.linspace(0, 1, 64 * 8).reshape(8, 64)
    ax.imshow(shades, extent=(0, 0.6, 0, 0.4), cmap="viridis", aspect="auto")
    ax.axhline(0.5, color="0.6", ls=":")
    (line,) = ax.plot([], [], color="tab:blue", lw=3)
    title = ax.set_title("")

    def update(i):
        line.set_data([0.1, 0.1 + 0.15 * i], [0.2, 0.2 + 0.1 * i])
        title.set_text(f"frame {i}")

    return fig, (line, title), update


def full_render(i) -> np.ndarray:
    fig, _, update = scene()
    update(i)
    fig.canvas.draw()
    image = np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(float)
    plt.close(fig)
    return image


def test_write_gif_frames_equal_full_renders(tmp_path):
    fig, artists, update = scene()
    path = tmp_path / "sub" / "anim.gif"
    write_gif(fig, artists, update, range(FRAMES), path, fps=4)
    assert not plt.fignum_exists(fig.number)  # closed
    with Image.open(path) as gif:
        frames = [np.asarray(f.convert("RGB"), float) for f in ImageSequence.Iterator(gif)]
        assert gif.info["duration"] == 250
    assert len(frames) == FRAMES
    for i, frame in enumerate(frames):
        reference = full_render(i)
        assert frame.shape == reference.shape
        # One palette for all frames: colours it lacks map to their nearest (a cube of 51 steps).
        assert np.abs(frame - reference).mean() < 3.0, i
        assert (np.abs(frame - reference).max(axis=-1) > 40).mean() < 0.002, i
        # Every coloured pixel keeps its colour, the small patch's included.
        coloured = np.ptp(reference, axis=-1) > 100
        assert coloured.sum() > 0
        assert np.abs(frame - reference)[coloured].max() < 60, i
    # The moving line is drawn where it is at each frame, not left where it was.
    assert np.abs(frames[0] - frames[-1]).max() > 100


def test_write_gif_refuses_no_frames(tmp_path):
    fig, artists, update = scene()
    with pytest.raises(ValueError, match="no frames"):
        write_gif(fig, artists, update, [], tmp_path / "a.gif", fps=4)
    plt.close(fig)
