"""ONNX export: the hand-built graph against the JAX policy, on random weights and the smoke run.

The reference is independent of the graph's gather tables: it assembles observations with the env's
own ``MashEnv.observe`` and applies the flax actors through ``Networks.policy_apply``. Random runs
are built without any MJX compile: parameter shapes from ``jax.eval_shape(networks.init)``, values
from NumPy (larger than the trained init, so differences would show), and a random normalizer with
some variances under the floor.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import onnx
import pytest

from mash.deploy import export
from mash.deploy import policy as policy_lib
from mash.rl import networks, normalization
from mash.rl.config import TrainConfig
from mash.runs import experiment
from mash.runs import loop as runs
from mash.sim import env as env_lib
from mash.sim import env_config

TOL = 1e-5


def random_run(task: str, partition: str = "mash", share_actor: bool = True, seed: int = 0,
               **env_overrides) -> export.PolicyParts:
  """The parts of a policy with random actor weights and normalizer on a real (uncompiled)
  MashEnv."""
  env_cfg = env_config.EnvConfig(task=task, partition=partition, **env_overrides)
  env = env_lib.MashEnv(env_cfg)
  train_cfg = TrainConfig(actor_hidden=(32, 16), critic_hidden=(8,), share_actor=share_actor)
  nets = networks.make_networks(env.agent_groups, env.critic_obs_size, train_cfg)
  shapes = jax.eval_shape(nets.init, jax.random.PRNGKey(0))
  rng = np.random.default_rng(seed)

  # Weights at 1/sqrt(fan_in) keep the actions of order one to ten, like a trained policy's: the
  # 1e-5 tolerance is absolute, and float32 spacing alone is 4e-6 at 32.
  def draw(s):
    fan_in = s.shape[-2] if len(s.shape) >= 2 else 10.0
    return jnp.asarray(rng.normal(0.0, 1.0 / math.sqrt(fan_in), s.shape), jnp.float32)

  params = jax.tree.map(draw, shapes)
  normalizer = {}
  for g in env.agent_groups:
    var = rng.uniform(0.0, 4.0, g.obs_dim) * (rng.uniform(size=g.obs_dim) > 0.15)  # some floored
    normalizer[g.name] = normalization.RunningStats(
        count=jnp.float32(50.0), mean=jnp.asarray(rng.normal(0.0, 0.5, g.obs_dim), jnp.float32),
        m2=jnp.asarray(50.0 * var, jnp.float32))
  algo = "ppo" if partition == "ppo" else "mash"
  cfg = experiment.ExperimentConfig(task=task, algo=algo, env=env_cfg, train=train_cfg)
  policy = policy_lib.Policy(cfg, {"actors": params["actors"]}, normalizer, 7, 0, "random")
  return export.policy_parts(policy, env)


CASES = {
    "bipedal_mash":
        dict(task="bipedal"),
    "armswing_mash":
        dict(task="armswing"),
    "armswing_ppo":
        dict(task="armswing", partition="ppo"),
    "armswing_per_limb":
        dict(task="armswing", partition="per_limb"),
    # Ablations that change the graph: per-agent actors, no one-hot id, no temporal director.
    "bipedal_no_sharing_no_id_no_td":
        dict(task="bipedal", share_actor=False, agent_id=False, temporal_director=False),
}


@pytest.mark.parametrize("case", list(CASES))
def test_onnx_matches_jax(case, tmp_path):
  run = random_run(**CASES[case])
  path = export.export_policy(run, tmp_path / "policy.onnx")
  diff = export.verify(path, run, n=256)
  assert diff["action"] <= TOL and diff["q_target"] <= TOL, diff
  # The check is not vacuous: the actions are of order one.
  inputs = export.random_inputs(run.env, 8, seed=1)
  action, q_target = export.onnx_session(path).run(None, inputs)
  assert action.shape == q_target.shape == (8, run.env.action_size)
  assert np.abs(action).max() > 0.1


def test_check_sees_a_drifted_weight(tmp_path):
  # The file against a reference whose output bias of one leg joint is 1e-4 higher: the mean of
  # that joint moves by 1e-4 in both leg agents (shared actor), its target by 0.25 * 1e-4, so the
  # check must report those, ten and 2.5 times its tolerance, not the export's usual 1e-6.
  run = random_run("bipedal")
  path = export.export_policy(run, tmp_path / "policy.onnx")
  target = ("actors", "legs", "params", "MLP_0", "Dense_2", "bias")  # actor_hidden (32, 16)
  hits = []

  def drift(keys, x):
    if tuple(k.key for k in keys) != target:
      return x
    hits.append(keys)
    return x + np.float32(1e-4) * (np.arange(x.shape[-1]) == 0)  # entry 0 only

  drifted = run._replace(params=jax.tree_util.tree_map_with_path(drift, run.params))
  assert len(hits) == 1
  diff = export.verify(path, drifted, n=256)
  assert abs(diff["action"] - 1e-4) < 5e-6, diff
  assert abs(diff["q_target"] - 2.5e-5) < 2e-6, diff
  assert max(diff["action"], diff["q_target"]) > TOL


def test_unnormalized_run_matches_jax(tmp_path):
  run = random_run("armswing")._replace(normalizer=None)
  path = export.export_policy(run, tmp_path / "policy.onnx")
  diff = export.verify(path, run, n=64)
  assert max(diff["action"], diff["q_target"]) <= TOL


def test_observation_layout_by_hand():
  # Bipedal MASH, J = 20 joints (legs 0-5, 6-11; arms 12-19), A = 12, L = 4 limbs. Feature row:
  # q_rel 0-19 | dq 20-39 | last_action 40-51 | sin 52-55 | cos 56-59 | euler 60-62 |
  # ang_vel 63-65 | command 66-69 | zero 70 | one 71.
  env = env_lib.MashEnv(env_config.EnvConfig(task="bipedal"))
  lay = export.layout(env)
  assert (lay.width, lay.zero, lay.one) == (72, 70, 71)
  right_leg = lay.obs_index["legs"][1]  # joints 6..11, limb 1
  expected = ([6, 7, 8, 9, 10, 11] + [26, 27, 28, 29, 30, 31] + [46, 47, 48, 49, 50, 51] +
              [53, 57] + list(range(60, 70)) + [70, 71])  # one-hot (0, 1): zero, one
  assert right_leg.tolist() == expected
  np.testing.assert_allclose(lay.phase_offset, [0.0, 0.5, 0.5, 0.0])  # legs 0/0.5, arms opposite


def test_q_target_and_metadata(tmp_path):
  run = random_run("bipedal")
  env = run.env
  path = export.export_policy(run, tmp_path / "policy.onnx")
  model = onnx.load(str(path))
  assert [i.name for i in model.graph.input] == list(export.INPUTS)
  assert [o.name for o in model.graph.output] == list(export.OUTPUTS)
  assert model.opset_import[0].version == export.OPSET

  meta = export.read_metadata(path)
  assert meta["joint_order"] == list(env.spec.joints)
  assert meta["controlled_joints"] == list(env.spec.joints[:12])  # bipedal: the legs
  assert meta["control_rate_hz"] == 50.0 and meta["action_scale"] == 0.25
  assert meta["default_pose_rad"][:4] == [-0.2, 0.0, 0.0, 0.4]  # hip pitch/roll/yaw, knee
  assert meta["checkpoint_iteration"] == 7

  # q_target = default + 0.25 * clip(action, -10, 10), batch of one.
  inputs = {k: v[:1] for k, v in export.random_inputs(env, 4).items()}
  inputs["last_action"][:] = 0.0
  action, q_target = export.onnx_session(path).run(None, inputs)
  default = np.array(meta["default_pose_rad"], np.float32)[:12]
  np.testing.assert_allclose(q_target, default + 0.25 * np.clip(action, -10, 10), atol=1e-6)


def test_seed_out_of_range(smoke_run, tmp_path, capsys):
  from experiments import export as export_cli
  with pytest.raises(SystemExit) as e:
    export_cli.main(["--run", str(smoke_run), "--seed", "3", "--out", str(tmp_path / "x.onnx")])
  assert e.value.code == 2
  err = capsys.readouterr().err.strip()
  assert err.startswith("error: seed 3 is out of range: the run has 1 seed") and "\n" not in err
  assert not (tmp_path / "x.onnx").exists()


def test_export_cli_on_smoke_run(smoke_run, tmp_path, capsys):
  from experiments import export as export_cli
  out = tmp_path / "smoke.onnx"
  export_cli.main(["--run", str(smoke_run), "--out", str(out)])
  text = capsys.readouterr().out
  assert "check on 256 random observations" in text and text.rstrip().endswith("OK"), text
  meta = export.read_metadata(out)
  assert meta["task"] == "bipedal" and meta["algo"] == "mash"
  assert meta["checkpoint_iteration"] == runs.load_config(smoke_run).train.num_iterations


def test_export_cli_bad_run(tmp_path, capsys):
  from experiments import export as export_cli
  with pytest.raises(SystemExit) as e:
    export_cli.main(["--run", str(tmp_path / "missing")])
  assert e.value.code == 2
  err = capsys.readouterr().err.strip()
  assert err.startswith("error: run directory") and "\n" not in err
