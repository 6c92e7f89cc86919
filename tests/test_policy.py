"""mash.deploy.policy: a trained policy loaded without the trainer, saved as a small folder, and the
import graph of the deployment code (evaluate, export, play, sim2sim), which must not reach training
code.

The reference of the first test is the trainer itself: the smoke run's checkpoint restored into the
trainer's own state template (``runs.restore_run``, the way evaluation loaded policies before
``mash.deploy.policy``) and applied through the trainer's networks.
"""

from __future__ import annotations

import ast
import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mash.deploy import policy as policy_lib
from mash.rl import networks
from mash.runs import checkpoint, experiment
from mash.runs import loop as runs
from mash.sim import env as env_lib

REPO = Path(__file__).resolve().parents[1]
DEPLOYMENT = ("experiments.evaluate", "experiments.export", "experiments.play",
              "experiments.sim2sim", "mash.cli", "mash.deploy.policy", "mash.deploy.export",
              "mash.deploy.sim2sim", "mash.deploy.video", "mash.deploy.play",
              "mash.deploy.native_report", "mash.analysis.evaluation", "mash.analysis.metrics",
              "mash.analysis.reports")
TRAINING = ("mash.rl.mappo", "mash.rl.trainer", "mash.rl.distributed", "mash.rl.losses",
            "mash.runs.loop", "mash.runs.launch", "optax")


def random_obs(env, batch: int, seed: int = 0) -> dict[str, jax.Array]:
  """``{group: [batch, n_agents, obs_dim]}`` observations, spread wide enough that some
  normalized entries reach the clip."""
  rng = np.random.default_rng(seed)
  return {
      g.name: jnp.asarray(rng.normal(0.0, 3.0, (batch, g.n_agents, g.obs_dim)), jnp.float32)
      for g in env.agent_groups
  }


def assert_same_policy(a: policy_lib.Policy, b: policy_lib.Policy) -> None:
  """Equal parameters and normalizer, bit for bit, with the same tree structure and dtypes."""
  for x, y in ((a.params, b.params), (a.normalizer, b.normalizer)):
    assert jax.tree.structure(x) == jax.tree.structure(y)
    jax.tree.map(np.testing.assert_array_equal, x, y)
    assert [l.dtype for l in jax.tree.leaves(x)] == [l.dtype for l in jax.tree.leaves(y)]


def test_policy_acts_as_the_trainer(smoke_run, smoke_trainer, smoke_config):
  """The policy loaded without a trainer holds the trainer's restored actors and actor-stream
  statistics bit for bit, and acts as the trainer's networks do on them."""
  restored = runs.restore_run(smoke_run, smoke_trainer, fields=checkpoint.POLICY_FIELDS)
  policy = policy_lib.load(smoke_run)
  assert policy.iteration == int(restored.step) == smoke_config.train.num_iterations
  assert (policy.seed, policy.source, policy.config) == (0, str(smoke_run), smoke_config)
  assert set(policy.params) == {"actors"}  # no critic
  assert set(policy.normalizer) == {g.name for g in smoke_trainer.env.agent_groups}
  jax.tree.map(np.testing.assert_array_equal, policy.params["actors"],
               restored.state.params["actors"])
  for name, stats in policy.normalizer.items():
    jax.tree.map(np.testing.assert_array_equal, stats, restored.state.normalizer[name])

  obs = random_obs(smoke_trainer.env, 64)
  reference = jax.jit(networks.make_policy_fn(smoke_trainer.networks, deterministic=True))
  want = np.asarray(reference(restored.state.params, restored.state.normalizer, obs))
  got = np.asarray(jax.jit(policy_lib.make_inference_fn(policy))(obs))  # its own env
  assert got.shape == (64, smoke_trainer.env.action_size)
  np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
  assert np.abs(want).max() > 1e-3  # the comparison is not between zeros


