"""Experiment configuration: task + algorithm + preset + env and trainer configs, as one JSON file.

``ExperimentConfig`` is what a run directory's ``config.json`` holds. Presets fix the sizes
(``smoke`` proves the pipeline in minutes, ``cpu`` is the best half hour of a 2-core CPU, ``gpu`` is
the paper's scale); ``--set path=value`` overrides any nested field, e.g.
``--set train.learning_rate=1e-3`` or ``--set env.reward_scales.joint_pos=2.0``.
"""

from __future__ import annotations

import dataclasses
import json
import numbers
import os
import typing
from pathlib import Path
from typing import Any, Mapping, Sequence

from mash.errors import InputError
from mash.rl import config as train_config
from mash.runs import loggers
from mash.sim import env as env_lib
from mash.sim import env_config, tasks

ALGOS = ("mash", "ppo")
MAX_SEEDS = 1024  # seeds of one run train side by side (vmapped) on one device
PRESETS = ("smoke", "cpu", "gpu")
# Ablation switches (paper-style studies): each maps to config changes on top of the algorithm.
ABLATIONS = ("none", "no_sharing", "local_critic", "single_value_head", "no_temporal_director",
             "no_agent_id", "per_limb", "legs_only")


class ConfigError(InputError):
  """A bad user-supplied setting (one line, names it and what was expected)."""


@dataclasses.dataclass(frozen=True)
class ExperimentConfig:
  """One training run (or several seeds of it).

  Attributes:
    task: 'bipedal' or 'armswing'.
    algo: 'mash' (limb agents, MAPPO) or 'ppo' (single agent, the same code).
    preset: the size preset the run started from.
    ablation: one of ``ABLATIONS`` ('none' for the method as published).
    seeds: independent seeds trained in one jitted call.
    env: environment config.
    train: trainer config.
    checkpoint_every: save an Orbax checkpoint every this many jitted calls (and at the end).
    keep_checkpoints: how many checkpoints to keep.
    checkpoint_env_state: save the envs' states in checkpoints (default), so ``--resume``
      continues bit-for-bit. ``False`` saves only what learning needs (params, optimizer state,
      normalizer, rng, iteration, episode statistics: a few MB instead of ~67 MB at 4096 envs,
      rsl_rl's convention); a resume then starts every env on a fresh episode (the curriculum
      clock is set to where it would have been), so the resumed curve is not bit-identical.
    wandb: also log to Weights & Biases (the ``[wandb]`` extra; :mod:`mash.runs.loggers`).
    wandb_project: the W&B project of the run.
  """

  task: str = "bipedal"
  algo: str = "mash"
  preset: str = "cpu"
  ablation: str = "none"
  seeds: int = 1
  env: env_config.EnvConfig = env_config.EnvConfig()
  train: train_config.TrainConfig = train_config.TrainConfig()
  checkpoint_every: int = 5
  keep_checkpoints: int = 3
  checkpoint_env_state: bool = True
  wandb: bool = False
  wandb_project: str = "mash-jax"


def _preset_train(preset: str) -> train_config.TrainConfig:
  # Action std 0.3 without the penalty curriculum (smoke); 1 under it (cpu, gpu): at std 1 the
  # paper's smoothness penalties alone would zero the clipped reward (docs/decisions.md).
  base = dataclasses.replace(train_config.TrainConfig(), init_log_std=-1.2)
  if preset == "smoke":
    return dataclasses.replace(base, num_iterations=10, unroll_length=16, num_envs=64,
                               iterations_per_call=5, num_epochs=2, num_minibatches=2,
                               actor_hidden=(64, 64), critic_hidden=(64, 64), learning_rate=1e-3)
  if preset == "cpu":
    # 1875 iterations of 400 envs x 24 steps (18 M steps), the learning rate decaying to 0: the
    # kicked recipe needs 1.5x the 12 M steps of the kick-free one (issue 52, candidate O).
    hidden = (256, 128, 64)
    return dataclasses.replace(base, num_iterations=1875, unroll_length=24, num_envs=400,
                               iterations_per_call=10, num_epochs=4, num_minibatches=4,
                               actor_hidden=hidden, critic_hidden=hidden, learning_rate=1e-3,
                               learning_rate_schedule="linear", init_log_std=0.0)
  # gpu: the paper's 3000 iterations of 4096 envs x 48 steps.
  return dataclasses.replace(base, init_log_std=0.0)


