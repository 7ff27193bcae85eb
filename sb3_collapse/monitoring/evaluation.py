"""The periodic evaluation of a training run (:class:`PeriodicEvaluation`), as the reference evaluates."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_collapse.monitoring.callbacks import FrameScheduleCallback
from sb3_collapse.protocol import EVAL_FIELDS, append_csv_rows


class PeriodicEvaluation(FrameScheduleCallback):
    """
    Deterministic evaluation at frame 0 and every ``every_frames`` frames, logged as ``eval/...``, appended to
    ``csv_path``, kept in :attr:`rows`; then ``callback_after_eval``, as SB3's ``EvalCallback``. See docs/monitoring.md.

    :param eval_env: evaluation environment (same pixel settings as the training one)
    :param every_frames: frames between evaluations
    :param episodes: episodes per evaluation
    :param csv_path: CSV file with the columns :data:`~sb3_collapse.protocol.EVAL_FIELDS`
    :param callback_after_eval: callback called after every evaluation (``None``: none)
    """

    period_parameter = "every_frames"
    check_at_start = True
    state_attributes = (*FrameScheduleCallback.state_attributes, "rows")

    def __init__(
        self,
        eval_env: Any,
        every_frames: int,
        episodes: int,
        csv_path: Path,
        callback_after_eval: BaseCallback | None = None,
    ) -> None:
        super().__init__(every_frames)
        self.eval_env = eval_env
        self.episodes = episodes
        self.csv_path = csv_path
        self.callback_after_eval = callback_after_eval
        if callback_after_eval is not None:
            callback_after_eval.parent = self
        self.start_time = time.time()
        self.rows: list[dict[str, float]] = []

    def _init_callback(self) -> None:
        super()._init_callback()
        if self.callback_after_eval is not None:
            self.callback_after_eval.init_callback(self.model)

    def _on_check(self, count: int) -> bool:
        self.evaluate()
        return self._after_eval()

    def _after_eval(self) -> bool:
        return self.callback_after_eval is None or self.callback_after_eval.on_step()

    def _run_episodes(self, prefix: str) -> dict[str, float]:
        """Evaluate now and log the result under ``<prefix>/...``; return the row."""
        rewards, _ = evaluate_policy(
            self.model, self.eval_env, n_eval_episodes=self.episodes, deterministic=True, return_episode_rewards=True
        )
        row = {
            "frame": self.frames,
            "step": self.model.num_timesteps,
            "mean_reward": float(np.mean(rewards)),
            "std_reward": float(np.std(rewards)),
            "episodes": len(rewards),
            "wall_time_s": round(time.time() - self.start_time, 1),
        }
        self.logger.record(f"{prefix}/mean_reward", row["mean_reward"])
        self.logger.record(f"{prefix}/std_reward", row["std_reward"])
        self.logger.record(f"{prefix}/frames", row["frame"])
        self.logger.dump(step=self.model.num_timesteps)
        return row

    def evaluate(self) -> dict[str, float]:
        """A scheduled evaluation: evaluate now, log the result and append it to the CSV; return the CSV row."""
        row = self._run_episodes("eval")
        append_csv_rows(self.csv_path, EVAL_FIELDS, [row])
        self.rows.append(row)
        return row

    def evaluate_saved_model(self) -> dict[str, float]:
        """Evaluate the final model as ``eval_saved_model/...`` (not in the CSV), then ``callback_after_eval``."""
        row = self._run_episodes("eval_saved_model")
        self._after_eval()
        return row
