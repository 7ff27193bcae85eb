"""The paper's Figures 6 and 7 (``python -m sb3_collapse.probe film``): a filmstrip PNG with the actions under each
strip, an animated GIF per film and the actions as CSV. See docs/figures.md."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from PIL import Image
from stable_baselines3.common.utils import get_device

from sb3_collapse.common.progress import progress_bar
from sb3_collapse.drqv2.checks import check_device
from sb3_collapse.errors import InputError
from sb3_collapse.probe.checkpoints import checkpoint_labels, load_checkpoint
from sb3_collapse.probe.film import FILM_FRAMES, FILM_SIZE, Film, film_episode
from sb3_collapse.probe.pipeline import check_checkpoint_files
from sb3_collapse.probe.rollouts import resolve_env_config
from sb3_collapse.report.style import OKABE_ITO, frames_axis
from sb3_collapse.staged_outputs import StagedOutputs

STRIP_EVERY_FRAMES = 30
"""Frames between two pictures of the filmstrip."""


def plot_filmstrip(films: Sequence[Film], path: Path, every_frames: int = STRIP_EVERY_FRAMES, title: str = "") -> None:
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


def write_gif(film: Film, path: Path, frames_per_second: float = 25.0) -> None:
    """An animated GIF of every picture of the film (looping)."""
    images = [Image.fromarray(image) for image in film.images]
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / frames_per_second), loop=0)


def write_actions_csv(films: Sequence[Film], path: Path) -> None:
    """``film, frame, reward, action_0, ...``: one row per picture of each film."""
    dims = max(f.actions.shape[1] for f in films)
    with path.open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(["film", "frame", "reward", *(f"action_{dimension}" for dimension in range(dims))])
        for film in films:
            for frame, reward, action in zip(film.frames, film.rewards, film.actions):
                values = ("" if np.isnan(v) else float(v) for v in (reward, *action))
                writer.writerow([film.label, int(frame), *values])


FILMSTRIP_PNG = "filmstrip.png"
ACTIONS_CSV = "actions.csv"
OUTPUT_FILES = (FILMSTRIP_PNG, "*.gif", ACTIONS_CSV)
"""What ``film`` writes (``actions.csv`` last)."""


def film_to_folder(
    checkpoint_paths: Sequence[str | Path],
    out: str | Path,
    frames: int = FILM_FRAMES,
    size: int = FILM_SIZE,
    every_frames: int = STRIP_EVERY_FRAMES,
    seeds: Sequence[int] = (0,),
    env: str | None = None,
    device: str = "auto",
    overwrite: bool = False,
    progress: bool = True,
) -> list[Path]:
    """
    ``python -m sb3_collapse.probe film``: film every checkpoint from each episode seed into ``out`` (all or nothing).

    :param checkpoint_paths: the agents (full models or snapshots)
    :param out: the output folder
    :param frames: environment frames per film
    :param size: render size of the film, in pixels
    :param every_frames: frames between two pictures of the strip
    :param seeds: episode seeds (one row per checkpoint and seed)
    :param env: the task, when a checkpoint does not say
    :param device: where the networks run
    :param overwrite: replace a previous film in ``out``
    :param progress: show a progress bar
    :return: the written files
    :raises InputError: for bad input
    """
    for name, value, low in (("frames", frames, 1), ("size", size, 16), ("every_frames", every_frames, 1)):
        if value < low:
            raise InputError(f"{name} must be >= {low}, got {value}.", parameter=name)
    if not seeds:
        raise InputError("seeds must hold at least one episode seed.", parameter="seeds")
    check_checkpoint_files(checkpoint_paths, same_observations=False)  # each films in its own env
    check_device(device)
    labels = checkpoint_labels(list(checkpoint_paths))
    films = []
    with StagedOutputs(out, OUTPUT_FILES, ACTIONS_CSV, overwrite=overwrite, error=InputError) as staged:
        for path, label in progress_bar(zip(checkpoint_paths, labels), "filming", "checkpoint", progress):
            checkpoint = load_checkpoint(path, device=get_device(device))
            env_config = resolve_env_config(checkpoint.env_config, task_id=env)
            for seed in seeds:
                name = f"{label} ({checkpoint.frames:,} training frames), episode seed {seed}"
                films.append(film_episode(checkpoint.model, env_config, name, frames, size, seed))
                write_gif(films[-1], staged.path(f"{label.replace('/', '_')}_seed{seed}.gif"))
        task = films[0].task
        plot_filmstrip(
            films,
            staged.path(FILMSTRIP_PNG),
            every_frames,
            f"{task}: frames 0-{frames} of an episode (every {every_frames}th), and the actions taken",
        )
        write_actions_csv(films, staged.path(ACTIONS_CSV))
        written = staged.commit()
    print("Wrote " + ", ".join(str(f) for f in written))
    return written