# The presets' recipe beyond the paper; each is the config of runs that met their bar (each choice
# and its measurement: docs/decisions.md). Curricula, in control steps per env: the gpu preset
# phases the penalties in by iteration 333 of 3000 (48 steps); the cpu preset phases them in and
# widens the floor friction from FRICTION_INITIAL to the paper's range by iteration 1500 of 1875.
GPU_CURRICULUM_STEPS = 16_000
CPU_CURRICULUM_STEPS = 36_000
FRICTION_INITIAL = (0.1, 0.3)
TRACKING_SIGMA = 0.1  # the cpu preset's linear-velocity tracking kernel (legged_gym's 0.25 else)
# The cpu preset's Newton and line-search iterations (1 and 4 elsewhere).
SOLVER_ITERATIONS = 2
LS_ITERATIONS = 2
# Velocity kicks of the torso in the cpu and gpu presets (issue 52; MuJoCo Playground's T1
# schedule, no yaw-rate kick): none before KICK_START_FRACTION of the curriculum, full size at
# KICK_START_FRACTION + KICK_RAMP_FRACTION of it. Kicked policies stop turning and slow down unless
# the yaw-tracking term weighs more (candidates J, L, O in docs/decisions.md).
KICK_VELOCITY = (0.1, 1.0)
KICK_INTERVAL_S = (5.0, 10.0)
KICK_START_FRACTION = 0.4
KICK_RAMP_FRACTION = 0.5
KICKED_TRACKING_SCALES = {"tracking_ang_vel": 2.8}


def _preset_env(preset: str, task: str, algo: str) -> env_config.EnvConfig:
  partition = "ppo" if algo == "ppo" else "mash"
  spec = tasks.get(task)  # its own command ranges and reward scales, where it has any
  base = env_config.EnvConfig()
  cfg = env_config.EnvConfig(
      task=task, partition=partition, commands=dataclasses.replace(base.commands, **spec.commands),
      reward_scales=dataclasses.replace(base.reward_scales, **spec.reward_scales))
  if preset == "smoke":
    return dataclasses.replace(cfg, episode_length=200)
  if preset == "gpu":
    return _with_kicks(
        dataclasses.replace(
            cfg, reward_params=dataclasses.replace(cfg.reward_params,
                                                   penalty_ramp_steps=GPU_CURRICULUM_STEPS)),
        GPU_CURRICULUM_STEPS)
  physics = dataclasses.replace(cfg.physics, iterations=SOLVER_ITERATIONS,
                                ls_iterations=LS_ITERATIONS)
  randomization = dataclasses.replace(cfg.randomization, friction_initial=FRICTION_INITIAL,
                                      friction_ramp_steps=CPU_CURRICULUM_STEPS)
  reward_params = dataclasses.replace(cfg.reward_params, penalty_ramp_steps=CPU_CURRICULUM_STEPS,
                                      tracking_sigma=TRACKING_SIGMA)
  return _with_kicks(
      dataclasses.replace(cfg, stride_reference=True, physics=physics, randomization=randomization,
                          reward_params=reward_params), CPU_CURRICULUM_STEPS)


def _with_kicks(cfg: env_config.EnvConfig, curriculum_steps: int) -> env_config.EnvConfig:
  """``cfg`` with the presets' velocity kicks, timed on the curriculum's clock (control steps per
  env), and the tracking scales that keep a kicked policy following its commands."""
  randomization = dataclasses.replace(
      cfg.randomization, kick_velocity=KICK_VELOCITY, kick_interval_s=KICK_INTERVAL_S,
      kick_yaw_rate=(0.0, 0.0), kick_ramp_start_steps=round(KICK_START_FRACTION * curriculum_steps),
      kick_ramp_steps=round(KICK_RAMP_FRACTION * curriculum_steps))
  return dataclasses.replace(
      cfg, randomization=randomization,
      reward_scales=dataclasses.replace(cfg.reward_scales, **KICKED_TRACKING_SCALES))


