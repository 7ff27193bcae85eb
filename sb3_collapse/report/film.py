"""The paper's Figures 6 and 7 (``python -m sb3_collapse.probe film``): a filmstrip PNG with the actions under each
strip, an animated GIF per film and the actions as CSV, of films of :func:`~sb3_collapse.probe.film.film_episode`
(each with ``label``, ``frames``, ``images``, ``actions`` and ``rewards``). See docs/figures.md."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from PIL import Image

from sb3_collapse.report.style import OKABE_ITO, frames_axis

STRIP_EVERY_FRAMES = 30
"""Frames between two pictures of the filmstrip."""


def plot_filmstrip(films: Sequence[Any], path: Path, every_frames: int = STRIP_EVERY_FRAMES, title: str = "") -> None:
    """The filmstrip to ``path``: a row per film, a picture every ``every_frames`` frames and, under it, each action
    dimension."""
    picks = [_one_per_period(f.frames, every_frames) for f in films]
    columns = max(len(pick) for pick in picks)
    thumb = 1.15  # inches per picture: the strip's frame axis spans columns x every_frames frames
    left, right, top = 0.65, 1.0, 0.45
    strip_width = thumb * columns
    row_height = thumb + 0.3 + 1.0 + 0.75  # pictures, their frame labels, the actions, their axis label
    width, height = left + strip_width + right, top + row_height * len(films)
    fig = plt.figure(figsize=(width, height))
    half = every_frames / 2
    limits = (-half, -half + every_frames * columns)
    for i, (film, pick) in enumerate(zip(films, picks)):
        bottom = height - top - row_height * (i + 1)
        strip_ax = fig.add_axes(((left) / width, (bottom + 2.05) / height, strip_width / width, thumb / height))
        action_ax = fig.add_axes((left / width, (bottom + 0.75) / height, strip_width / width, 1.0 / height))
        for j in pick:  # each picture centred on its own frame, square
            frame = float(film.frames[j])
            strip_ax.imshow(film.images[j], extent=(frame - half, frame + half, 0, 1), aspect="auto")
        strip_ax.set_xlim(*limits)
        strip_ax.set_ylim(0, 1)
        strip_ax.set_yticks([])
        strip_ax.set_xticks([int(film.frames[j]) for j in pick])
        strip_ax.tick_params(labelsize=7, length=2)
        strip_ax.set_title(film.label, fontsize=9, loc="left")
        for dimension in range(film.actions.shape[1]):
            color = OKABE_ITO[dimension % len(OKABE_ITO)]
            action_ax.step(
                film.frames, film.actions[:, dimension], where="post", lw=1.1, color=color, label=f"{dimension}"
            )
        action_ax.set_xlim(*limits)
        action_ax.set_ylim(-1.1, 1.1)
        action_ax.set_ylabel("action", fontsize=8)
        action_ax.grid(alpha=0.3)
        action_ax.tick_params(labelsize=7)
        frames_axis(action_ax, "environment frames")
        action_ax.xaxis.label.set_size(8)
        action_ax.legend(
            title="dim", fontsize=6, title_fontsize=6, loc="upper left", bbox_to_anchor=(1.005, 1.05), frameon=False
        )
    fig.suptitle(title or "Frames of an episode and the actions taken", fontsize=10, y=1 - 0.12 / height)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _one_per_period(frames: np.ndarray, every_frames: int) -> list[int]:
    """:return: the index of the first picture at or after each multiple of ``every_frames``"""
    picks = []
    for target in range(0, int(frames[-1]) + 1, every_frames):
        index = int(np.searchsorted(frames, target))
        if index < len(frames) and (not picks or index != picks[-1]):
            picks.append(index)
    return picks


def write_gif(film: Any, path: Path, frames_per_second: float = 25.0) -> None:
    """An animated GIF of every picture of the film (looping)."""
    images = [Image.fromarray(image) for image in film.images]
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / frames_per_second), loop=0)


def write_actions_csv(films: Sequence[Any], path: Path) -> None:
    """``film, frame, reward, action_0, ...``: one row per picture of each film."""
    dims = max(f.actions.shape[1] for f in films)
    with path.open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(["film", "frame", "reward", *(f"action_{dimension}" for dimension in range(dims))])
        for film in films:
            for frame, reward, action in zip(film.frames, film.rewards, film.actions):
                values = ("" if np.isnan(v) else float(v) for v in (reward, *action))
                writer.writerow([film.label, int(frame), *values])
