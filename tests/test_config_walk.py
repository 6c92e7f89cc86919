"""Every numeric setting of every config, walked with NaN, inf, 0, -1 and a huge value (issue 27,
item 1).

The fields are found by introspection (a field added later is walked too): every ``int``,
``float`` and tuple-of-number field of :class:`mash.runs.experiment.ExperimentConfig`, its sections
included (``train``, ``env``, ``env.commands``, ``env.physics``, ``env.randomization``,
``env.reward_scales``, ``env.reward_params``), and of the evaluation's :class:`EvalConfig` and
sim2sim's :class:`Sim2SimConfig`. A tuple gets the bad value in one element. Each value must be
refused with one line that names the field and the value, or be accepted; NaN and inf are always
refused, and an accepted value must start: what a start builds from it is built (the env for an
``env.*`` field, the trainer's networks, optimizer and keys for a ``train.*`` one, the checkpoint
manager for the run's own numbers, the evaluation env, the sim2sim MuJoCo model), without jit.

Cost: a MashEnv is ~0.3 s, nearly all of it compiling the MuJoCo model, which depends only on
``env.physics``: the models are cached per physics setting, so each env costs ~0.05 s.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import subprocess
import sys
import typing
from pathlib import Path
from typing import Any, Iterator

import jax
import pytest

from mash.analysis import evaluation
from mash.deploy import sim2sim
from mash.rl import mappo
from mash.rl import trainer as trainer_lib
from mash.runs import experiment
from mash.sim import env as env_lib
from mash.sim import model as model_lib
from mash.sim import robots

REPO = Path(__file__).resolve().parents[1]
BAD = ("nan", "inf", "0", "-1", "huge")
HUGE = {int: "1000000000000", float: "1e300"}


def _number_kind(hint: Any) -> tuple[type, int | None] | None:
  """``(int | float, None)`` for a number field, ``(kind, length)`` for a tuple of numbers
  (``length`` None: any), None for any other field; ``X | None`` is looked through."""
  args = [a for a in typing.get_args(hint) if a is not type(None)]
  if type(None) in typing.get_args(hint) and len(args) == 1:
    hint, args = args[0], list(typing.get_args(args[0]))
  if hint in (int, float):
    return hint, None
  if typing.get_origin(hint) is tuple and args and args[0] in (int, float):
    return args[0], None if Ellipsis in args else len(args)
  return None


def numeric_fields(obj: Any, prefix: str = "") -> Iterator[tuple[str, type, int | None, Any]]:
  """``(path, kind, tuple length or None, current value)`` of every number field of a config and
  of its sections, in declaration order."""
  hints = typing.get_type_hints(type(obj))
  for f in dataclasses.fields(obj):
    value = getattr(obj, f.name)
    if dataclasses.is_dataclass(value):
      yield from numeric_fields(value, f"{prefix}{f.name}.")
      continue
    kind = _number_kind(hints[f.name])
    if kind is not None:
      yield f"{prefix}{f.name}", kind[0], kind[1], value


def _is_tuple(current: Any, length: int | None) -> bool:
  return isinstance(current, tuple) or length is not None


def _override_text(kind: type, length: int | None, current: Any, bad: str, which: int) -> str:
  """The ``--set`` text of ``bad`` for a field: the value itself, or for a tuple field its current
  elements (1.0 each when it is None) with element ``which`` replaced."""
  text = HUGE[kind] if bad == "huge" else bad
  if not _is_tuple(current, length):
    return text
  elements = [str(x) for x in (current if current is not None else (1.0,) * (length or 1))]
  elements[which % len(elements)] = text
  return ",".join(elements)


def _spellings(text: str) -> set[str]:
  """How a message may show the value typed as ``text``: as typed, or parsed (``1e+300``)."""
  forms = {text}
  try:
    forms.add(str(float(text)))
    forms.add(str(int(text)))
  except (ValueError, OverflowError):
    pass
  return forms


def _names_field(message: str, path: str) -> bool:
  """The message names the field: its path, or ``TrainConfig.<name>`` for a ``train.*`` one."""
  name = path.split(".")[-1]
  return path in message or (path.startswith("train.") and f"TrainConfig.{name}" in message)


SMOKE = experiment.make_config("bipedal", "mash", "smoke")
CONFIG_FIELDS = list(numeric_fields(SMOKE))
EVAL_FIELDS = list(numeric_fields(evaluation.EvalConfig()))
SIM2SIM_FIELDS = list(numeric_fields(sim2sim.Sim2SimConfig()))


@pytest.fixture(scope="module", autouse=True)
def cached_models():
  """``model_lib.build_model`` memoized per robot and physics setting for this module: the model a
  MashEnv compiles depends on nothing else."""
  real = model_lib.build_model

  @functools.lru_cache(maxsize=None)
  def build(name: str, physics: model_lib.PhysicsConfig, full_collision: bool):
    return real(robots.load(name), physics, full_collision)

  with pytest.MonkeyPatch.context() as mp:
    mp.setattr(
        model_lib, "build_model",
        lambda spec, physics=model_lib.PhysicsConfig(), full_collision=False: build(
            spec.name, physics, full_collision))
    yield


@pytest.fixture(scope="module")
def smoke_env(cached_models) -> env_lib.MashEnv:
  return env_lib.MashEnv(SMOKE.env)


def _start(cfg: experiment.ExperimentConfig, path: str, env: env_lib.MashEnv,
           tmp_path: Path) -> None:
  """Builds what a run of ``cfg`` builds before its first jitted call, for the part ``path``
  changed: the env, or the trainer's networks, optimizer state and keys (shapes only), or the
  checkpoint manager."""
  if path.startswith("env."):
    env = env_lib.MashEnv(cfg.env)
    assert env.n_substeps >= 1 and env.action_size > 0
  algo = mappo.make_mappo(cfg.train, env)
  params = jax.eval_shape(algo.networks.init, jax.random.PRNGKey(0))
  jax.eval_shape(algo.optimizer.init, params)
  trainer_lib.seed_keys(cfg.train.seed, cfg.seeds)
  if path in ("checkpoint_every", "keep_checkpoints"):
    from mash.runs import checkpoint
    checkpoint.make_manager(tmp_path / "checkpoints", max_to_keep=cfg.keep_checkpoints).close()


def test_the_walk_finds_every_section():
  """A guard on the introspection: each section's fields are walked, tuples included."""
  paths = {p for p, *_ in CONFIG_FIELDS}
  for section in ("train.", "env.commands.", "env.physics.", "env.randomization.",
                  "env.reward_scales.", "env.reward_params."):
    assert any(p.startswith(section) for p in paths), section
  for path in ("checkpoint_every", "seeds", "env.ctrl_dt", "env.randomization.push_force",
               "env.randomization.friction_initial", "train.actor_hidden", "train.num_envs"):
    assert path in paths, path
  assert "env.agent_id" not in paths and "train.normalize_advantages" not in paths  # bools
  assert len(CONFIG_FIELDS) >= 85 and {p for p, *_ in EVAL_FIELDS} >= {"friction", "seed"}


