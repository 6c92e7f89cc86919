"""A trained policy without the trainer: load it, save it as a small folder, and act with it.

:func:`load` reads a policy from either

- a **run directory** (``config.json`` + Orbax ``checkpoints/``, :mod:`mash.runs.loop`): only the
  policy fields (:data:`mash.runs.checkpoint.POLICY_FIELDS`) of the newest checkpoint that restores
  (older ones are tried, with a warning, when newer ones are torn), or of the one saved at
  ``iteration``, read as saved (no template state, so no trainer, optimizer or env state is built);
  or
- a **policy folder** (:func:`save`), format ``mash-policy-folder/1``:

  ``config.json``  the run's resolved :class:`mash.runs.experiment.ExperimentConfig`, as in the run
  ``policy.npz``   NumPy arrays, float32, one seed (no seed axis), named by their path:
                   ``params/actors/<group>/params/MLP_0/Dense_<k>/{kernel,bias}``,
                   ``params/actors/<group>/params/log_std`` and, when the run normalizes
                   observations, ``normalizer/<group>/{count,mean,m2}`` (running statistics,
                   :class:`mash.rl.normalization.RunningStats`); no critic, optimizer or env state
  ``policy.json``  ``format``, ``iteration``, ``seed`` (of its run), ``saved_from``, ``task``,
                   ``algo``; written last, so a folder without it is not a policy folder
  ``card.md``      a short human-readable description
  ``policy.onnx``  optional: the deployable graph (:mod:`mash.deploy.export`, ``docs/deploy.md``)

:func:`make_inference_fn` gives the deterministic (mean) action, the function evaluation, export and
sim-to-sim use. :func:`read_progress` reads a run's learning curve, which evaluation shows beside
the policy. Nothing here imports training code (:mod:`mash.rl.mappo`, :mod:`mash.runs.loop`, optax).
"""

from __future__ import annotations

import csv
import dataclasses
import gzip
import json
import os
import zipfile
from pathlib import Path
from typing import Any, Callable, Mapping, NamedTuple

import flax.traverse_util
import jax
import jax.numpy as jnp
import numpy as np

from mash.errors import InputError
from mash.rl import networks, normalization
from mash.runs import checkpoint, experiment, records
from mash.sim import env as env_lib
from mash.sim import robots

FORMAT = "mash-policy-folder/1"
CONFIG = "config.json"
ARRAYS = "policy.npz"
INFO = "policy.json"
CARD = "card.md"
ONNX = "policy.onnx"


class RunError(InputError):
  """A run directory or policy folder that cannot be used as asked (one line, names the path)."""


class Policy(NamedTuple):
  """One seed's trained policy: what acting needs, nothing of training.

  Attributes:
    config: the run's experiment config (``config.seeds`` is the run's, whichever seed this is).
    params: ``{'actors': {group: flax variables}}``, the actors only (no critic).
    normalizer: ``{group: RunningStats}`` of the actors' observation streams, or None when the run
      does not normalize observations.
    iteration: the training iteration of its checkpoint.
    seed: which seed of its run (0 for a one-seed run).
    source: the run directory or policy folder it was loaded from.
  """

  config: experiment.ExperimentConfig
  params: dict[str, Any]
  normalizer: normalization.Normalizer | None
  iteration: int
  seed: int
  source: str


def is_policy_folder(path: str | os.PathLike) -> bool:
  """Whether ``path`` is a policy folder written by :func:`save` (it has ``policy.json``)."""
  return (Path(path) / INFO).is_file()


def load_config(path: str | os.PathLike, robot: str | None = None) -> experiment.ExperimentConfig:
  """The config of a run directory or a policy folder; RunError when ``path`` is neither.

  ``robot``: a robot file (or shipped name) to use instead of the run's ``env.robot``, e.g. a
  user's robot file that has moved since training; it must be the robot the run names (the same
  ``name``) when the run's own is still readable.
  """
  cfg = _read_config(Path(path))
  if robot is None:
    return cfg
  spec = robots.load(robot)
  try:
    trained = robots.load(cfg.env.robot).name
  except robots.SpecError:  # the run's file is gone: the given one stands in for it
    trained = spec.name
  if spec.name != trained:
    raise RunError(f"--robot {robot} is robot '{spec.name}', but '{path}' was trained on "
                   f"'{trained}'")
  return dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, robot=robot))


