"""Training runs on disk: the host loop around the jitted trainer.

A run directory holds ``config.json`` (the resolved :class:`ExperimentConfig`), ``progress.csv``
(one row per iteration, mean over seeds; with several seeds ``progress_seeds.csv`` has one row
per iteration and seed),
TensorBoard event files (and a Weights & Biases run with ``wandb``: :mod:`mash.runs.loggers`), Orbax
``checkpoints/``, ``summary.json`` and ``reward_curve.png``.
The loop (:func:`train`) only calls a :class:`mash.rl.trainer.Trainer`, whichever its variant
(one seed, many seeds, a mesh); what happens between its jitted calls (logs, scalar
loggers, checkpoints, the progress bar) are :class:`Hook` s, and signals :class:`StopOnSignals`.
SIGINT/SIGTERM end the run after the call in flight, with a complete checkpoint to ``--resume`` from
(a second signal aborts at once; Orbax's atomic step directories still leave the last complete
checkpoint loadable). Files a resume rewrites (``progress.csv``, ``summary.json``) are replaced
atomically. A checkpoint step that does not restore is skipped with a warning
(:func:`mash.runs.checkpoint.restore_latest`); on resume such newer steps are moved to
``checkpoints_unrestorable/``, never deleted. A kill (SIGKILL, a power cut) loses at most the calls
since the last complete checkpoint: a resume drops the log rows past it, and a torn last row. A
checkpoint or run file the storage refuses (a full disk, a quota, a read-only file system) ends the
run with one line, :class:`mash.errors.StorageError`, naming it and the last complete checkpoint.
Evaluation, export and sim-to-sim load a run's policy without this module:
:mod:`mash.deploy.policy`.

Several devices (``jax.device_count() > 1``: one process with several GPUs, or several processes
joined by :func:`mash.rl.distributed.initialize`) train one seed with its env batch split over a
mesh of all of them (:func:`build_trainer`); ``num_envs`` must divide by the device count. Every
process runs the same loop; only process 0 writes run files and draws the progress bar, while
checkpoint saves and restores are collective (every process takes part). ``--seeds N > 1`` keeps the
seed-vmapped single-device trainer: in one process it trains on the first device (with a warning),
across processes it is refused. ``docs/multi_device.md`` has the commands.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any, Iterator, NamedTuple

import jax
import numpy as np
from matplotlib.figure import Figure
from tqdm import tqdm

from mash import errors

# Shared with deployment code, which loads policies without this module (mash.deploy.policy).
from mash.deploy.policy import RunError, read_progress  # noqa: F401
from mash.rl import distributed
from mash.rl import trainer as trainer_lib
from mash.rl.config import derived as derived_sizes
from mash.runs import checkpoint, experiment, loggers

BASE_COLUMNS = ("iteration", "env_steps", "wall_s", "episode_reward", "episode_length")


def is_run(path: Path) -> bool:
  return (path / "config.json").is_file()


def check_new_run_dir(out: Path) -> None:
  """Refuses (:class:`RunError`, one line) a new run's folder that is a file or already holds a
  run; whether it can be written is the caller's to check before any work."""
  if out.exists() and not out.is_dir():
    raise RunError(f"'{out}' is a file, not a run directory")
  if is_run(out):
    raise RunError(f"'{out}' already holds a run; pass --resume {out} to continue it, or choose "
                   "another --out")


def _write_atomic(path: Path, text: str) -> None:
  """Writes ``text`` to ``path`` through a temporary file and a rename: a crash leaves either the
  old file or the new one, never a truncated one."""
  tmp = path.with_name(f".{path.name}.tmp")
  tmp.write_text(text)
  os.replace(tmp, path)


def load_config(run_dir: str | os.PathLike) -> experiment.ExperimentConfig:
  """The config of an existing run; RunError when ``run_dir`` is not one."""
  path = Path(run_dir)
  if not path.is_dir():
    raise RunError(f"run directory '{path}' does not exist")
  if not is_run(path):
    raise RunError(f"'{path}' is not a run directory (no config.json)")
  try:
    return experiment.from_json((path / "config.json").read_text())
  except experiment.ConfigError as e:
    raise RunError(f"'{path}/config.json': {e}") from None


def uses_mesh(cfg: experiment.ExperimentConfig) -> bool:
  """Whether :func:`build_trainer` splits ``cfg``'s env batch over every device: a one-seed run
  where there are several devices (several seeds train on one device)."""
  return jax.device_count() > 1 and cfg.seeds == 1


