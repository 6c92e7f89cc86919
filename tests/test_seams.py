"""Tests where the pieces meet (issue 27, item 6): each fails when its seam is broken.

- ``mappo_loss`` with real networks: agent ``k``'s advantage column must weigh agent ``k``'s own
  log-prob (the group and member the env's agent order names), and value column ``k`` must meet
  return column ``k``. Checked by making only agent ``k``'s advantage (or return error) non-zero
  and comparing the loss gradient with the gradient of that one agent's term written out.
- Gradient averaging over devices: ``train.loss_gradients`` on two devices, each holding half of a
  minibatch, must equal one device's gradient on the whole minibatch (a ``psum`` in place of the
  ``pmean`` doubles it; Adam's scale invariance would hide that from a comparison of parameters).
- sim2sim's robot side against the env: the MJX state copied into MuJoCo C (same model, converged
  solvers), then the sensor reads, the exported policy's action on them, the gait clock and the
  state after each control step's PD loop must agree. Checked to fail with the torque held over
  the control period, roll and pitch swapped in the readings, or the clock a step ahead.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from mash.rl import losses
from mash.rl import networks as nets
from mash.rl.config import TrainConfig

from toy_env import make_toy_env

ROOT = Path(__file__).resolve().parents[1]
M = 6  # samples in the minibatch


def _agent_order(groups) -> list[tuple[str, int]]:
  """``(group, member)`` of each agent column: groups in order, members in order (the env's)."""
  return [(g.name, i) for g in groups for i in range(g.n_agents)]


@pytest.fixture(scope="module")
def setup():
  """Toy legs + arms (MASH partition: two groups of two agents), small networks, one minibatch."""
  env = make_toy_env("legs_arms", "mash")
  config = TrainConfig(actor_hidden=(16,), critic_hidden=(16,), init_log_std=-0.5,
                       normalize_advantages=False, clip_epsilon=1e6, value_clip=0.0,
                       entropy_coef=0.0)
  networks = nets.make_networks(env.agent_groups, env.critic_obs_size, config)
  params = networks.init(jax.random.PRNGKey(0))
  obs = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(1), M)).obs
  keys = iter(jax.random.split(jax.random.PRNGKey(2), 8))
  actions = {
      g.name: jax.random.normal(next(keys), (M, g.n_agents, g.act_dim)) for g in env.agent_groups
  }
  dists = networks.policy_apply(params, None, obs)
  log_probs = nets.per_agent(
      env.agent_groups,
      {g.name: nets.gaussian_log_prob(dists[g.name], actions[g.name]) for g in env.agent_groups})
  values = networks.value_apply(params, None, obs["critic"])
  return dict(env=env, config=config, networks=networks, params=params, obs=obs, actions=actions,
              log_probs=log_probs, values=values)


def _grad(fn, params):
  return jax.jit(jax.grad(fn))(params)


@pytest.mark.parametrize("k", [0, 1, 2, 3])
def test_advantage_k_weighs_agent_k_log_prob(setup, k):
  """Advantage 1 for agent ``k`` only, ratio 1 (old log-probs = current): the policy-loss gradient
  is ``-grad mean log pi(a_k | o_k)`` of agent k's own row of its group's actor."""
  s = setup
  n = s["log_probs"].shape[-1]
  advantages = jnp.zeros((M, n)).at[:, k].set(1.0)
  batch = losses.LossBatch(obs=s["obs"], actions=s["actions"], log_probs=s["log_probs"],
                           values=s["values"], advantages=advantages, returns=s["values"])
  config = s["config"]
  got = _grad(lambda p: losses.mappo_loss(p, None, batch, s["networks"], config)[0], s["params"])

  group, member = _agent_order(s["env"].agent_groups)[k]

  def own_term(p):
    dist = s["networks"].policy_apply(p, None, s["obs"])[group]
    return -jnp.mean(nets.gaussian_log_prob(dist, s["actions"][group])[:, member])

  want = _grad(own_term, s["params"])
  chex.assert_trees_all_close(got, want, atol=1e-6, rtol=1e-5)
  # The check can tell agents apart: another agent's term has another gradient.
  other_group, other_member = _agent_order(s["env"].agent_groups)[(k + 1) % n]
  other = _grad(
      lambda p: -jnp.mean(
          nets.gaussian_log_prob(s["networks"].policy_apply(p, None, s["obs"])[other_group], s[
              "actions"][other_group])[:, other_member]), s["params"])
  diff = jax.tree.map(lambda a, b: float(jnp.max(jnp.abs(a - b))), want, other)
  assert max(jax.tree.leaves(diff)) > 1e-3