def _read_config(path: Path) -> experiment.ExperimentConfig:
  if not path.exists():
    raise RunError(f"run directory '{path}' does not exist")
  if not path.is_dir():
    raise RunError(f"'{path}' is a file; expected a run directory or a policy folder")
  if not (path / CONFIG).is_file():
    raise RunError(f"'{path}' is not a run directory or a policy folder (no config.json)")
  try:
    return experiment.from_json((path / CONFIG).read_text())
  except experiment.ConfigError as e:
    raise RunError(f"'{path}/config.json': {e}") from None


def load(path: str | os.PathLike, iteration: int | None = None, seed: int = 0,
         robot: str | None = None) -> Policy:
  """The policy of a run directory or a policy folder (see the module docstring).

  Args:
    path: a run directory or a policy folder.
    iteration: the checkpoint saved at this iteration instead of the newest that restores (a
      policy folder holds one: asking for another is an error).
    seed: which seed of a multi-seed run (a policy folder holds one: 0).
    robot: the robot file to use instead of the run's (:func:`load_config`).

  Raises:
    RunError: one line naming the path: neither a run nor a policy folder, no checkpoint that
      restores, no checkpoint of ``iteration``, ``seed`` out of range, unreadable files.
  """
  path = Path(path)
  cfg = load_config(path, robot)
  if is_policy_folder(path):
    policy = _load_folder(path, cfg)
    if iteration is not None and iteration != policy.iteration:
      raise RunError(f"'{path}' is a policy folder of iteration {policy.iteration} only, not "
                     f"{iteration}")
    if seed != 0:
      raise RunError(f"seed {seed} is out of range: the policy folder '{path}' holds one policy "
                     f"(seed 0; seed {policy.seed} of its run)")
    return policy
  if not 0 <= seed < cfg.seeds:
    raise RunError(f"seed {seed} is out of range: the run has {cfg.seeds} seed(s) "
                   f"(0..{cfg.seeds - 1})")
  return _load_run(path, cfg, iteration, (seed,))[0]


def load_all(path: str | os.PathLike, iteration: int | None = None,
             robot: str | None = None) -> tuple[Policy, ...]:
  """Every seed's policy of a run (its checkpoint read once), or a policy folder's one; see
  :func:`load`."""
  path = Path(path)
  cfg = load_config(path, robot)
  if is_policy_folder(path):
    return (load(path, iteration, robot=robot),)
  return _load_run(path, cfg, iteration, tuple(range(cfg.seeds)))


def _load_run(path: Path, cfg: experiment.ExperimentConfig, iteration: int | None,
              seeds: tuple[int, ...]) -> tuple[Policy, ...]:
  try:
    restored = checkpoint.restore_latest_flat(path / "checkpoints", checkpoint.POLICY_FIELDS,
                                              step=iteration)
  except checkpoint.CheckpointError as e:
    raise RunError(str(e)) from None
  if restored is None:
    raise RunError(f"'{path}' has no complete checkpoint (it was stopped before its first "
                   "checkpoint was saved)")
  tree = checkpoint.unflatten(restored.state)
  actors = tree["params"]["actors"]
  normalizer = None
  if cfg.train.normalize_observations:  # only the actors' streams (the critic's is training's)
    normalizer = {name: normalization.RunningStats(**tree["normalizer"][name]) for name in actors}
  # A multi-seed run stores every leaf with a leading seed axis.
  pick = (lambda tree, s: tree) if cfg.seeds == 1 else (
      lambda tree, s: jax.tree.map(lambda x: x[s], tree))
  return tuple(
      Policy(cfg, {"actors": pick(actors, s)}, None if normalizer is None else pick(normalizer, s),
             int(restored.step), s, str(path)) for s in seeds)