def test_policy_folder_round_trip(smoke_run, tmp_path):
  """save -> load: the same config, iteration, seed, parameters and actions (bit for bit); the
  folder holds the four documented files, only actor parameters and statistics, and is small."""
  policy = policy_lib.load(smoke_run)
  folder = policy_lib.save(policy, tmp_path / "policy")
  assert sorted(p.name for p in folder.iterdir()) == [
      "card.md", "config.json", "policy.json", "policy.npz"
  ]
  size = sum(p.stat().st_size for p in folder.iterdir())
  # Smoke actor: 32-64-64-6 MLP (6,534 floats) + statistics: ~30 KiB of arrays, ~35 KiB in all.
  assert size < 64 * 1024, size
  with np.load(folder / "policy.npz", allow_pickle=False) as data:
    names = list(data.files)
  assert names and all(n.startswith(("params/actors/", "normalizer/")) for n in names), names
  assert not [n for n in names if "critic" in n], names
  info = json.loads((folder / "policy.json").read_text())
  assert info["format"] == policy_lib.FORMAT and info["iteration"] == policy.iteration

  loaded = policy_lib.load(folder)
  assert (loaded.config, loaded.iteration, loaded.seed) == (policy.config, policy.iteration,
                                                            policy.seed)
  assert loaded.source == str(folder) and policy_lib.load_all(folder)[0].source == str(folder)
  assert_same_policy(loaded, policy)
  env = env_lib.MashEnv(policy.config.env)
  obs = random_obs(env, 32, seed=1)
  act = lambda p: np.asarray(jax.jit(policy_lib.make_inference_fn(p, env))(obs))
  np.testing.assert_array_equal(act(loaded), act(policy))

  # Saved again from the folder: the same arrays; an old policy.onnx there is removed.
  (folder / "policy.onnx").write_bytes(b"stale")
  policy_lib.save(loaded, folder)
  assert not (folder / "policy.onnx").exists()
  assert_same_policy(policy_lib.load(folder), policy)


class _SeedState(NamedTuple):
  """The train state's policy fields, as ``checkpoint.save`` keys them (``.params``, ...)."""

  params: dict
  normalizer: dict


def test_a_multi_seed_run_gives_each_seed(smoke_run, smoke_config, tmp_path):
  """A checkpoint with a leading seed axis (as ``--seeds 2`` saves it, built here from the smoke
  policy and a scaled copy, no training): ``seed`` picks one, ``load_all`` gives both."""
  one = policy_lib.load(smoke_run)
  two = jax.tree.map(lambda x: 2.0 * x, (one.params, one.normalizer))
  stack = lambda a, b: jax.tree.map(lambda x, y: jnp.stack([x, y]), a, b)
  state = _SeedState(stack(one.params, two[0]), stack(one.normalizer, two[1]))
  cfg = dataclasses.replace(smoke_config, seeds=2)
  run = tmp_path / "two_seeds"
  run.mkdir()
  (run / "config.json").write_text(experiment.to_json(cfg))
  manager = checkpoint.make_manager(run / "checkpoints")
  checkpoint.save(manager, 10, state, cfg.train)
  manager.close()

  second = policy_lib.load(run, seed=1)
  assert second.seed == 1 and second.config.seeds == 2
  assert_same_policy(second, one._replace(params=two[0], normalizer=two[1]))
  assert [p.seed for p in policy_lib.load_all(run)] == [0, 1]
  assert_same_policy(policy_lib.load_all(run)[0], one)
  with pytest.raises(policy_lib.RunError, match=r"seed 2 is out of range: the run has 2 seed"):
    policy_lib.load(run, seed=2)


def test_paths_that_are_not_a_policy_are_one_line(smoke_run, tmp_path):
  policy = policy_lib.load(smoke_run)
  folder = policy_lib.save(policy, tmp_path / "policy")
  (tmp_path / "empty").mkdir()
  (tmp_path / "file").write_text("x")
  cases = [
      (lambda: policy_lib.load(tmp_path / "empty"),
       "is not a run directory or a policy folder (no config.json)"),
      (lambda: policy_lib.load(tmp_path / "file"), "is a file; expected a run directory or a "
       "policy folder"),
      (lambda: policy_lib.load(tmp_path / "missing"), "run directory '"),
      (lambda: policy_lib.load(folder, iteration=3), "is a policy folder of iteration 10 only"),
      (lambda: policy_lib.load(folder, seed=1), "seed 1 is out of range: the policy folder"),
      (lambda: policy_lib.load(smoke_run, seed=3), "seed 3 is out of range: the run has 1 seed"),
      (lambda: policy_lib.load(smoke_run, iteration=7), "no checkpoint of step 7"),
      (lambda: policy_lib.save(policy, smoke_run), "is a run directory"),
  ]
  for call, words in cases:
    with pytest.raises(policy_lib.RunError) as e:
      call()
    assert words in str(e.value) and "\n" not in str(e.value), str(e.value)
  assert runs.RunError is policy_lib.RunError  # the CLIs catch one class
  (folder / "policy.json").write_text(json.dumps({"format": "mash-policy-folder/99"}))
  with pytest.raises(policy_lib.RunError, match="is not 'mash-policy-folder/1'"):
    policy_lib.load(folder)