def build_trainer(cfg: experiment.ExperimentConfig) -> trainer_lib.Trainer:
  """The trainer :func:`train` builds for ``cfg``: on the global mesh
  (:func:`mash.rl.distributed.global_mesh`) when :func:`uses_mesh`, else on one device,
  seed-vmapped when ``cfg.seeds > 1``."""
  mesh = distributed.global_mesh() if uses_mesh(cfg) else None
  return trainer_lib.make_trainer(cfg.train, experiment.make_env(cfg), seeds=cfg.seeds, mesh=mesh)


def with_fresh_episodes(trainer: trainer_lib.Trainer, state, iteration: int):
  """``state`` (restored without env states) with every env on a fresh episode, drawn with keys
  of ``iteration`` and the curriculum clock (``info['env_steps']``) at ``iteration *
  unroll_length``, as it would have read: running episode returns and lengths restart at zero."""
  fresh = trainer.init(trainer_lib.fold(trainer, iteration + 1),
                       iteration * trainer.config.unroll_length)
  episodes = state.episodes.replace(running_return=fresh.episodes.running_return,
                                    running_length=fresh.episodes.running_length,
                                    running_paper_return=fresh.episodes.running_paper_return)
  return state.replace(env_state=fresh.env_state, episodes=episodes)


def restore_run(run_dir: str | os.PathLike, trainer: trainer_lib.Trainer,
                fields: tuple[str, ...] | None = None,
                iteration: int | None = None) -> checkpoint.Restored:
  """The newest checkpoint of a run that restores (older ones are tried, with a warning, when
  newer ones are torn), or the one saved at ``iteration``; RunError (one line) when there is
  none."""
  try:
    restored = checkpoint.restore_latest(
        Path(run_dir) / "checkpoints", trainer.state_shapes(), fields, step=iteration)
  except checkpoint.CheckpointError as e:
    raise RunError(str(e)) from None
  if restored is None:
    raise RunError(f"'{run_dir}' has no complete checkpoint (it was stopped before its first "
                   "checkpoint was saved)")
  return restored


class StopOnSignals:
  """Signal handling for the host loop: inside ``with``, SIGINT/SIGTERM become a request to stop
  after the call in flight (a second signal aborts at once, ``KeyboardInterrupt``); the handlers
  there were before come back on exit. :meth:`requested` is asked once per call; across processes
  it is a collective, so that every process stops after the same call (a signal may reach only
  some of them)."""

  def __init__(self, verbose: bool = True):
    self.verbose = verbose
    self.signum = 0
    self._old = {}

  def _handle(self, signum, frame):
    if self.signum:  # a second signal: stop now
      raise KeyboardInterrupt
    self.signum = int(signum)
    if self.verbose:
      print(
          f"\nsignal {signal.Signals(signum).name}: finishing the current call and saving a "
          "checkpoint (send again to abort)", flush=True)

  def __enter__(self) -> "StopOnSignals":
    self._old = {s: signal.signal(s, self._handle) for s in (signal.SIGINT, signal.SIGTERM)}
    return self

  def __exit__(self, *exc) -> None:
    for s, h in self._old.items():
      # None: a handler installed outside Python (jax.distributed's preemption notifier catches
      # SIGTERM), which Python cannot reinstate; ours stays, harmless once the loop is over.
      if h is not None:
        signal.signal(s, h)

  def requested(self) -> str | None:
    """The name of the signal that asks the run to stop (the first one any process got), or
    None."""
    signums = distributed.allgather_ints(self.signum)
    first = signums[np.flatnonzero(signums)]
    return signal.Signals(int(first[0])).name if first.size else None


def _rows(metrics: dict[str, np.ndarray], first_iteration: int, env_steps_per_iteration: int,
          wall_s: float, seeds: int) -> tuple[list[dict[str, float]], list[dict[str, float]]]:
  """Turns one call's metrics into progress rows (mean over seeds) and per-seed rows."""
  keys = (["episode_reward", "episode_length", "paper_episode_reward"] +
          sorted(k for k in metrics if k.startswith("reward/")))
  extra = sorted(k for k in metrics if k not in keys)
  per_seed = {k: np.asarray(metrics[k]).reshape(seeds, -1) for k in keys + extra}
  n = per_seed["episode_reward"].shape[1]
  rows, seed_rows = [], []
  for i in range(n):
    it = first_iteration + i + 1
    base = {"iteration": it, "env_steps": it * env_steps_per_iteration, "wall_s": round(wall_s, 3)}
    rows.append({**base, **{k: float(per_seed[k][:, i].mean()) for k in keys + extra}})
    for s in range(seeds):
      seed_rows.append({**base, "seed": s, **{k: float(per_seed[k][s, i]) for k in keys}})
  return rows, seed_rows