@pytest.mark.parametrize("path, kind, length, current", CONFIG_FIELDS,
                         ids=[p for p, *_ in CONFIG_FIELDS])
def test_every_config_number_is_refused_in_one_line_or_starts(path, kind, length, current,
                                                              smoke_env, tmp_path):
  for which, bad in enumerate(BAD):
    text = _override_text(kind, length, current, bad, which)
    try:
      cfg = experiment.make_config("bipedal", "mash", "smoke", overrides=[f"{path}={text}"])
    except experiment.ConfigError as e:
      message = str(e)
      value = HUGE[kind] if bad == "huge" else bad
      assert "\n" not in message and _names_field(message, path), message
      assert any(form in message for form in _spellings(value)), (value, message)
      continue
    assert bad not in ("nan", "inf"), f"{path}={text} was accepted"
    _start(cfg, path, smoke_env, tmp_path)


def _walk_settings(fields, default, check, start) -> list[str]:
  """Walks the number fields of a settings class through its ``check`` (the one its command line
  calls); returns the values accepted (each then built by ``start``)."""
  accepted = []
  for path, kind, length, current in fields:
    for which, bad in enumerate(BAD):
      value = {
          "nan": math.nan, "inf": math.inf, "0": 0, "-1": -1,
          "huge": 10**12 if kind is int else 1e300
      }[bad]
      if _is_tuple(current, length):
        elements = list(current if current is not None else (1.0,) * length)
        elements[which % len(elements)] = value
        value = tuple(elements)
      settings = dataclasses.replace(default, **{path: value})
      try:
        check(settings)
      except ValueError as e:
        assert "\n" not in str(e) and path in str(e) and str(value) in str(e), str(e)
        continue
      assert bad not in ("nan", "inf"), f"{path}={value} was accepted"
      start(settings)
      accepted.append(f"{path}={value}")
  return accepted