def _apply_ablation(cfg: ExperimentConfig) -> ExperimentConfig:
  a = cfg.ablation
  env, train = cfg.env, cfg.train
  if a == "no_sharing":
    train = dataclasses.replace(train, share_actor=False)
  elif a == "single_value_head":
    train = dataclasses.replace(train, shared_value_head=True)
  elif a == "local_critic":
    train = dataclasses.replace(train, local_critic=True)
    env = dataclasses.replace(env, critic="local")
  elif a == "no_temporal_director":
    env = dataclasses.replace(env, temporal_director=False)
  elif a == "no_agent_id":
    env = dataclasses.replace(env, agent_id=False)
  elif a == "per_limb":
    env = dataclasses.replace(env, partition="per_limb")
  elif a == "legs_only":
    env = dataclasses.replace(env, task="bipedal")
  return dataclasses.replace(cfg, env=env, train=train)


def make_config(task: str, algo: str = "mash", preset: str = "cpu", seeds: int = 1,
                ablation: str = "none", overrides: Sequence[str] = ()) -> ExperimentConfig:
  """The resolved config of a run: preset, then ablation, then ``overrides``.

  Raises:
    ConfigError: an unknown task, algo, preset or ablation, a malformed override, or an override
      that leaves the config invalid (see :func:`check`).
  """
  _check_choices(task, algo, preset, ablation, seeds)
  cfg = ExperimentConfig(task=task, algo=algo, preset=preset, ablation=ablation, seeds=seeds,
                         env=_preset_env(preset, task, algo), train=_preset_train(preset))
  cfg = _apply_ablation(cfg)
  cfg = apply_overrides(cfg, overrides)
  check(cfg)
  return cfg


def config_from_file(path: str | os.PathLike, task: str, seeds: int = 1,
                     overrides: Sequence[str] = ()) -> ExperimentConfig:
  """The config in the file ``path`` (a run's ``config.json``), training ``seeds`` seeds, then
  ``overrides``: a run that repeats another's recipe exactly (a comparison's new seed).

  Raises:
    ConfigError: the file is missing or not a config, it is another task's, or an override is bad.
  """
  try:
    text = Path(path).read_text()
  except (OSError, UnicodeDecodeError) as e:
    raise ConfigError(f"--config '{path}' cannot be read: {getattr(e, 'strerror', None) or e}") \
        from None
  try:
    cfg = from_json(text)
  except ConfigError as e:
    raise ConfigError(f"--config '{path}': {e}") from None
  if cfg.task != task:
    raise ConfigError(f"--config '{path}' is a '{cfg.task}' config, not '{task}'")
  _check_choices(cfg.task, cfg.algo, cfg.preset, cfg.ablation, seeds)
  cfg = apply_overrides(dataclasses.replace(cfg, seeds=seeds), overrides)
  check(cfg)
  return cfg


def _check_choices(task: str, algo: str, preset: str, ablation: str, seeds: int) -> None:
  for value, allowed, what in ((task, tasks.names(), "task"), (algo, ALGOS, "algo"),
                               (preset, PRESETS, "preset"), (ablation, ABLATIONS, "ablation")):
    if value not in allowed:
      raise ConfigError(f"{what} '{value}' is unknown; expected one of {', '.join(allowed)}")
  if seeds < 1:
    raise ConfigError(f"seeds must be >= 1, got {seeds}")
  if seeds > MAX_SEEDS:
    raise ConfigError(f"seeds must be at most {MAX_SEEDS} (seeds train side by side on one "
                      f"device), got {seeds}")
  if ablation != "none" and algo != "mash":
    raise ConfigError(f"ablation '{ablation}' applies to --algo mash, not '{algo}'")