def _row_iteration(row: dict[str | None, Any]) -> int | None:
  """The iteration of a whole CSV row (every column there, none extra), else None."""
  if None in row or any(v is None for v in row.values()):
    return None
  try:
    return int(row["iteration"])
  except (KeyError, ValueError):
    return None


def _wall_at(out: Path, iteration: int, previous: dict[str, Any]) -> float:
  """Seconds the run had trained when it reached ``iteration``, the restored checkpoint: that row's
  ``wall_s`` in ``progress.csv``. A kill writes no ``summary.json``, and one left by an earlier
  stop predates the newer checkpoints, so the summary is only the fallback (no such row)."""
  if not iteration:
    return 0.0
  path = out / "progress.csv"
  if path.exists():
    text = path.read_text(errors="replace")
    for row in csv.DictReader(io.StringIO(text[:text.rfind("\n") + 1])):
      if _row_iteration(row) == iteration:
        try:
          return float(row["wall_s"])
        except (KeyError, ValueError):
          break
  return float(previous.get("wall_s", 0.0))


class _CsvLog:
  """Appends rows to a CSV, writing the header once. On resume it keeps only the whole rows up to
  ``keep_until``: a write cut short (a kill, a full disk) leaves a last line without its line end,
  which may still parse (``10,...`` cut after ``1`` reads as iteration 1), so it is dropped as
  torn, and so are rows that do not parse."""

  def __init__(self, path: Path, keep_until: int | None):
    self.path = path
    self.header: list[str] | None = None
    if path.exists() and keep_until is not None:
      text = path.read_text(errors="replace")
      reader = csv.DictReader(io.StringIO(text[:text.rfind("\n") + 1]))
      self.header = reader.fieldnames
      kept = [r for r in reader if (it := _row_iteration(r)) is not None and it <= keep_until]
      out = io.StringIO(newline="")
      if self.header is not None:
        w = csv.DictWriter(out, fieldnames=self.header)
        w.writeheader()
        w.writerows(kept)
      _write_atomic(path, out.getvalue())  # empty when even the header was torn

  def write(self, rows: list[dict[str, Any]]) -> None:
    if not rows:
      return
    new = self.header is None
    if new:
      self.header = list(rows[0])
    with self.path.open("a", newline="") as f:
      w = csv.DictWriter(f, fieldnames=self.header, extrasaction="ignore")
      if new:
        w.writeheader()
      w.writerows(rows)


def plot_reward_curve(run_dir: Path) -> None:
  """``reward_curve.png``: the run's mean episode reward against the iteration."""
  p = read_progress(run_dir)
  if not p:
    return
  fig = Figure(figsize=(6, 3.5))
  ax = fig.subplots()
  ax.plot(p["iteration"], p["episode_reward"], label="mean episode reward")
  ax.set_xlabel("iteration")
  ax.set_ylabel("episode reward")
  ax.grid(alpha=0.3)
  fig.tight_layout()
  fig.savefig(run_dir / "reward_curve.png", dpi=120)


def _set_aside(out: Path, steps: tuple[int, ...]) -> None:
  """Moves checkpoint steps that do not restore out of the way of new saves (Orbax would silently
  skip saving a step whose directory exists), into ``checkpoints_unrestorable/``."""
  for step in steps:
    dest = out / "checkpoints_unrestorable" / str(step)
    if dest.exists():
      dest = dest.with_name(f"{step}-{time.strftime('%Y%m%d-%H%M%S')}")
    dest.parent.mkdir(exist_ok=True)
    os.replace(out / "checkpoints" / str(step), dest)
    print(f"warning: moved checkpoint step {step}, which does not restore, to '{dest}'",
          file=sys.stderr, flush=True)


def _kept(out: Path, step: int | None) -> str:
  """What a run stopped by a refused write keeps, and how to go on."""
  if step is None:
    return "no checkpoint was saved: free space, then start the run again in another --out"
  return f"checkpoint step {step} is complete: free space, then --resume {out}"