def folder_info(path: str | os.PathLike) -> dict[str, Any]:
  """A policy folder's ``policy.json``; RunError when it is unreadable or of another format."""
  file = Path(path) / INFO
  try:
    info = json.loads(file.read_text())
  except (OSError, ValueError) as e:
    raise RunError(f"'{file}' cannot be read ({e})") from None
  if not isinstance(info, dict) or info.get("format") != FORMAT:
    found = info.get("format") if isinstance(info, dict) else None
    raise RunError(f"'{file}': format {found!r} is not {FORMAT!r}, the one this version reads")
  return info


def _load_folder(path: Path, cfg: experiment.ExperimentConfig) -> Policy:
  info = folder_info(path)
  try:
    with np.load(path / ARRAYS, allow_pickle=False) as data:
      tree = flax.traverse_util.unflatten_dict({k: jnp.asarray(data[k]) for k in data.files},
                                               sep="/")
    actors = tree["params"]["actors"]
    normalizer = None
    if "normalizer" in tree:
      normalizer = {
          name: normalization.RunningStats(**stats) for name, stats in tree["normalizer"].items()
      }
    if set(tree) - {"params", "normalizer"} or set(tree["params"]) != {"actors"}:
      raise ValueError(f"unexpected arrays {sorted(set(tree) | set(tree['params']))}")
  except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile) as e:
    raise RunError(f"'{path / ARRAYS}' is not a policy's arrays ({type(e).__name__}: "
                   f"{str(e).splitlines()[0] if str(e) else ''})") from None
  return Policy(cfg, {"actors": actors}, normalizer, int(info["iteration"]), int(info["seed"]),
                str(path))


def save(policy: Policy, folder: str | os.PathLike) -> Path:
  """Writes ``policy`` as a policy folder (see the module docstring; tens to hundreds of KiB).

  Files of an earlier policy in ``folder`` are replaced; a ``policy.onnx`` left from one is removed
  (:func:`mash.deploy.export.save_policy_folder` writes the folder with a new one).

  Args:
    policy: from :func:`load`.
    folder: the folder to write (created if missing); not a run directory.

  Returns:
    ``folder``.
  """
  folder = Path(folder)
  if (folder / "checkpoints").exists() or (folder / "progress.csv").exists():
    raise RunError(f"'{folder}' is a run directory; save the policy folder elsewhere")
  if folder.exists() and not folder.is_dir():
    raise RunError(f"'{folder}' is a file; expected a folder for the policy")
  folder.mkdir(parents=True, exist_ok=True)
  (folder / INFO).unlink(missing_ok=True)  # until the new files are all written
  (folder / CONFIG).write_text(experiment.to_json(policy.config))
  tree = {"params": policy.params}
  if policy.normalizer is not None:
    tree["normalizer"] = {
        name: {"count": s.count, "mean": s.mean, "m2": s.m2}
        for name, s in policy.normalizer.items()
    }
  flat = flax.traverse_util.flatten_dict(jax.device_get(tree), sep="/")
  with open(folder / ARRAYS, "wb") as f:
    np.savez(f, **{k: np.asarray(v) for k, v in flat.items()})
  (folder / CARD).write_text(card(policy))
  (folder / ONNX).unlink(missing_ok=True)
  info = {
      "format": FORMAT, "iteration": int(policy.iteration), "seed": int(policy.seed),
      "saved_from": policy.source, "task": policy.config.task, "algo": policy.config.algo
  }
  (folder / INFO).write_text(json.dumps(info, indent=2) + "\n")
  return folder


def card(policy: Policy) -> str:
  """The ``card.md`` of a policy folder: what the policy is and how to use it."""
  cfg = policy.config
  hidden = "-".join(str(w) for w in cfg.train.actor_hidden)
  groups = ", ".join(sorted(policy.params["actors"]))
  return "\n".join([
      f"# MASH policy: {cfg.task}, {cfg.algo}", "",
      f"- task `{cfg.task}`, algorithm `{cfg.algo}`, preset `{cfg.preset}`, ablation "
      f"`{cfg.ablation}`; robot `{cfg.env.robot}`, `{cfg.env.partition}` partition",
      f"- checkpoint iteration {policy.iteration}, seed {policy.seed} of its run; loaded from "
      f"`{policy.source}`", f"- actors: {groups} (MLP {hidden}, ELU), deterministic mean action at "
      f"{1.0 / cfg.env.ctrl_dt:g} Hz; observation normalization "
      f"{'on' if policy.normalizer is not None else 'off'}", "",
      f"Files: `{CONFIG}` (the run's config), `{ARRAYS}` (actor parameters and observation "
      f"statistics, {FORMAT}), `{INFO}`, this card, and `{ONNX}` when exported.", "",
      "Use: `mash.deploy.policy.load(FOLDER)`, or `python -m experiments.evaluate --run FOLDER`, "
      "`experiments.export` and `experiments.sim2sim` likewise (`docs/deploy.md`).", ""
  ])


