"""Training runs on disk: the host loop around the jitted trainer.

A run directory holds ``config.json`` (the resolved :class:`ExperimentConfig`), ``progress.csv``
(one row per iteration, mean over seeds; ``progress_seeds.csv`` has one row per seed),
TensorBoard event files (and a Weights & Biases run with ``wandb``: :mod:`mash.loggers`), Orbax
``checkpoints/``, ``summary.json`` and ``reward_curve.png``.
Between jitted calls the host only logs, checkpoints and draws the progress bar. SIGINT/SIGTERM
end the run after the call in flight, with a complete checkpoint to ``--resume`` from (a second
signal aborts at once; Orbax's atomic step directories still leave the last complete checkpoint
loadable). Files a resume rewrites (``progress.csv``, ``summary.json``) are replaced atomically. A
checkpoint step that does not restore is skipped with a warning (:func:`mash.checkpoint.restore_latest`);
on resume such newer steps are moved to ``checkpoints_unrestorable/``, never deleted. A kill
(SIGKILL, a power cut) loses at most the calls since the last complete checkpoint: a resume drops
the log rows past it, and a torn last row. A checkpoint or run file the storage refuses (a full
disk, a quota, a read-only file system) ends the run with one line,
:class:`mash.checkpoint.StorageError`, naming it and the last complete checkpoint.
Evaluation, export and sim-to-sim load a run's policy without this module: :mod:`mash.policy`.

Several devices (``jax.device_count() > 1``: one process with several GPUs, or several processes
joined by :func:`mash.distributed.initialize`) train one seed with its env batch split over a mesh of
all of them (:mod:`mash.distributed`); ``num_envs`` must divide by the device count. Every process
runs the same loop; only process 0 writes run files and draws the progress bar, while checkpoint
saves and restores are collective (every process takes part). ``--seeds N > 1`` keeps the seed-vmapped
single-device trainer: in one process it trains on the first device (with a warning), across
processes it is refused. ``docs/multi_device.md`` has the commands.
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
from typing import Any, Iterator

import jax
import numpy as np

from mash import checkpoint
from mash import distributed
from mash import experiment
from mash import loggers
from mash import train as train_lib
# Shared with deployment code, which loads policies without this module (mash.policy).
from mash.policy import RunError, read_progress  # noqa: F401

BASE_COLUMNS = ("iteration", "env_steps", "wall_s", "episode_reward", "episode_length")


def is_run(path: Path) -> bool:
  return (path / "config.json").is_file()


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


def build_trainer(cfg: experiment.ExperimentConfig):
  """The (seed-vmapped when ``cfg.seeds > 1``) trainer of a config."""
  env = experiment.make_env(cfg)
  trainer = train_lib.make_train(cfg.train, env)
  if cfg.seeds > 1:
    trainer = train_lib.make_seed_trainer(trainer)
  return trainer


def build_distributed_trainer(cfg: experiment.ExperimentConfig,
                              mesh: jax.sharding.Mesh | None = None
                              ) -> distributed.DistributedTrainer:
  """The one-seed trainer of a config with its env batch split over ``mesh`` (default: every
  device of every process, :func:`mash.distributed.global_mesh`)."""
  mesh = distributed.global_mesh() if mesh is None else mesh
  return distributed.make_distributed_trainer(cfg.train, experiment.make_env(cfg), mesh)


def _is_mesh(trainer) -> bool:
  return isinstance(trainer, distributed.DistributedTrainer)


def init_state(trainer, cfg: experiment.ExperimentConfig, salt: int = 0,
               env_steps: int | None = None):
  """A fresh train state from the config's seed(s); a non-zero ``salt`` is folded into every key
  (fresh env states for a resume from a checkpoint without them); ``env_steps``: the envs'
  curriculum clock at their first episodes (``None``: a fresh run's)."""
  fold = (lambda key: jax.random.fold_in(key, salt)) if salt else (lambda key: key)
  if cfg.seeds > 1 and not _is_mesh(trainer):
    return trainer.init(jax.vmap(fold)(train_lib.seed_keys(cfg.train.seed, cfg.seeds)), env_steps)
  return trainer.init(fold(jax.random.PRNGKey(cfg.train.seed)), env_steps)


def with_fresh_episodes(trainer, cfg: experiment.ExperimentConfig, state, iteration: int):
  """``state`` (restored without env states) with every env on a fresh episode, drawn with keys
  of ``iteration`` and the curriculum clock (``info['env_steps']``) at ``iteration *
  unroll_length``, as it would have read: running episode returns and lengths restart at zero."""
  fresh = init_state(trainer, cfg, salt=iteration + 1,
                     env_steps=iteration * cfg.train.unroll_length)
  episodes = state.episodes.replace(running_return=fresh.episodes.running_return,
                                    running_length=fresh.episodes.running_length,
                                    running_paper_return=fresh.episodes.running_paper_return)
  return state.replace(env_state=fresh.env_state, episodes=episodes)


def state_shapes(trainer, cfg: experiment.ExperimentConfig):
  """Shapes and dtypes of the train state, without running ``init`` (restore template); for a
  :class:`mash.distributed.DistributedTrainer` also the global shardings, so that every process
  reads only its own shards."""
  if _is_mesh(trainer):
    return distributed.global_state_shapes(trainer.trainer, trainer.mesh,
                                           jax.random.PRNGKey(cfg.train.seed))
  if cfg.seeds > 1:
    return jax.eval_shape(trainer.init, train_lib.seed_keys(cfg.train.seed, cfg.seeds))
  return jax.eval_shape(trainer.init, jax.random.PRNGKey(cfg.train.seed))


def restore_run(run_dir: str | os.PathLike, trainer, cfg: experiment.ExperimentConfig,
                fields: tuple[str, ...] | None = None,
                iteration: int | None = None) -> checkpoint.Restored:
  """The newest checkpoint of a run that restores (older ones are tried, with a warning, when
  newer ones are torn), or the one saved at ``iteration``; RunError (one line) when there is
  none."""
  try:
    restored = checkpoint.restore_latest(Path(run_dir) / "checkpoints", state_shapes(trainer, cfg),
                                         fields, step=iteration)
  except checkpoint.CheckpointError as e:
    raise RunError(str(e)) from None
  if restored is None:
    raise RunError(f"'{run_dir}' has no complete checkpoint (it was stopped before its first "
                   "checkpoint was saved)")
  return restored


@contextlib.contextmanager
def _stop_on_signals(verbose: bool = True) -> Iterator[dict[str, Any]]:
  """Turns SIGINT/SIGTERM into a flag the loop checks between jitted calls (``flag['signal']``
  names the first signal, ``flag['signum']`` is its number, 0 before one)."""
  flag: dict[str, Any] = {"stop": False, "signal": None, "signum": 0}

  def handler(signum, frame):
    if flag["stop"]:  # a second signal: stop now
      raise KeyboardInterrupt
    flag["stop"] = True
    flag["signal"] = signal.Signals(signum).name
    flag["signum"] = int(signum)
    if verbose:
      print(f"\nsignal {flag['signal']}: finishing the current call and saving a "
            "checkpoint (send again to abort)", flush=True)

  old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
  try:
    yield flag
  finally:
    for s, h in old.items():
      # None: a handler installed outside Python (jax.distributed's preemption notifier catches
      # SIGTERM), which Python cannot reinstate; ours stays, harmless once the loop is over.
      if h is not None:
        signal.signal(s, h)


def _rows(metrics: dict[str, np.ndarray], first_iteration: int, env_steps_per_iteration: int,
          wall_s: float, seeds: int) -> tuple[list[dict[str, float]], list[dict[str, float]]]:
  """Turns one call's metrics into progress rows (mean over seeds) and per-seed rows."""
  keys = (["episode_reward", "episode_length", "paper_episode_reward"]
          + sorted(k for k in metrics if k.startswith("reward/")))
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
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  p = read_progress(run_dir)
  if not p:
    return
  fig, ax = plt.subplots(figsize=(6, 3.5))
  ax.plot(p["iteration"], p["episode_reward"], label="mean episode reward")
  ax.set_xlabel("iteration")
  ax.set_ylabel("episode reward")
  ax.grid(alpha=0.3)
  fig.tight_layout()
  fig.savefig(run_dir / "reward_curve.png", dpi=120)
  plt.close(fig)


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
  :class:`mash.checkpoint.StorageError` line: ``what`` (or the checkpoint step) could not be
  written, why, and the last complete checkpoint, ``kept_step``, to resume from."""
  try:
    yield
  except checkpoint.StorageError as e:  # a checkpoint save: the message names the step
    raise checkpoint.StorageError(f"{e}; {_kept(out, kept_step)}") from None
  except OSError as e:
    if e.errno not in checkpoint.STORAGE_ERRNOS:
      raise
    raise checkpoint.StorageError(f"cannot write {what}: {os.strerror(e.errno)}; "
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


def _sync(name: str) -> None:
  """A barrier across processes (nothing in a one-process run)."""
  if jax.process_count() > 1:
    from jax.experimental import multihost_utils
    multihost_utils.sync_global_devices(name)


def _gather_ints(value: int) -> np.ndarray:
  """``value`` from every process, in process order (a collective; ``[value]`` in one process)."""
  if jax.process_count() == 1:
    return np.array([value])
  from jax.experimental import multihost_utils
  return np.asarray(multihost_utils.process_allgather(np.int32(value))).reshape(-1)


def _agree(error: Exception | None, out: Path) -> None:
  """Raises ``error``; across processes, every process raises when any process has an error (so
  none is left waiting in a collective for one that gave up)."""
  if jax.process_count() > 1:
    failed = _gather_ints(error is not None)
    if error is None and failed.any():
      error = RunError(f"process {int(np.argmax(failed))} refused the run in '{out}' (its error "
                       "line says why)")
  if error is not None:
    raise error


def _plan_devices(cfg: experiment.ExperimentConfig, trainer: Any) -> tuple[bool, int]:
  """Whether to train on the global mesh, and over how many devices; ConfigError when the config
  cannot train on the devices there are."""
  processes = jax.process_count()
  if trainer is not None:
    mesh = _is_mesh(trainer)
    if mesh and cfg.seeds > 1:
      raise experiment.ConfigError(f"--seeds {cfg.seeds}: the distributed trainer trains one seed")
  else:
    mesh = jax.device_count() > 1 and cfg.seeds == 1
    if jax.device_count() > 1 and cfg.seeds > 1 and processes > 1:
      raise experiment.ConfigError(
          f"--seeds {cfg.seeds} cannot train across {processes} processes (several seeds train "
          "in one process, on one device); use --seeds 1 (one run per seed) or one process")
  if processes > 1 and not mesh:
    raise experiment.ConfigError(f"a run over {processes} processes needs the distributed "
                                 "trainer (mash.distributed.DistributedTrainer)")
  devices = (trainer.mesh.size if trainer is not None else jax.device_count()) if mesh else 1
  if mesh:
    try:
      train_lib.derived(cfg.train, devices)
    except ValueError as e:
      raise experiment.ConfigError(f"{str(e).rstrip('.')}: the env batch is split over all "
                                   f"{devices} devices") from None
  return mesh, devices


def train(cfg: experiment.ExperimentConfig, out_dir: str | os.PathLike, resume: bool = False,
          show_progress: bool = True, max_calls: int | None = None,
          trainer: Any = None) -> dict[str, Any]:
  """Trains ``cfg`` into ``out_dir`` (or continues the run there when ``resume``).

  With several devices (``jax.device_count() > 1``) and ``cfg.seeds == 1`` the env batch is split
  over all of them (:func:`build_distributed_trainer`); every process of a multi-process run calls
  this with the same arguments, and only process 0 writes run files. With several seeds it trains
  on one device, with a warning (refused across processes).

  Args:
    cfg: the resolved experiment config (on resume, the run's own config).
    out_dir: the run directory; refused when it already holds a run and ``resume`` is false.
    resume: continue from the latest checkpoint in ``out_dir`` that restores.
    show_progress: draw a progress bar (on process 0).
    max_calls: stop after this many jitted calls (tests, interrupted-run demos).
    trainer: ``build_trainer(cfg)`` or ``build_distributed_trainer(cfg)`` (or a
      :class:`mash.distributed.DistributedTrainer` of another env) made beforehand, to reuse its
      compiled programs (tests); it decides between one device and the mesh.

  Returns:
    The summary written to ``summary.json``; ``interrupted`` is true (and ``signal`` names the
    signal) when SIGINT/SIGTERM stopped the run early.

  Raises:
    RunError: ``out_dir`` cannot be used as asked (one line).
    mash.experiment.ConfigError: the config does not fit the devices (one line).
    mash.checkpoint.StorageError: the storage refused a checkpoint or a run file (a full disk, a
      quota, a read-only file system); one line naming it and the last complete checkpoint,
      which stays loadable (``resume`` goes on from it once there is space).
  """
  from tqdm import tqdm

  out = Path(out_dir)
  primary = distributed.is_primary()
  multi = jax.process_count() > 1
  error = None
  try:
    if out.exists() and not out.is_dir():
      raise RunError(f"'{out}' is a file, not a run directory")
    if resume:
      cfg = load_config(out)
    elif out.exists() and is_run(out):
      raise RunError(f"'{out}' already holds a run; pass --resume {out} to continue it, or choose "
                     "another --out")
    on_mesh, devices = _plan_devices(cfg, trainer)
  except (RunError, experiment.ConfigError) as e:
    error = e
  _agree(error, out)  # also the barrier before anything is written
  derived = train_lib.derived(cfg.train, devices)
  if trainer is None and not on_mesh and jax.device_count() > 1 and primary:
    print(f"warning: --seeds {cfg.seeds} trains on one of the {jax.device_count()} devices (only "
          "a one-seed run splits its env batch over devices)", file=sys.stderr, flush=True)

  if trainer is None:
    trainer = build_distributed_trainer(cfg) if on_mesh else build_trainer(cfg)
  to_host = distributed.gather_to_host if on_mesh else jax.device_get
  start_iteration, saved = 0, None
  saved_fields = None if cfg.checkpoint_env_state else checkpoint.LEARNING_FIELDS
  if resume:
    restored = restore_run(out, trainer, cfg, fields=saved_fields)
    saved = restored.step  # the last complete checkpoint, named when a write is refused
    if primary:
      with _writing(f"'{out / 'checkpoints_unrestorable'}'", out, saved):
        _set_aside(out, restored.skipped)
    _sync("mash.runs.set_aside")
    state = restored.state
    start_iteration = int(np.asarray(to_host(state.iteration)).reshape(-1)[0])
    if saved_fields is not None:
      state = with_fresh_episodes(trainer, cfg, state, start_iteration)
  else:
    state = init_state(trainer, cfg)
    if primary:
      with _writing(f"'{out / 'config.json'}'", out, saved):
        out.mkdir(parents=True, exist_ok=True)
        _write_atomic(out / "config.json", experiment.to_json(cfg))
    _sync("mash.runs.config_written")
  manager = checkpoint.make_manager(out / "checkpoints", max_to_keep=cfg.keep_checkpoints)

  progress = seed_log = None
  scalar_loggers = []
  if primary:
    with _writing(f"the logs in '{out}'", out, saved):
      progress = _CsvLog(out / "progress.csv", start_iteration if resume else None)
      seed_log = _CsvLog(out / "progress_seeds.csv", start_iteration if resume else None)
      scalar_loggers = loggers.make_loggers(cfg, out)
  total_calls = -(-(cfg.train.num_iterations - start_iteration) // cfg.train.iterations_per_call)
  if max_calls is not None:
    total_calls = min(total_calls, max_calls)
  bar = tqdm(total=cfg.train.num_iterations, initial=start_iteration,
             disable=not (show_progress and primary), unit="it", dynamic_ncols=True)
  previous = {}
  if (out / "summary.json").exists() and resume:
    previous = json.loads((out / "summary.json").read_text())
  wall0 = time.perf_counter() - float(previous.get("wall_s", 0.0))
  compile_s, call_s, iteration = None, [], start_iteration
  stopped, stop_signal, last_reward = False, None, None
  try:
    with _stop_on_signals(verbose=primary) as flag:
      for call in range(total_calls):
        t0 = time.perf_counter()
        state, metrics = trainer.train_epoch(state)
        metrics = to_host(metrics)
        dt = time.perf_counter() - t0
        if compile_s is None:
          compile_s = dt
        else:
          call_s.append(dt)
        rows, seed_rows = _rows(metrics, iteration, derived.env_steps_per_iteration,
                                time.perf_counter() - wall0, cfg.seeds)
        iteration = rows[-1]["iteration"]
        last_reward = rows[-1]["episode_reward"]
        if primary:
          for log, new_rows in ((progress, rows), (seed_log, seed_rows)):
            with _writing(f"'{log.path}'", out, saved):
              log.write(new_rows)
          for logger in scalar_loggers:
            logger.log(rows)
        stop, stop_signal = flag["stop"], flag["signal"]
        if multi:  # every process stops after the same call (a signal may reach only some)
          signums = _gather_ints(flag["signum"])
          stop = bool(signums.any())
          stop_signal = signal.Signals(int(signums[np.flatnonzero(signums)[0]])).name if stop \
              else None
        last = call == total_calls - 1 or stop
        if (call + 1) % cfg.checkpoint_every == 0 or last:  # collective: every process saves
          with _writing(f"checkpoint step {iteration}", out, saved):
            new = checkpoint.save(manager, iteration, state, cfg.train, fields=saved_fields)
          if not new and primary:
            print(f"warning: checkpoint step {iteration} was not saved (Orbax found it already in "
                  f"'{out / 'checkpoints'}')", file=sys.stderr, flush=True)
          saved = iteration
        if primary and len(call_s) == ETA_CALLS and call < total_calls - 1:
          bar.write(_expected_duration(call_s, cfg.train.iterations_per_call,
                                       cfg.train.num_iterations - iteration), file=sys.stderr)
        sps = derived.env_steps_per_call / dt
        bar.set_postfix(reward=f"{rows[-1]['episode_reward']:.3f}", steps_per_s=f"{sps:,.0f}")
        bar.update(len(rows))
        if stop:
          stopped = True
          break
  finally:  # also on an abort (a second signal): Orbax saves are atomic anyway
    bar.close()
    manager.close()
    for logger in scalar_loggers:
      logger.close()
  if primary:
    with _writing(f"'{out / 'reward_curve.png'}'", out, saved):
      plot_reward_curve(out)
  steady = float(np.median(call_s)) if call_s else None
  if primary:
    final_reward = read_progress(out)["episode_reward"][-1].item() if iteration else None
  else:
    final_reward = last_reward if iteration > start_iteration else previous.get(
        "final_episode_reward")
  summary = {
      "task": cfg.task, "algo": cfg.algo, "preset": cfg.preset, "ablation": cfg.ablation,
      "seeds": cfg.seeds, "iterations": iteration,
      "env_steps": iteration * derived.env_steps_per_iteration,
      "wall_s": time.perf_counter() - wall0,
      "first_call_s": compile_s,
      "train_env_steps_per_s": (derived.env_steps_per_call * cfg.seeds / steady) if steady else None,
      "final_episode_reward": final_reward,
      "interrupted": stopped,
      "signal": stop_signal if stopped else None,
      "backend": jax.default_backend(), "devices": devices, "processes": jax.process_count(),
  }
  if primary:
    with _writing(f"'{out / 'summary.json'}'", out, saved):
      _write_atomic(out / "summary.json", json.dumps(summary, indent=2))
  _sync("mash.runs.done")
  return summary