@contextlib.contextmanager
def _writing(what: str, out: Path, kept_step: int | None) -> Iterator[None]:
  """Turns a write the storage refuses (a full disk, a quota, a read-only file system) into one
  :class:`mash.errors.StorageError` line: ``what`` (or the checkpoint step) could not be
  written, why, and the last complete checkpoint, ``kept_step``, to resume from."""
  try:
    yield
  except errors.StorageError as e:  # a checkpoint save: the message names the step
    raise errors.StorageError(f"{e}; {_kept(out, kept_step)}") from None
  except OSError as e:
    if e.errno not in errors.STORAGE_ERRNOS:
      raise
    raise errors.StorageError(f"cannot write {what}: {os.strerror(e.errno)}; "
                              f"{_kept(out, kept_step)}") from None


# Calls after the first (which compiles) timed before the run says how long it will take.
ETA_CALLS = 2


def _expected_duration(call_s: list[float], iterations_per_call: int, remaining: int) -> str:
  """One line: the measured seconds per iteration and when the ``remaining`` iterations end."""
  per_it = float(np.median(call_s)) / iterations_per_call
  left = per_it * remaining
  end = time.strftime("%H:%M", time.localtime(time.time() + left))
  return (f"timed: {per_it:.2f} s per iteration ({1 / per_it:.2f} it/s) after compiling; the "
          f"remaining {remaining} iterations take about {left / 60:.0f} min (done around {end})")


def _agree(error: Exception | None, out: Path) -> None:
  """Raises ``error``; across processes, every process raises when any process has an error (so
  none is left waiting in a collective for one that gave up)."""
  if jax.process_count() > 1:
    failed = distributed.allgather_ints(error is not None)
    if error is None and failed.any():
      error = RunError(f"process {int(np.argmax(failed))} refused the run in '{out}' (its error "
                       "line says why)")
  if error is not None:
    raise error


def _devices(cfg: experiment.ExperimentConfig, trainer: trainer_lib.Trainer | None) -> int:
  """The devices the run's env batch is split over; ConfigError when the config cannot train
  on the devices there are (or with the ``trainer`` given)."""
  processes = jax.process_count()
  if trainer is not None and trainer.seeds != cfg.seeds:
    raise experiment.ConfigError(f"the trainer given trains {trainer.seeds} seed(s), the config "
                                 f"{cfg.seeds}")
  if processes > 1 and cfg.seeds > 1:
    raise experiment.ConfigError(
        f"--seeds {cfg.seeds} cannot train across {processes} processes (several seeds train "
        "in one process, on one device); use --seeds 1 (one run per seed) or one process")
  if trainer is not None:
    devices = trainer.devices
  else:
    devices = jax.device_count() if uses_mesh(cfg) else 1
  if processes > 1 and devices < jax.device_count():
    raise experiment.ConfigError(f"a run over {processes} processes needs a trainer over every "
                                 "process's devices (mash.rl.trainer.make_trainer with a mesh)")
  if devices > 1:
    try:
      derived_sizes(cfg.train, devices)
    except ValueError as e:
      raise experiment.ConfigError(f"{str(e).rstrip('.')}: the env batch is split over all "
                                   f"{devices} devices") from None
  return devices


class _Storage:
  """Where a run writes, and its last complete checkpoint, named when a write is refused."""

  def __init__(self, out: Path, saved: int | None = None):
    self.out, self.saved = out, saved

  def writing(self, what: str):
    return _writing(what, self.out, self.saved)


class Call(NamedTuple):
  """What the host loop hands its hooks after each jitted call.

  Attributes:
    index: the call's number in this sitting, from 0.
    iteration: the iterations done after it.
    rows: its ``progress.csv`` rows, one per iteration (mean over seeds).
    seed_rows: its ``progress_seeds.csv`` rows, one per iteration and seed.
    state: the train state after it (read it before the next call donates it).
    seconds: its wall time (the first call's includes compiling).
    last: whether the loop ends after it (the last call planned, or a stop signal).
  """

  index: int
  iteration: int
  rows: list[dict[str, float]]
  seed_rows: list[dict[str, float]]
  state: Any
  seconds: float
  last: bool


class Hook:
  """One concern of the host loop, called after every jitted call and closed when the loop
  ends, also on an abort. Hooks run in the order :func:`train` gives them."""

  def after_call(self, call: Call) -> None:
    pass

  def close(self) -> None:
    pass