@pytest.mark.parametrize("k", [0, 3])
def test_return_k_trains_value_head_k(setup, k):
  """Returns off by 1 for agent ``k`` only (zero advantages): the critic gradient is that of
  ``mean((V_k - R_k)^2) / N``, value head k alone (the value loss is a mean over agents)."""
  s = setup
  n = s["values"].shape[-1]
  returns = s["values"].at[:, k].add(1.0)
  batch = losses.LossBatch(obs=s["obs"], actions=s["actions"], log_probs=s["log_probs"],
                           values=s["values"], advantages=jnp.zeros((M, n)), returns=returns)
  got = _grad(lambda p: losses.mappo_loss(p, None, batch, s["networks"], s["config"])[0],
              s["params"])

  def own_term(p):
    v = s["networks"].value_apply(p, None, s["obs"]["critic"])[:, k]
    return jnp.mean(jnp.square(v - returns[:, k])) / n

  chex.assert_trees_all_close(got, _grad(own_term, s["params"]), atol=1e-6, rtol=1e-5)


TWO_DEVICE_GRADIENTS = textwrap.dedent("""
    import jax, jax.numpy as jnp, numpy as np
    from jax.sharding import PartitionSpec as P
    from mash.rl import losses
    from mash.rl import networks as nets
    from mash.rl import mappo as train
    from mash.rl.config import TrainConfig
    from toy_env import make_toy_env
    assert jax.device_count() == 2, jax.devices()
    env = make_toy_env('legs_arms', 'mash')
    config = TrainConfig(actor_hidden=(16,), critic_hidden=(16,))  # advantages normalized
    networks = nets.make_networks(env.agent_groups, env.critic_obs_size, config)
    params = networks.init(jax.random.PRNGKey(0))
    m = 8
    obs = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(1), m)).obs
    k = iter(jax.random.split(jax.random.PRNGKey(2), 8))
    n = sum(g.n_agents for g in env.agent_groups)
    actions = {g.name: jax.random.normal(next(k), (m, g.n_agents, g.act_dim))
               for g in env.agent_groups}
    values = networks.value_apply(params, None, obs['critic'])
    batch = losses.LossBatch(
        obs=obs, actions=actions, log_probs=-jax.random.uniform(next(k), (m, n)) - 3.0,
        values=values, advantages=jax.random.normal(next(k), (m, n)),
        returns=values + jax.random.normal(next(k), (m, n)))
    one, one_metrics = jax.jit(lambda b: train.loss_gradients(params, None, b, networks,
                                                              config))(batch)
    mesh = jax.make_mesh((2,), ('devices',), axis_types=(jax.sharding.AxisType.Auto,))
    two, two_metrics = jax.jit(jax.shard_map(
        lambda b: train.loss_gradients(params, None, b, networks, config, 'devices'),
        mesh=mesh, in_specs=(P('devices'),), out_specs=P(), check_vma=False))(batch)
    for a, b in zip(jax.tree.leaves((one, one_metrics)), jax.tree.leaves((two, two_metrics))):
      np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=2e-5, atol=1e-6)
    assert max(float(jnp.max(jnp.abs(x))) for x in jax.tree.leaves(one)) > 1e-3
    print('OK')
""")