def check(cfg: ExperimentConfig) -> None:
  """Checks a whole config without building anything (so that ``--set`` mistakes are one line,
  before any file is written).

  Raises:
    ConfigError: names the bad field and what was expected.
  """
  _check_kinds(cfg)
  _check_choices(cfg.task, cfg.algo, cfg.preset, cfg.ablation, cfg.seeds)
  for name in ("checkpoint_every", "keep_checkpoints"):
    if getattr(cfg, name) < 1:
      raise ConfigError(f"{name} must be >= 1, got {getattr(cfg, name)}")
  if cfg.wandb and not loggers.wandb_installed():
    raise ConfigError('wandb=true needs Weights & Biases, which is not installed here: pip '
                      'install -e ".[wandb]" (or leave wandb at false)')
  if not cfg.wandb_project.strip() or len(cfg.wandb_project) > 128 or any(
      c in cfg.wandb_project for c in "/\\#?%:\n"):
    raise ConfigError(f"wandb_project must be a W&B project name (1 to 128 characters, none of "
                      f"/ \\ # ? % :), got {cfg.wandb_project!r}")
  try:
    env_config.check_config(cfg.env)
  except ValueError as e:
    raise ConfigError(f"env.{e}") from None
  try:
    train_config.derived(cfg.train)
  except ValueError as e:
    raise ConfigError(str(e)) from None
  physics = cfg.env.physics
  if physics.impl == "warp" and cfg.train.num_envs * cfg.seeds > physics.warp_max_envs:
    # MuJoCo Warp's contact buffer is shared by the batch and sized for warp_max_envs: beyond it,
    # contacts would be dropped without a word.
    raise ConfigError(f"env.physics.warp_max_envs={physics.warp_max_envs} must be at least the "
                      f"envs stepped at once, train.num_envs x seeds = "
                      f"{cfg.train.num_envs * cfg.seeds}")


_KINDS = {bool: "true or false", int: "a whole number", float: "a number", str: "text"}
_KINDS_PLURAL = {bool: "true/false values", int: "whole numbers", float: "numbers", str: "names"}


def _kind(hint: Any) -> str:
  """What a field of type ``hint`` holds, in words."""
  args = [a for a in typing.get_args(hint) if a is not Ellipsis]
  if typing.get_origin(hint) is tuple:
    return f"a list of {_KINDS_PLURAL.get(args[0], 'values')}"
  if type(None) in args:
    return " or ".join(_kind(a) for a in args if a is not type(None)) + " or none"
  return _KINDS.get(hint, getattr(hint, "__name__", str(hint)))


def _is_kind(value: Any, hint: Any) -> bool:
  """Whether ``value`` is of the field type ``hint`` (an int passes for a float)."""
  args = [a for a in typing.get_args(hint) if a is not Ellipsis]
  if typing.get_origin(hint) is tuple:
    return isinstance(value, tuple) and all(_is_kind(v, args[0]) for v in value)
  if type(None) in args:
    return value is None or any(_is_kind(value, a) for a in args if a is not type(None))
  if hint is bool:
    return isinstance(value, bool)
  if hint is int:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)
  if hint is float:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)
  return isinstance(value, hint)


def _check_kinds(obj: Any, prefix: str = "") -> None:
  """Checks that every field of a config, sections included, holds its declared kind of value
  (a config.json written by hand, or a config built in code, may hold anything), so that the
  range checks compare numbers with numbers.

  Raises:
    ConfigError: names the field, its value and the kind expected.
  """
  hints = typing.get_type_hints(type(obj))
  for f in dataclasses.fields(obj):
    value, hint, path = getattr(obj, f.name), hints[f.name], prefix + f.name
    if dataclasses.is_dataclass(hint):
      if not isinstance(value, hint):
        raise ConfigError(f"{path} must be a {hint.__name__} section, got {value!r}")
      _check_kinds(value, path + ".")
    elif not _is_kind(value, hint):
      raise ConfigError(f"{path} must be {_kind(hint)}, got {value!r}")