class ProgressLogs(Hook):
  """Appends each call's rows to ``progress.csv`` and, for several seeds, ``progress_seeds.csv``
  (a one-seed run's would repeat ``progress.csv``); on resume, after dropping the rows past
  ``keep_until``, the restored iteration."""

  def __init__(self, storage: _Storage, keep_until: int | None, seeds: int):
    self.storage = storage
    names = ("progress.csv", "progress_seeds.csv")[:2 if seeds > 1 else 1]
    with storage.writing(f"the logs in '{storage.out}'"):
      self.logs = [_CsvLog(storage.out / name, keep_until) for name in names]

  def after_call(self, call: Call) -> None:
    for log, rows in zip(self.logs, (call.rows, call.seed_rows)):
      with self.storage.writing(f"'{log.path}'"):
        log.write(rows)


class ScalarLoggers(Hook):
  """Hands each call's rows to TensorBoard (and Weights & Biases): :mod:`mash.runs.loggers`."""

  def __init__(self, storage: _Storage, cfg: experiment.ExperimentConfig):
    with storage.writing(f"the logs in '{storage.out}'"):
      self.loggers = loggers.make_loggers(storage.out, json.loads(experiment.to_json(cfg)),
                                          cfg.wandb_project if cfg.wandb else None)

  def after_call(self, call: Call) -> None:
    for logger in self.loggers:
      logger.log(call.rows)

  def close(self) -> None:
    for logger in self.loggers:
      logger.close()


class Checkpoints(Hook):
  """Saves the state every ``every`` calls and after the last one (a collective: every process
  runs this hook), and keeps ``storage.saved`` at the last complete step."""

  def __init__(self, storage: _Storage, cfg: experiment.ExperimentConfig,
               fields: tuple[str, ...] | None):
    self.storage, self.cfg, self.fields = storage, cfg, fields
    self.manager = checkpoint.make_manager(storage.out / "checkpoints",
                                           max_to_keep=cfg.keep_checkpoints)

  def after_call(self, call: Call) -> None:
    if (call.index + 1) % self.cfg.checkpoint_every and not call.last:
      return
    with self.storage.writing(f"checkpoint step {call.iteration}"):
      new = checkpoint.save(self.manager, call.iteration, call.state, self.cfg.train,
                            fields=self.fields)
    if not new and distributed.is_primary():
      print(
          f"warning: checkpoint step {call.iteration} was not saved (Orbax found it already in "
          f"'{self.storage.out / 'checkpoints'}')", file=sys.stderr, flush=True)
    self.storage.saved = call.iteration

  def close(self) -> None:
    self.manager.close()


class ProgressBar(Hook):
  """The progress bar (reward, env steps per second), and one line with the expected duration
  once ``ETA_CALLS`` calls after the first are timed."""

  def __init__(self, cfg: experiment.ExperimentConfig, start_iteration: int,
               env_steps_per_call: int, show: bool):
    self.cfg, self.env_steps_per_call = cfg, env_steps_per_call
    self.bar = tqdm(total=cfg.train.num_iterations, initial=start_iteration, disable=not show,
                    unit="it", dynamic_ncols=True)
    self.timed: list[float] = []

  def after_call(self, call: Call) -> None:
    if call.index:
      self.timed.append(call.seconds)
    if len(self.timed) == ETA_CALLS and not call.last:
      self.bar.write(
          _expected_duration(self.timed, self.cfg.train.iterations_per_call,
                             self.cfg.train.num_iterations - call.iteration), file=sys.stderr)
    self.bar.set_postfix(reward=f"{call.rows[-1]['episode_reward']:.3f}",
                         steps_per_s=f"{self.env_steps_per_call / call.seconds:,.0f}")
    self.bar.update(len(call.rows))

  def close(self) -> None:
    self.bar.close()


def _loop(trainer: trainer_lib.Trainer, state, iteration: int, calls: int,
          env_steps_per_iteration: int, wall0: float, hooks: list[Hook],
          stop: StopOnSignals) -> "_Ended":
  """Runs ``calls`` jitted calls from ``iteration``, handing each to the hooks; ends early after
  the call during which a stop signal came (:class:`_Ended`)."""
  seconds, stop_signal, last_reward = [], None, None
  with stop:
    for index in range(calls):
      t0 = time.perf_counter()
      state, metrics = trainer.train_epoch(state)
      metrics = trainer.to_host(metrics)
      seconds.append(time.perf_counter() - t0)
      rows, seed_rows = _rows(metrics, iteration, env_steps_per_iteration,
                              time.perf_counter() - wall0, trainer.seeds)
      iteration, last_reward = rows[-1]["iteration"], rows[-1]["episode_reward"]
      stop_signal = stop.requested()
      call = Call(index, iteration, rows, seed_rows, state, seconds[-1], last=index == calls - 1 or
                  stop_signal is not None)
      for hook in hooks:
        hook.after_call(call)
      if stop_signal is not None:
        break
  return _Ended(iteration, seconds, stop_signal, last_reward)