def test_two_devices_average_gradients_to_the_whole_minibatch():
  env = dict(
      os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
      PYTHONPATH=os.pathsep.join([str(ROOT),
                                  str(ROOT / "tests"),
                                  os.environ.get("PYTHONPATH", "")]), JAX_PLATFORMS="cpu")
  result = subprocess.run([sys.executable, "-c", TWO_DEVICE_GRADIENTS], env=env, cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
  assert result.returncode == 0 and "OK" in result.stdout, result.stdout + result.stderr[-3000:]


SIM2SIM_STEPS = 3  # control steps compared after the copied state


def test_sim2sim_sensors_and_pd_loop_match_mjx_on_the_same_state(smoke_run, tmp_path):
  """sim2sim's robot side (sensor reads, the ONNX inputs built from them, the PD loop at the
  motor rate) against the env's on one state: MuJoCo C built with the env's model, collision set
  and (converged) solver settings, the MJX state copied in (warm start included), randomization
  off. The readings, the action the exported policy returns, the gait clock and the state after
  each control step must agree."""
  from mash.analysis import evaluation
  from mash.deploy import export, sim2sim
  from mash.deploy import policy as policy_lib
  from mash.sim import env as env_lib

  policy = policy_lib.load(smoke_run)
  eval_cfg = evaluation.EvalConfig(randomization=False, episode_s=1.0, num_episodes=1)
  # Converged solvers on both sides: at the training's one Newton iteration MJX's and MuJoCo C's
  # solvers part by ~3e-3 rad in a control step, which would hide a seam's error.
  env_cfg = evaluation.eval_env_config(policy.config.env, eval_cfg)
  phys = dataclasses.replace(env_cfg.physics, iterations=20, ls_iterations=20)
  env = env_lib.MashEnv(dataclasses.replace(env_cfg, physics=phys))
  act = jax.jit(policy_lib.make_inference_fn(policy, env))
  step, sensors = jax.jit(env.step), jax.jit(env.sensors)  # eagerly, MJX runs op by op: minutes
  state = jax.jit(env.reset)(jax.random.PRNGKey(3))
  for _ in range(10):  # off the home pose
    state = step(state, act(state.obs))
  d = state.pipeline_state  # and moving: the PD loop has work to do
  kick = 0.5 * jax.random.normal(jax.random.PRNGKey(4), d.qvel.shape)
  state = state.replace(pipeline_state=d.replace(qvel=d.qvel + kick))
  state = step(state, act(state.obs))  # observations of the kicked state

  onnx_path = export.export_policy(policy, tmp_path / "policy.onnx")
  dep = sim2sim.Deployment.from_metadata(export.read_metadata(onnx_path))
  robot = sim2sim.NativeRobot(
      env.spec, dep,
      sim2sim.Sim2SimConfig(sim_dt=phys.sim_dt, iterations=phys.iterations,
                            ls_iterations=phys.ls_iterations, integrator=phys.integrator,
                            full_collision=False))
  controller = sim2sim.Controller(export.onnx_session(onnx_path), dep)
  d = state.pipeline_state
  robot.data.qpos[:] = np.asarray(d.qpos, np.float64)
  robot.data.qvel[:] = np.asarray(d.qvel, np.float64)
  robot.data.qacc_warmstart[:] = np.asarray(d.qacc_warmstart, np.float64)
  mujoco.mj_forward(robot.model, robot.data)
  controller.phase = float(state.info["phase"])
  controller.last_action = np.asarray(state.info["last_action"], np.float32)
  command = np.asarray(state.info["command"], np.float64)

  worst = {}

  def close(what, ours, theirs, atol):
    err = float(np.max(np.abs(np.asarray(ours, np.float64) - np.asarray(theirs, np.float64))))
    worst[what] = max(worst.get(what, 0.0), err)
    assert err <= atol, f"step {t}: {what} differs by {err:.3g} (tolerance {atol:g})"

  for t in range(SIM2SIM_STEPS):
    # float64 against float32: the same state reads the same to ~1e-6, and a converged step
    # lands within ~1e-6 in angle and ~1e-4 in rate (measured: 2e-7 rad, 2e-5 rad/s). The base
    # height is compared after steps only: both read it, as MuJoCo's step leaves it, from body
    # positions of the last substep's start, which the copy (mj_forward) does not have.
    ours, theirs = robot.sensors(), sensors(state.pipeline_state)
    for key in ("q", "dq", "euler", "ang_vel", "lin_vel", "base_height")[:5 + (t > 0)]:
      close(key, ours[key], theirs[key], 1e-3 if key in ("dq", "ang_vel", "lin_vel") else 1e-5)
    action, target = controller.act(ours, command)
    close("action", action, act(state.obs), 1e-4)  # the exported policy on sim2sim's readings
    robot.step(target)
    state = step(state, jnp.asarray(action))
    close("gait phase", controller.phase, state.info["phase"], 1e-6)
    close("qpos", robot.data.qpos, state.pipeline_state.qpos, 1e-5)
    close("qvel", robot.data.qvel, state.pipeline_state.qvel, 1e-3)
  print("sim2sim against MJX, max |difference|:", {k: f"{v:.2g}" for k, v in worst.items()})
  assert float(jnp.max(jnp.abs(state.pipeline_state.qvel[6:]))) > 0.3  # the joints did move
