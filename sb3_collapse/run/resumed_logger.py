"""The SB3 logger of a run resumed from a checkpoint: its logs continue after the checkpoint (docs/checkpoints.md)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from stable_baselines3.common.logger import (
    CSVOutputFormat,
    Logger,
    TensorBoardOutputFormat,
    configure,
    make_output_format,
)
from torch.utils.tensorboard import SummaryWriter

from sb3_collapse.protocol import PROGRESS_CSV

if TYPE_CHECKING:
    from sb3_collapse.run.checkpoints import LoadedCheckpoint


class _ResumedCSVOutputFormat(CSVOutputFormat):
    """SB3's CSV log continuing an existing file: its header gives the columns, rows are appended."""

    def __init__(self, filename: str) -> None:
        self.file = open(filename, "r+")  # noqa: SIM115 - closed by Logger.close
        header = self.file.readline().strip()
        self.keys = header.split(",") if header else []
        self.file.seek(0, os.SEEK_END)
        self.separator, self.quotechar = ",", '"'


class _ResumedTensorBoardOutputFormat(TensorBoardOutputFormat):
    """TensorBoard events from ``purge_step`` on: TensorBoard drops the earlier files' events at or after it."""

    def __init__(self, folder: str, purge_step: int) -> None:
        self.writer = SummaryWriter(log_dir=folder, purge_step=purge_step)
        self._is_closed = False


def resumed_logger(run_dir: Path, formats: Sequence[str], checkpoint: LoadedCheckpoint | None) -> Logger:
    """The run's SB3 logger in ``formats``: a new one (``checkpoint`` ``None``), or one that continues the CSV log and
    the TensorBoard events after ``checkpoint`` with the values not dumped yet (its resume wrote the CSV files back)."""

    if checkpoint is None:
        return configure(str(run_dir), list(formats))
    state = checkpoint.state
    outputs = []
    for kind in formats:
        if kind == "csv" and (run_dir / PROGRESS_CSV).is_file():
            outputs.append(_ResumedCSVOutputFormat(str(run_dir / PROGRESS_CSV)))
        elif kind == "tensorboard":
            outputs.append(_ResumedTensorBoardOutputFormat(str(run_dir), purge_step=state["num_timesteps"] + 1))
        else:
            outputs.append(make_output_format(kind, str(run_dir)))
    logger = Logger(str(run_dir), outputs)
    logger.name_to_value.update(state["logger"]["values"])
    logger.name_to_count.update(state["logger"]["counts"])
    logger.name_to_excluded.update(state["logger"]["excluded"])
    return logger