def _start(trainer: trainer_lib.Trainer, cfg: experiment.ExperimentConfig, storage: _Storage,
           resume: bool) -> tuple[Any, int]:
  """The state to train from and its iteration: restored from the run's checkpoints (moving
  aside the steps that do not restore), or fresh, with ``config.json`` written."""
  out, primary = storage.out, distributed.is_primary()
  if not resume:
    state = trainer.init()
    if primary:
      with storage.writing(f"'{out / 'config.json'}'"):
        out.mkdir(parents=True, exist_ok=True)
        _write_atomic(out / "config.json", experiment.to_json(cfg))
    distributed.barrier("mash.runs.loop.config_written")
    return state, 0
  fields = None if cfg.checkpoint_env_state else checkpoint.LEARNING_FIELDS
  restored = restore_run(out, trainer, fields=fields)
  storage.saved = restored.step
  if primary:
    with storage.writing(f"'{out / 'checkpoints_unrestorable'}'"):
      _set_aside(out, restored.skipped)
  distributed.barrier("mash.runs.loop.set_aside")
  iteration = int(np.asarray(trainer.to_host(restored.state.iteration)).reshape(-1)[0])
  state = restored.state if fields is None else with_fresh_episodes(trainer, restored.state,
                                                                    iteration)
  return state, iteration