_GRAPH_PROBE = """
import json, sys
import experiments.evaluate, experiments.export, experiments.play, experiments.sim2sim
import mash.analysis.evaluation, mash.analysis.reports, mash.deploy.export, mash.deploy.policy
import mash.deploy.native_report, mash.deploy.play, mash.deploy.sim2sim, mash.deploy.video
import jax.numpy as jnp
from mash.sim import env as env_lib
from mash.deploy import policy
run, folder, onnx = sys.argv[1:4]
for source in (run, folder):
  p = policy.load(source)
  env = env_lib.MashEnv(p.config.env)
  policy.make_inference_fn(p, env)({g.name: jnp.zeros((g.n_agents, g.obs_dim))
                                    for g in env.agent_groups})
  policy.load_all(source)
experiments.export.main(["--run", folder, "--out", onnx, "--check", "8"])
print(json.dumps(sorted(m for m in json.loads(sys.argv[4]) if m in sys.modules)))
"""


def test_a_truncated_policy_archive_is_one_line(smoke_run, tmp_path):
  """A policy folder whose policy.npz was cut short (a copy interrupted): one RunError line
  naming the file, also through ``evaluate``, not a BadZipFile traceback."""
  folder = policy_lib.save(policy_lib.load(smoke_run), tmp_path / "policy")
  data = (folder / "policy.npz").read_bytes()
  (folder / "policy.npz").write_bytes(data[:len(data) // 2])
  with pytest.raises(policy_lib.RunError, match="policy.npz' is not a policy's arrays"):
    policy_lib.load(folder)
  out = subprocess.run([
      sys.executable, "-m", "experiments.evaluate", "--run",
      str(folder), "--episodes", "1", "--seconds", "0.1"
  ], cwd=REPO, capture_output=True, text=True, timeout=600, env=dict(os.environ,
                                                                     PYTHONPATH=str(REPO)))
  lines = [l for l in out.stderr.splitlines() if l.strip() and "warp" not in l]
  assert out.returncode == 2 and len(lines) == 1, out.stderr[-2000:]
  assert lines[0].startswith("error: ") and "policy.npz' is not a policy's arrays" in lines[0]


def test_deployment_does_not_import_training(smoke_run, tmp_path):
  """In a fresh process: import evaluate, export, play, sim2sim (the entry points and their
  modules), load the smoke run's policy and a policy folder, build the action function and export
  the folder through the CLI; then no training module is loaded (:data:`TRAINING`: the trainer,
  its losses, the host loop and the launcher, nor optax, the optimizer: flax.linen, which the
  networks use, does not import it; only training does)."""
  folder = policy_lib.save(policy_lib.load(smoke_run), tmp_path / "policy")
  out = subprocess.run([
      sys.executable, "-c", _GRAPH_PROBE,
      str(smoke_run),
      str(folder),
      str(tmp_path / "probe.onnx"),
      json.dumps(TRAINING)
  ], cwd=REPO, capture_output=True, text=True, timeout=600, env=dict(os.environ,
                                                                     PYTHONPATH=str(REPO)))
  assert out.returncode == 0, out.stderr[-3000:]
  assert "OK" in out.stdout, out.stdout
  assert json.loads(out.stdout.strip().splitlines()[-1]) == [], out.stdout


def _imported_names(module: str) -> set[str]:
  """Every module an import statement of ``module``'s source names, top level or inside a
  function (``from mash import runs`` names ``mash`` and ``mash.runs.loop``)."""
  path = REPO / (module.replace(".", "/") + ".py")
  names = set()
  for node in ast.walk(ast.parse(path.read_text())):
    if isinstance(node, ast.Import):
      names.update(a.name for a in node.names)
    elif isinstance(node, ast.ImportFrom) and node.module:
      names.add(node.module)
      names.update(f"{node.module}.{a.name}" for a in node.names)
  return names


@pytest.mark.parametrize("module", DEPLOYMENT)
def test_deployment_code_names_no_training_module(module):
  """The import statements of the deployment modules, also those inside functions that the
  subprocess test does not run (evaluation's rollouts, sim2sim's episodes), name no training
  module."""
  named = _imported_names(module)
  bad = sorted(n for n in named if any(n == t or n.startswith(t + ".") for t in TRAINING))
  assert not bad, f"{module} imports {bad}"