def actor_networks(policy: Policy, env: env_lib.MashEnv) -> networks.Networks:
  """The networks of ``policy``'s config on ``env``'s agent groups (acting uses the actors only);
  RunError when the policy's actor parameters do not fit them."""
  nets = networks.make_networks(env.agent_groups, env.critic_obs_size, policy.config.train)
  expected = jax.eval_shape(nets.init, jax.random.PRNGKey(0))["actors"]
  shapes = lambda tree: {
      k: tuple(np.shape(v)) for k, v in flax.traverse_util.flatten_dict(tree, sep="/").items()
  }
  want, got = shapes(expected), shapes(policy.params["actors"])
  if want != got:
    key = sorted(k for k in set(want) | set(got) if want.get(k) != got.get(k))[0]
    raise RunError(f"'{policy.source}': the actor parameters do not fit its config's networks "
                   f"(actors/{key}: {got.get(key)} saved, {want.get(key)} expected)")
  return nets


def make_inference_fn(
    policy: Policy,
    env: env_lib.MashEnv | None = None) -> Callable[[Mapping[str, jax.Array]], jax.Array]:
  """The deterministic policy: ``obs {group: [..., n_agents, obs_dim]} -> [..., action_size]``
  flat mean action (normalized observations when the run normalizes them).

  Args:
    policy: from :func:`load`.
    env: an env with the policy's agent partition (e.g. the evaluation env); by default one is
      built from ``policy.config.env``.
  """
  env = env_lib.MashEnv(policy.config.env) if env is None else env
  apply = networks.make_policy_fn(actor_networks(policy, env), deterministic=True)
  params, normalizer = policy.params, policy.normalizer
  return lambda obs: apply(params, normalizer, obs)


def _log(run_dir: Path, name: str) -> Path | None:
  """A run's log ``name`` (``progress.csv``, ``progress_seeds.csv``), as written by training or,
  in a committed record, gzip-compressed (``name.gz``); None when it has neither."""
  for path in (run_dir / name, run_dir / f"{name}.gz"):
    if path.is_file():
      return path
  return None


def read_progress(run_dir: str | os.PathLike, per_seed: bool = False) -> dict[str, np.ndarray]:
  """Columns of a run's progress log as float arrays ``[rows]``: ``progress.csv`` (one row per
  iteration, mean over seeds) or, with ``per_seed``, ``progress_seeds.csv`` (one row per
  iteration and seed, with a ``seed`` column). A one-seed run keeps no per-seed log: its
  ``progress.csv`` is returned with a ``seed`` column of zeros. Either log may be gzip-compressed
  (``.csv.gz``, a committed record, whose float32 cells are written with 9 digits; each cell is
  read with :func:`mash.runs.records.read_cell`, so they are the values training logged). Empty
  when the run has logged nothing."""
  run_dir = Path(run_dir)
  path = _log(run_dir, "progress_seeds.csv" if per_seed else "progress.csv")
  if path is None:
    if per_seed and _log(run_dir, "progress.csv") is not None:
      columns = read_progress(run_dir)
      return {**columns, "seed": np.zeros_like(columns["iteration"])} if columns else {}
    raise RunError(f"'{run_dir}' has no progress log (progress.csv)")
  opener = gzip.open if path.suffix == ".gz" else open
  with opener(path, "rt", newline="") as f:
    rows = list(csv.DictReader(f))
  if not rows:
    return {}
  return {k: np.array([records.read_cell(r[k], k) for r in rows]) for k in rows[0]}