def test_every_evaluation_number_is_refused_in_one_line_or_starts(smoke_env):

  def start(settings):  # the env an evaluation builds
    env_lib.MashEnv(evaluation.eval_env_config(SMOKE.env, settings))

  accepted = _walk_settings(EVAL_FIELDS, evaluation.EvalConfig(), evaluation.check_config, start)
  assert "num_episodes=0" not in accepted and "episode_s=1e+300" not in accepted


def test_every_sim2sim_number_is_refused_in_one_line_or_starts(cached_models):

  def start(settings):  # the MuJoCo C model sim2sim steps
    model_lib.build_model(robots.load(SMOKE.env.robot), sim2sim.physics(settings),
                          full_collision=settings.full_collision)

  accepted = _walk_settings(SIM2SIM_FIELDS, sim2sim.Sim2SimConfig(), sim2sim.check_config, start)
  assert not any(a.startswith(("sim_dt=", "iterations=", "ls_iterations=")) for a in accepted)


def test_the_command_lines_name_their_flags():
  """evaluate and sim2sim name the flag, not the field, in the error line."""
  with pytest.raises(ValueError, match=r"^--seconds must be in \(0, 3600\] s, got nan$"):
    evaluation.check_config(evaluation.EvalConfig(episode_s=math.nan), {"episode_s": "--seconds"})
  with pytest.raises(ValueError, match=r"^--iterations must be in \[1, 1000\], got 0$"):
    sim2sim.check_config(sim2sim.Sim2SimConfig(iterations=0), {"iterations": "--iterations"})


@pytest.mark.parametrize("override, words", [
    ("env.randomization.push_force=nan,20",
     "env.randomization.push_force must be a range (lo, hi) with -10000 <= lo <= hi <= 10000 N, "
     "got (nan, 20.0)"),
    ("train.num_envs=1000000000000",
     "TrainConfig.num_envs must be in [1, 1048576], got 1000000000000."),
    ("env.physics.sim_dt=0", "env.physics.sim_dt must be in (0, 0.1] s, got 0.0"),
], ids=["nan_push_force", "huge_num_envs", "zero_sim_dt"])
def test_bad_numbers_on_the_command_line_are_one_line_and_exit_2(override, words, tmp_path):
  """The real command, in a subprocess: status 2, one stderr line, nothing written (~10 s each)."""
  out = tmp_path / "run"
  path = os.environ.get("PYTHONPATH", "")
  env = dict(os.environ, PYTHONPATH=f"{REPO}{os.pathsep}{path}" if path else str(REPO))
  result = subprocess.run([
      sys.executable, "-m", "experiments.bipedal", "--preset", "smoke", "--set", override, "--out",
      str(out)
  ], capture_output=True, text=True, cwd=tmp_path, env=env, timeout=120)
  lines = [l for l in result.stderr.splitlines() if l.strip() and "warp" not in l]
  assert result.returncode == 2 and lines == [f"error: {words}"], result.stderr
  assert not out.exists()