def train(
    cfg: experiment.ExperimentConfig, out_dir: str | os.PathLike, resume: bool = False,
    show_progress: bool = True, max_calls: int | None = None,
    trainer: trainer_lib.Trainer | None = None, hooks: tuple[Hook, ...] = ()) -> dict[str, Any]:
  """Trains ``cfg`` into ``out_dir`` (or continues the run there when ``resume``).

  With several devices (``jax.device_count() > 1``) and ``cfg.seeds == 1`` the env batch is split
  over all of them (:func:`build_trainer`); every process of a multi-process run calls
  this with the same arguments, and only process 0 writes run files. With several seeds it trains
  on one device, with a warning (refused across processes). The loop itself only calls the
  trainer; logs, scalar loggers, checkpoints and the progress bar are :class:`Hook` s around it,
  and SIGINT/SIGTERM are :class:`StopOnSignals`.

  Args:
    cfg: the resolved experiment config (on resume, the run's own config).
    out_dir: the run directory; refused when it already holds a run and ``resume`` is false.
    resume: continue from the latest checkpoint in ``out_dir`` that restores.
    show_progress: draw a progress bar (on process 0).
    max_calls: stop after this many jitted calls (tests, interrupted-run demos).
    trainer: a :class:`mash.rl.trainer.Trainer` made beforehand (:func:`build_trainer`, or one of
      another env), to reuse its compiled programs (tests).
    hooks: more :class:`Hook` s, run on every process after the built-in ones (a live plot in a
      notebook, an early stop's bookkeeping); closed with them.

  Returns:
    The summary written to ``summary.json``; ``interrupted`` is true (and ``signal`` names the
    signal) when SIGINT/SIGTERM stopped the run early.

  Raises:
    RunError: ``out_dir`` cannot be used as asked (one line).
    mash.runs.experiment.ConfigError: the config does not fit the devices (one line).
    mash.errors.StorageError: the storage refused a checkpoint or a run file (a full disk, a
      quota, a read-only file system); one line naming it and the last complete checkpoint,
      which stays loadable (``resume`` goes on from it once there is space).
  """
  out = Path(out_dir)
  primary = distributed.is_primary()
  cfg, devices = _accept(cfg, out, resume, trainer)
  if trainer is None:
    if devices == 1 and jax.device_count() > 1 and primary:
      print(
          f"warning: --seeds {cfg.seeds} trains on one of the {jax.device_count()} devices "
          "(only a one-seed run splits its env batch over devices)", file=sys.stderr, flush=True)
    trainer = build_trainer(cfg)
  derived = derived_sizes(cfg.train, devices)

  storage = _Storage(out)
  state, start_iteration = _start(trainer, cfg, storage, resume)
  previous = json.loads(
      (out / "summary.json").read_text()) if (resume and (out / "summary.json").exists()) else {}
  wall0 = time.perf_counter() - _wall_at(out, start_iteration if resume else 0, previous)
  calls = -(-(cfg.train.num_iterations - start_iteration) // cfg.train.iterations_per_call)
  calls = calls if max_calls is None else min(calls, max_calls)

  run_hooks: list[Hook] = []
  try:
    if primary:
      run_hooks += [
          ProgressLogs(storage, start_iteration if resume else None, cfg.seeds),
          ScalarLoggers(storage, cfg)
      ]
    run_hooks += [
        Checkpoints(storage, cfg, None if cfg.checkpoint_env_state else checkpoint.LEARNING_FIELDS),
        ProgressBar(cfg, start_iteration, derived.env_steps_per_call, show_progress and primary),
        *hooks
    ]
    ended = _loop(trainer, state, start_iteration, calls, derived.env_steps_per_iteration, wall0,
                  run_hooks, StopOnSignals(verbose=primary))
  finally:  # also on an abort (a second signal): Orbax saves are atomic anyway
    for hook in run_hooks:
      hook.close()
  summary = _summary(cfg, out, storage, ended, start_iteration, previous, wall0, devices)
  distributed.barrier("mash.runs.loop.done")
  return summary


def _accept(cfg: experiment.ExperimentConfig, out: Path, resume: bool,
            trainer: trainer_lib.Trainer | None) -> tuple[experiment.ExperimentConfig, int]:
  """The config to train (on resume, the run's own) and the devices its env batch is split
  over, once every process agrees that ``out`` can be used as asked (else every process raises
  the one-line error)."""
  error, devices = None, 1
  try:
    if resume and out.is_file():
      raise RunError(f"'{out}' is a file, not a run directory")
    if resume:
      cfg = load_config(out)
    else:
      check_new_run_dir(out)
    devices = _devices(cfg, trainer)
  except (RunError, experiment.ConfigError) as e:
    error = e
  _agree(error, out)  # also the barrier before anything is written
  return cfg, devices


class _Ended(NamedTuple):
  """How the loop ended: the iteration reached, each call's seconds, the stop signal's name (or
  None) and the last row's episode reward (None without a call)."""

  iteration: int
  seconds: list[float]
  stop_signal: str | None
  last_reward: float | None


def _summary(cfg: experiment.ExperimentConfig, out: Path, storage: _Storage, ended: _Ended,
             start_iteration: int, previous: dict[str, Any], wall0: float,
             devices: int) -> dict[str, Any]:
  """Writes the reward curve and ``summary.json`` (process 0) and returns the summary."""
  primary = distributed.is_primary()
  derived = derived_sizes(cfg.train, devices)
  if primary:
    with storage.writing(f"'{out / 'reward_curve.png'}'"):
      plot_reward_curve(out)
  if ended.iteration > start_iteration:
    final_reward = ended.last_reward
  elif primary and ended.iteration:
    final_reward = read_progress(out)["episode_reward"][-1].item()
  else:
    final_reward = previous.get("final_episode_reward")
  seconds = ended.seconds
  steady = float(np.median(seconds[1:])) if len(seconds) > 1 else None
  summary = {
      "task":
          cfg.task,
      "algo":
          cfg.algo,
      "preset":
          cfg.preset,
      "ablation":
          cfg.ablation,
      "seeds":
          cfg.seeds,
      "iterations":
          ended.iteration,
      "env_steps":
          ended.iteration * derived.env_steps_per_iteration,
      "wall_s":
          time.perf_counter() - wall0,
      "first_call_s":
          seconds[0] if seconds else None,
      "train_env_steps_per_s":
          (derived.env_steps_per_call * cfg.seeds / steady) if steady else None,
      "final_episode_reward":
          final_reward,
      "interrupted":
          ended.stop_signal is not None,
      "signal":
          ended.stop_signal,
      "backend":
          jax.default_backend(),
      "devices":
          devices,
      "processes":
          jax.process_count(),
  }
  if primary:
    with storage.writing(f"'{out / 'summary.json'}'"):
      _write_atomic(out / "summary.json", json.dumps(summary, indent=2))
  return summary