def _coerce(text: str, like: Any, path: str) -> Any:
  """Parses ``text`` as the type of the current value ``like``."""
  try:
    if isinstance(like, bool):
      if text.lower() in ("1", "true", "yes", "on"):
        return True
      if text.lower() in ("0", "false", "no", "off"):
        return False
      raise ValueError
    if isinstance(like, int):
      return int(text)
    if isinstance(like, float):
      return float(text)
    if isinstance(like, tuple):
      items = [t for t in text.strip("()[] ").split(",") if t.strip()]
      kind = type(like[0]) if like else float
      return tuple(kind(t) for t in items)
    return text
  except ValueError:
    what = {**_KINDS, tuple: "comma-separated values"}.get(type(like), "text")
    raise ConfigError(f"override '{path}={text}': expected {what} like {like!r}") from None


def _coerce_field(text: str, obj: Any, name: str, path: str) -> Any:
  """Parses ``text`` for field ``name`` of ``obj``: as the type of its current value, or for an
  ``X | None`` field, ``none`` as None and anything else as an ``X``."""
  current = getattr(obj, name)
  kinds = typing.get_args(typing.get_type_hints(type(obj))[name])
  if type(None) in kinds:
    if text.lower() == "none":
      return None
    if current is None:
      kind = next(k for k in kinds if k is not type(None))
      current = {tuple: (0.0,), float: 0.0, int: 0,
                 bool: False}.get(typing.get_origin(kind) or kind, "")
  return _coerce(text, current, path)


def apply_overrides(cfg: Any, overrides: Sequence[str]) -> Any:
  """Applies ``path=value`` strings to nested frozen dataclasses."""
  for item in overrides:
    if "=" not in item:
      raise ConfigError(f"override '{item}': expected the form path=value, e.g. "
                        "train.learning_rate=1e-3")
    path, text = item.split("=", 1)
    keys = path.strip().split(".")
    cfg = _replace_path(cfg, keys, text.strip(), path.strip())
  return cfg


def _replace_path(obj: Any, keys: list[str], text: str, path: str) -> Any:
  if not dataclasses.is_dataclass(obj):
    raise ConfigError(f"override '{path}': '{keys[0]}' is not inside a config section")
  names = [f.name for f in dataclasses.fields(obj)]
  if keys[0] not in names:
    raise ConfigError(f"override '{path}': '{keys[0]}' is not a field of "
                      f"{type(obj).__name__} (fields: {', '.join(names)})")
  current = getattr(obj, keys[0])
  if len(keys) == 1:
    if dataclasses.is_dataclass(current):
      raise ConfigError(f"override '{path}': '{keys[0]}' is a section; name one of its fields")
    value = _coerce_field(text, obj, keys[0], path)
  else:
    value = _replace_path(current, keys[1:], text, path)
  return dataclasses.replace(obj, **{keys[0]: value})


def to_dict(cfg: ExperimentConfig) -> dict[str, Any]:
  return dataclasses.asdict(cfg)


def to_json(cfg: ExperimentConfig) -> str:
  return json.dumps(to_dict(cfg), indent=2, sort_keys=True)


def _from_dict(cls: type, data: Mapping[str, Any]) -> Any:
  hints = typing.get_type_hints(cls)
  kwargs = {}
  for f in dataclasses.fields(cls):
    if f.name not in data:
      continue
    value, hint = data[f.name], hints[f.name]
    if dataclasses.is_dataclass(hint):
      value = _from_dict(hint, value)
    elif isinstance(value, list):
      value = tuple(value)
    kwargs[f.name] = value
  return cls(**kwargs)


def from_json(text: str) -> ExperimentConfig:
  """Parses a ``config.json``; raises ConfigError when it is not one, or not a valid one."""
  try:
    cfg = _from_dict(ExperimentConfig, json.loads(text))
  except (json.JSONDecodeError, TypeError, AttributeError, ValueError) as e:
    raise ConfigError(f"config.json is not an experiment config ({e})") from None
  check(cfg)
  return cfg


def make_env(cfg: ExperimentConfig) -> env_lib.MashEnv:
  return env_lib.MashEnv(cfg.env)
