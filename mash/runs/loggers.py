"""Scalar loggers of a training run: TensorBoard always, Weights & Biases when asked.

The host loop (:func:`mash.runs.loop.train`) hands every iteration's row of ``progress.csv`` to each
logger of :func:`make_loggers`; only process 0 logs. W&B is an optional extra
(``pip install -e ".[wandb]"``) switched on by one setting, ``--set wandb=true``; the project is
``wandb_project``, the run is named after its directory, and a resumed run continues the same
W&B run (its id is kept in ``DIR/wandb_id``). ``WANDB_MODE=offline`` (or ``disabled``) works as
W&B documents: offline runs are written under ``DIR/wandb/`` for a later ``wandb sync``.
"""

from __future__ import annotations

import importlib.util
import secrets
from pathlib import Path
from typing import Any, Mapping, Protocol, Sequence

from tensorboardX import SummaryWriter

# Row columns that are the step axis, not logged as scalars.
STEP_COLUMNS = ("iteration", "env_steps", "wall_s")
WANDB_ID_FILE = "wandb_id"


class Logger(Protocol):

  def log(self, rows: Sequence[Mapping[str, float]]) -> None:
    """Logs rows of ``progress.csv`` (each with its ``iteration``)."""

  def close(self) -> None:
    """Flushes and closes."""


def wandb_installed() -> bool:
  return importlib.util.find_spec("wandb") is not None


class TensorBoardLogger:
  """Every column of a row as a scalar at its iteration, in ``DIR/tensorboard/``."""

  def __init__(self, out: Path):
    self.writer = SummaryWriter(str(out / "tensorboard"))

  def log(self, rows: Sequence[Mapping[str, float]]) -> None:
    for r in rows:
      for k, v in r.items():
        if k not in STEP_COLUMNS:
          self.writer.add_scalar(k, v, r["iteration"])

  def close(self) -> None:
    self.writer.close()


class WandbLogger:
  """Every column of a row at its iteration (``env_steps`` and ``wall_s`` as columns too, so W&B
  can plot against either), in one W&B run per run directory."""

  def __init__(self, out: Path, project: str, config: Mapping[str, Any]):
    import wandb
    id_file = out / WANDB_ID_FILE
    run_id = id_file.read_text().strip() if id_file.is_file() else secrets.token_hex(4)
    self.run = wandb.init(project=project, name=out.name, id=run_id, resume="allow", dir=str(out),
                          config=dict(config))
    id_file.write_text(run_id + "\n")

  def log(self, rows: Sequence[Mapping[str, float]]) -> None:
    for r in rows:
      self.run.log({k: v for k, v in r.items() if k != "iteration"}, step=int(r["iteration"]))

  def close(self) -> None:
    self.run.finish()


def make_loggers(out: Path, config: Mapping[str, Any], wandb_project: str | None) -> list[Logger]:
  """The loggers of a run in ``out``: TensorBoard, and Weights & Biases in ``wandb_project``
  unless None; ``config`` is the run's resolved config as a JSON-ready mapping (W&B shows it)."""
  loggers: list[Logger] = [TensorBoardLogger(out)]
  if wandb_project is not None:
    loggers.append(WandbLogger(out, wandb_project, config))
  return loggers
