"""Tests for mash.sim.env, mash.sim.randomize and the T1 robot spec.

Most tests call pure functions (``pd_torque``, ``quat_to_euler``, ``MashEnv.observe`` on hand-built
sensor dicts, ``randomize.sample`` / ``apply``): no MJX step, so nothing slow to compile. Three
MJX programs are compiled, once each: a batched reset + scanned rollout of the bipedal env with
domain randomization on (short episodes, to see time-outs and auto-resets), the same for the
nominal robot (DR off) for the standing test (both session fixtures), and one batched step of
1-step episodes for the friction curriculum's test.
"""

import dataclasses

import chex
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mash.analysis import evaluation
from mash.sim import env as env_lib
from mash.sim import env_config, geometry, randomize, rewards, robots

T1 = robots.load("booster_t1")
DR_OFF = randomize.DomainRandConfig(enabled=False)
EPISODE_LENGTH = 50  # control steps of the DR-on env (1 s), so a 200-step rollout sees time-outs
RANDOM_STEPS = 200  # random-action rollout (DR on)
STAND_STEPS = 100  # 2 s at 50 Hz (DR off)
SHARED = 3 + 3 + 4  # euler, angular velocity, command


# ------------------------------------------------------------------------------------- fixtures
def _make_simulate(env):
  """jit(keys [B], actions [T, B, A]) -> (first state, last state, per-step trace): one program."""
  reset, step = jax.vmap(env.reset), jax.vmap(env.step)

  def simulate(keys, actions):
    state0 = reset(keys)

    def body(state, action):
      state = step(state, action)
      qpos = state.pipeline_state.qpos
      trace = dict(qpos=qpos, qvel=state.pipeline_state.qvel, z=qpos[:, 2], euler=jax.vmap(
          geometry.quat_to_euler)(qpos[:, 3:7]), done=state.done, reward=state.reward,
                   metrics=state.metrics, step=state.info["step"],
                   env_steps=state.info["env_steps"], truncation=state.info["truncation"],
                   fall=state.info["fall"], torque=state.info["last_torque"],
                   ctrl=state.pipeline_state.ctrl, next_critic_obs=state.info["next_critic_obs"],
                   push=state.info["push"], obs=state.obs)
      return state, trace

    last, trace = jax.lax.scan(body, state0, actions)
    return state0, last, trace

  return jax.jit(simulate)


@pytest.fixture(scope="session")
def dr_env():
  """Bipedal MASH env, domain randomization on, 1 s episodes, agents observing their last 2
  steps (the nominal env below keeps the paper's 1, so both paths run in MJX)."""
  return env_lib.make_env("bipedal", "mash", episode_length=EPISODE_LENGTH, actor_history=2)


@pytest.fixture(scope="session")
def nominal_env():
  """Bipedal MASH env, domain randomization off (nominal robot, no delay, no pushes)."""
  return env_lib.make_env("bipedal", "mash", randomization=DR_OFF)


@pytest.fixture(scope="session")
def armswing_env():
  """Armswing MASH env (legs and arms act); only its pure functions are called."""
  return env_lib.make_env("armswing", "mash")


@pytest.fixture(scope="session")
def random_rollout(dr_env):
  """4 envs, DR on, 200 steps of uniform actions in [-1, 1]: (state0, last, trace), numpy."""
  b = 4
  actions = jax.random.uniform(jax.random.key(1), (RANDOM_STEPS, b, dr_env.action_size),
                               minval=-1.0, maxval=1.0)
  out = _make_simulate(dr_env)(jax.random.split(jax.random.key(0), b), actions)
  return _to_numpy(out)


@pytest.fixture(scope="session")
def standing_rollout(nominal_env):
  """2 envs, DR off, default pose, zero action for 2 s: (state0, last, trace), numpy."""
  b = 2
  actions = jnp.zeros((STAND_STEPS, b, nominal_env.action_size))
  out = _make_simulate(nominal_env)(jax.random.split(jax.random.key(2), b), actions)
  return _to_numpy(out)


# -------------------------------------------------------------------------------------- helpers
def _to_numpy(tree):
  """Device arrays -> numpy (typed PRNG keys -> their raw key data)."""

  def conv(x):
    if jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
      x = jax.random.key_data(x)
    return np.asarray(x)

  return jax.tree.map(conv, tree)


def _controlled_joints(env):
  """Joint name of each entry of the flat action vector (per-limb groups), from the agent groups."""
  limbs = {l.name: l for l in env.spec.limbs}
  names = [None] * env.action_size
  for g in env.agent_groups:
    for member, idx in zip(g.members, g.action_index):
      for j, pos in zip(limbs[member].joints, idx):
        names[pos] = j
  return names


def _mirror(values, names):
  """Sagittal mirror of a joint-indexed vector: swap left/right partners, apply mirror_sign."""
  pos = {n: i for i, n in enumerate(names)}
  out = np.empty_like(values)
  partner = {}
  for group in ("legs", "arms"):
    left, right = T1.limbs_of(group)
    partner.update({**dict(zip(left.joints, right.joints)), **dict(zip(right.joints, left.joints))})
  for i, n in enumerate(names):
    out[i] = T1.mirror_sign[T1.role_of(n)] * values[pos[partner[n]]]
  return out


def _random_inputs(env, seed, phase=0.3, standing=0.0):
  """A hand-built sensor dict, info dict and contact mask (numpy, nominal DR params)."""
  rng = np.random.default_rng(seed)
  nj = env.n_joints
  q_default = np.array([T1.default_pose[j] for j in T1.joints])
  sensors = dict(q=q_default + rng.normal(0, 0.2, nj), dq=rng.normal(0, 1.0, nj),
                 euler=rng.normal(0, 0.1, 3), ang_vel=rng.normal(0, 0.5,
                                                                 3), lin_vel=rng.normal(0, 0.5, 3))
  command = np.array([standing, *(rng.uniform(-0.5, 0.5, 3) * (1.0 - standing))])
  info = dict(command=command, phase=np.asarray(phase),
              last_action=rng.uniform(-1, 1, env.action_size),
              dr=randomize.nominal(env.mj_model.nbody, nj), push=rng.uniform(-5, 5, 5))
  return sensors, info, np.array([1.0, 0.0])


def _observe(env, sensors, info, contact):
  return jax.tree.map(
      np.asarray,
      env.observe({k: jnp.asarray(v, jnp.float32) for k, v in sensors.items()}, {
          k: (jnp.asarray(v, jnp.float32) if isinstance(v, np.ndarray) else v)
          for k, v in info.items()
      }, jnp.asarray(contact, jnp.float32)))


def _mirror_inputs(env, sensors, info):
  """The sagittal mirror of a state: joints swapped with signs, roll/yaw, wx/wz, vy, yaw-rate
  negated, gait phase half a cycle on."""
  flip_xz = np.array([-1.0, 1.0, -1.0])
  s = dict(sensors, q=_mirror(sensors["q"], T1.joints), dq=_mirror(sensors["dq"], T1.joints),
           euler=sensors["euler"] * flip_xz, ang_vel=sensors["ang_vel"] * flip_xz,
           lin_vel=sensors["lin_vel"] * np.array([1.0, -1.0, 1.0]))
  i = dict(info, command=info["command"] * np.array([1.0, 1.0, -1.0, -1.0]),
           phase=np.mod(info["phase"] + 0.5,
                        1.0), last_action=_mirror(info["last_action"], _controlled_joints(env)))
  return s, i


# ---------------------------------------------------------------------------- pure functions
def test_pd_torque_hand_values():
  """tau = kp (q* - q) - kd dq inside the limits."""
  tau = env_lib.pd_torque(q_target=jnp.array([0.1, -0.2, 0.0]), q=jnp.array([0.0, 0.0, 0.05]),
                          dq=jnp.array([1.0, -0.5, 0.0]), kp=jnp.array([100.0, 50.0, 200.0]),
                          kd=jnp.array([2.0, 4.0, 3.0]), tau_max=jnp.array([45.0, 30.0, 60.0]))
  # 100*0.1 - 2*1 = 8;  50*(-0.2) - 4*(-0.5) = -10 + 2 = -8;  200*(-0.05) - 0 = -10.
  chex.assert_trees_all_close(tau, jnp.array([8.0, -8.0, -10.0]), atol=1e-5)


def test_pd_torque_clips_at_limits():
  """Large target errors (either sign) and large velocities saturate at +-tau_max, no further."""
  tau_max = jnp.array([45.0, 30.0, 60.0, 20.0])
  tau = env_lib.pd_torque(q_target=jnp.array([10.0, -10.0, 0.0, 0.3]), q=jnp.zeros(4),
                          dq=jnp.array([0.0, 0.0, -100.0,
                                        0.0]), kp=jnp.array([150.0, 150.0, 200.0, 150.0]),
                          kd=jnp.array([3.0] * 4), tau_max=tau_max)
  # 1500 -> 45;  -1500 -> -30;  -3*(-100) = 300 -> 60;  150*0.3 = 45 -> 20.
  chex.assert_trees_all_close(tau, jnp.array([45.0, -30.0, 60.0, 20.0]))
  # Just under the limit: not clipped. 150*0.1 = 15 < 20.
  assert float(env_lib.pd_torque(0.1, 0.0, 0.0, 150.0, 3.0, 20.0)) == pytest.approx(15.0)


def test_quat_to_euler_matches_scipy():
  """ZYX roll/pitch/yaw from a (w, x, y, z) quaternion, against scipy's intrinsic 'ZYX'."""
  chex.assert_trees_all_close(geometry.quat_to_euler(jnp.array([1.0, 0, 0, 0])), jnp.zeros(3))
  # Rotation about x by 0.3: q = (cos 0.15, sin 0.15, 0, 0) -> roll 0.3.
  q = jnp.array([np.cos(0.15), np.sin(0.15), 0.0, 0.0])
  chex.assert_trees_all_close(geometry.quat_to_euler(q), jnp.array([0.3, 0.0, 0.0]), atol=1e-6)
  rng = np.random.default_rng(0)
  for _ in range(5):
    rpy = rng.uniform([-1.0, -1.2, -3.0], [1.0, 1.2, 3.0])
    x, y, z, w = Rotation.from_euler("ZYX", rpy[::-1]).as_quat()
    chex.assert_trees_all_close(geometry.quat_to_euler(jnp.array([w, x, y, z])),
                                jnp.asarray(rpy, jnp.float32), atol=1e-5)


# ---------------------------------------------------------------------------------- observations
@pytest.mark.parametrize("task,partition,sizes,action_size", [
    ("bipedal", "mash", {"legs": (2, 32), "critic": (106,)}, 12),
    ("armswing", "mash", {"legs": (2, 32), "arms": (2, 26), "critic": (106,)}, 20),
    ("bipedal", "ppo", {"body": (1, 50), "critic": (106,)}, 12),
    ("armswing", "ppo", {"body": (1, 78), "critic": (106,)}, 20),
])
def test_observation_sizes(task, partition, sizes, action_size):
  """observation_size / action_size per task and partition, and observe() returns those shapes."""
  env = env_lib.make_env(task, partition)
  assert env.observation_size == sizes
  assert env.action_size == action_size
  obs = _observe(env, *_random_inputs(env, seed=0))
  assert set(obs) == set(sizes)
  for name, shape in sizes.items():
    chex.assert_shape(obs[name], shape)


def test_actor_history_stacks_the_last_steps_newest_first():
  """actor_history 3: agents observe 3 x 32 (3 x 50 for the single PPO agent); at reset the frame
  three times; after a step the new frame, then the two newest of the previous observation; the
  critic keeps its one step. Export refuses such a policy in one line."""
  from mash.deploy import export
  env = env_lib.make_env("bipedal", "mash", actor_history=3)
  assert env.observation_size == {"legs": (2, 96), "critic": (106,)}
  assert env.frame_dims == {"legs": 32}
  assert env_lib.make_env("bipedal", "ppo", actor_history=3).observation_size["body"] == (1, 150)
  frames = [{
      "legs": np.full((2, 32), float(t)) + np.arange(2)[:, None] * 10, "critic": np.full((106,),
                                                                                         float(t))
  } for t in range(4)]
  obs = jax.tree.map(np.asarray, env.with_history(frames[0], None))
  np.testing.assert_array_equal(obs["legs"], np.tile(frames[0]["legs"], (1, 3)))
  for t in (1, 2, 3):
    obs = jax.tree.map(np.asarray, env.with_history(frames[t], obs))
  # Newest first: steps 3, 2, 1 (step 0 has dropped out); each agent keeps its own rows.
  np.testing.assert_array_equal(obs["legs"],
                                np.concatenate([frames[t]["legs"] for t in (3, 2, 1)], axis=-1))
  np.testing.assert_array_equal(obs["critic"], frames[3]["critic"])
  with pytest.raises(export.ExportError, match="actor_history=3"):
    export.layout(env)
  with pytest.raises(ValueError, match=r"actor_history must be in \[1, 100\] control steps"):
    env_config.check_config(env_config.EnvConfig(actor_history=0))


def test_local_critic_sees_each_agents_newest_frame_with_actor_history():
  """critic='local' with actor_history 2: the critic is each agent's newest frame (2 x 32), not its
  stacked history (a padding by the stacked size once made this fail at trace time). Traced with
  eval_shape: no compile."""
  env = env_lib.make_env("bipedal", "mash", critic="local", actor_history=2)
  assert env.observation_size == {"legs": (2, 64), "critic": (64,)}
  shapes = jax.eval_shape(env.reset, jax.random.key(0)).obs
  assert {k: v.shape for k, v in shapes.items()} == {"legs": (2, 64), "critic": (64,)}


def test_leg_observation_layout(dr_env):
  """Leg agent row: q_rel 6 | dq 6 | previous action 6 | phase sin,cos | euler | angvel | command |
  id."""
  sensors, info, contact = _random_inputs(dr_env, seed=1, phase=0.3)
  obs = _observe(dr_env, sensors, info, contact)["legs"]
  q_rel = sensors["q"] - np.array([T1.default_pose[j] for j in T1.joints])
  for k, (offset, one_hot) in enumerate([(0.0, [1, 0]), (0.5, [0, 1])]):  # left, right
    idx = slice(6 * k, 6 * k + 6)  # legs are joints 0..5 (left), 6..11 (right)
    angle = 2 * np.pi * (0.3 + offset)
    expected = np.concatenate([
        q_rel[idx], sensors["dq"][idx], info["last_action"][idx], [np.sin(angle),
                                                                   np.cos(angle)], sensors["euler"],
        sensors["ang_vel"], info["command"], one_hot
    ])
    np.testing.assert_allclose(obs[k], expected, rtol=1e-5, atol=1e-5)


def test_arm_and_ppo_observation_layout(armswing_env):
  """Arm rows (4+4+4+2+10+2) and the PPO body row (all joints, acting limbs' phases, no id)."""
  sensors, info, contact = _random_inputs(armswing_env, seed=2, phase=0.1)
  q_rel = sensors["q"] - np.array([T1.default_pose[j] for j in T1.joints])
  shared = np.concatenate([sensors["euler"], sensors["ang_vel"], info["command"]])
  arms = _observe(armswing_env, sensors, info, contact)["arms"]
  for k, (offset, one_hot) in enumerate([(0.5, [1, 0]), (0.0, [0, 1])]):  # arm opposite its leg
    idx = slice(12 + 4 * k, 16 + 4 * k)
    angle = 2 * np.pi * (0.1 + offset)
    expected = np.concatenate([
        q_rel[idx], sensors["dq"][idx], info["last_action"][idx], [np.sin(angle),
                                                                   np.cos(angle)], shared, one_hot
    ])
    np.testing.assert_allclose(arms[k], expected, rtol=1e-5, atol=1e-5)

  ppo = env_lib.make_env("armswing", "ppo")
  body = _observe(ppo, sensors, info, contact)["body"][0]
  angles = 2 * np.pi * (0.1 + np.array([0.0, 0.5, 0.5, 0.0]))  # left/right leg, left/right arm
  expected = np.concatenate([
      q_rel, sensors["dq"], info["last_action"],
      np.stack([np.sin(angles), np.cos(angles)], -1).reshape(-1), shared
  ])
  np.testing.assert_allclose(body, expected, rtol=1e-5, atol=1e-5)


def test_critic_observation_layout(dr_env):
  """Critic: q_rel 20 | dq 20 | prev action 20 | q_rel - q_ref 20 | phase 2 | command 4 | v 3 |
  euler 3 | w 3 | push 5 | friction | mass offset | stance 2 | contact 2 (= 106)."""
  sensors, info, contact = _random_inputs(dr_env, seed=3, phase=0.3)
  info["dr"] = info["dr"].replace(friction=jnp.asarray(0.7), mass_scale=jnp.full(
      (dr_env.mj_model.nbody,), 1.1))
  c = _observe(dr_env, sensors, info, contact)["critic"]
  q_rel = sensors["q"] - np.array([T1.default_pose[j] for j in T1.joints])
  q_ref, stance = map(np.asarray, dr_env.gait(jnp.asarray(0.3), jnp.asarray(0.0)))
  last_full = np.zeros(20)
  last_full[:12] = info["last_action"]
  expected = np.concatenate([
      q_rel,
      sensors["dq"],
      last_full,
      q_rel - q_ref,
      [np.sin(2 * np.pi * 0.3), np.cos(2 * np.pi * 0.3)],
      info["command"],
      sensors["lin_vel"],
      sensors["euler"],
      sensors["ang_vel"],
      info["push"],
      [0.7],
      [0.1 * dr_env.mj_model.body_mass.sum()],  # mass offset from nominal: 10 % of 31.6 kg
      stance,
      contact
  ])
  np.testing.assert_allclose(c, expected, rtol=1e-4, atol=1e-4)
  # Phase 0.3: left leg sin(0.6 pi) > 0 is in swing, right leg sin(1.6 pi) < 0 in stance.
  np.testing.assert_array_equal(stance, [0.0, 1.0])


KICKS = randomize.DomainRandConfig(kick_velocity=(0.5, 0.5), kick_interval_s=(0.1, 0.1),
                                   kick_yaw_rate=(0.2, 0.2))


def test_critic_sees_the_kick_and_the_actors_do_not(dr_env):
  """With kicks on, the critic gains the last kick (3) after the push; the actors' observations
  are those of the env without kicks."""
  kicked = env_lib.make_env("bipedal", "mash", episode_length=EPISODE_LENGTH, actor_history=2,
                            randomization=KICKS)
  sensors, info, contact = _random_inputs(dr_env, seed=3, phase=0.3)
  plain = _observe(dr_env, sensors, info, contact)
  obs = _observe(kicked, sensors, dict(info, kick=np.array([0.3, -0.4, 0.2])), contact)
  lay = kicked.layout.critic
  assert lay.size == dr_env.layout.critic.size + 3 and lay.offset("kick") == lay.offset("push") + 5
  np.testing.assert_allclose(obs["critic"][lay.slice("kick")], [0.3, -0.4, 0.2], rtol=1e-6)
  no_kick = np.delete(obs["critic"], np.arange(lay.offset("kick"), lay.offset("kick") + 3))
  np.testing.assert_allclose(no_kick, plain["critic"], rtol=1e-6)
  for group in plain:
    if group != "critic":
      np.testing.assert_array_equal(obs[group], plain[group])


def test_sample_kick_sizes_directions_and_yaw():
  """4096 kicks of 0.2-1.0 m/s and 0.1-0.3 rad/s: every size in range, the direction uniform in
  the plane (each quadrant about a quarter, mean direction about 0), the yaw sign both ways."""
  cfg = randomize.DomainRandConfig(kick_velocity=(0.2, 1.0), kick_yaw_rate=(0.1, 0.3))
  kicks = np.asarray(
      jax.jit(jax.vmap(lambda k: randomize.sample_kick(k, cfg)))(jax.random.split(
          jax.random.key(0), 4096)))
  assert kicks.shape == (4096, randomize.KICK_SIZE)
  size = np.linalg.norm(kicks[:, :2], axis=1)
  assert size.min() >= 0.2 - 1e-6 and size.max() <= 1.0 + 1e-6
  assert abs(size.mean() - 0.6) < 0.02
  quadrant = np.bincount((kicks[:, 0] > 0) * 2 + (kicks[:, 1] > 0), minlength=4) / 4096
  np.testing.assert_allclose(quadrant, 0.25, atol=0.03)
  np.testing.assert_allclose((kicks[:, :2] / size[:, None]).mean(0), 0.0, atol=0.05)
  yaw = np.abs(kicks[:, 2])
  assert yaw.min() >= 0.1 - 1e-6 and yaw.max() <= 0.3 + 1e-6
  assert 0.45 < (kicks[:, 2] > 0).mean() < 0.55
  assert not randomize.DomainRandConfig().kicks  # off unless a preset turns them on
  assert not dataclasses.replace(cfg, enabled=False).kicks


def test_kick_interval_steps_hand_values():
  key = jax.random.key(0)
  for interval, steps in (((1.0, 1.0), 50), ((0.001, 0.001), 1), ((0.05, 0.05), 2)):
    cfg = randomize.DomainRandConfig(kick_interval_s=interval)
    assert int(randomize.kick_interval_steps(key, cfg, 0.02)) == steps, interval
  cfg = randomize.DomainRandConfig(kick_interval_s=(5.0, 10.0))
  drawn = np.asarray(
      jax.vmap(lambda k: randomize.kick_interval_steps(k, cfg, 0.02))(jax.random.split(key, 512)))
  assert drawn.min() >= 250 and drawn.max() <= 500 and drawn.std() > 50


def test_a_kick_changes_the_torso_velocity_when_its_timer_runs_out(random_rollout):
  """The kick stage on a state: with its timer at 1 the torso's world vx, vy and its yaw rate
  jump by the kick (0.5 m/s, 0.2 rad/s) and the timer restarts at 0.1 s / 20 ms = 5 steps;
  with the timer above 1 nothing moves and the timer counts down. Other velocities never move."""
  kicked = env_lib.make_env("bipedal", "mash", episode_length=EPISODE_LENGTH, actor_history=2,
                            randomization=KICKS)
  state = jax.tree.map(lambda x: jnp.asarray(x[0]), random_rollout[1])
  qvel = np.asarray(state.pipeline_state.qvel)
  for timer, kicks in ((1, True), (3, False)):
    info = dict(state.info, kick=jnp.zeros(3), kick_timer=jnp.asarray(timer, jnp.int32))
    after, kept = kicked._kick(state.replace(info=info), jax.random.key(timer))
    dv = np.asarray(after.pipeline_state.qvel) - qvel
    if kicks:
      np.testing.assert_allclose(np.linalg.norm(dv[:2]), 0.5, rtol=1e-5)
      np.testing.assert_allclose(abs(dv[5]), 0.2, rtol=1e-5)
      np.testing.assert_allclose(dv[[0, 1, 5]], np.asarray(kept["kick"]), rtol=1e-5)
      assert int(kept["kick_timer"]) == 5
    else:
      np.testing.assert_array_equal(dv, 0.0)
      assert int(kept["kick_timer"]) == 2 and np.all(np.asarray(kept["kick"]) == 0)
    np.testing.assert_array_equal(np.delete(dv, [0, 1, 5]), 0.0)
  # Under the kick curriculum a slot 250 of 1000 steps in kicks at a quarter of the size.
  ramped = env_lib.make_env("bipedal", "mash", episode_length=EPISODE_LENGTH, actor_history=2,
                            randomization=dataclasses.replace(KICKS, kick_ramp_steps=1000))
  info = dict(state.info, kick=jnp.zeros(3), kick_timer=jnp.asarray(1, jnp.int32),
              env_steps=jnp.asarray(250, jnp.int32))
  after, kept = ramped._kick(state.replace(info=info), jax.random.key(1))
  dv = np.asarray(after.pipeline_state.qvel) - qvel
  np.testing.assert_allclose(np.linalg.norm(dv[:2]), 0.125, rtol=1e-5)
  np.testing.assert_allclose(abs(dv[5]), 0.05, rtol=1e-5)


def test_kick_relief_counts_the_steps_since_the_kick(random_rollout):
  """With reward_params.kick_relief_s on, a fresh episode's kick state says "long ago" (the cap)
  and the kick stage keeps the steps since the last kick: 0 on the kick's step, +1 after; the
  step itself zeroes the gait terms on the kick's step and keeps them once the window is past.
  A kick the curriculum scales to 0 does not count. Without the relief there is no such count
  (the state of earlier kicked runs)."""
  params = dataclasses.replace(rewards.RewardParams(), kick_relief_s=0.1)
  relief = env_lib.make_env("bipedal", "mash", episode_length=EPISODE_LENGTH, actor_history=2,
                            randomization=KICKS, reward_params=params)
  assert int(relief._fresh_kick(jax.random.key(0))["kick_age"]) == env_lib._KICK_AGE_CAP
  assert "kick_age" not in env_lib.make_env("bipedal", "mash", episode_length=EPISODE_LENGTH,
                                            actor_history=2,
                                            randomization=KICKS)._fresh_kick(jax.random.key(0))
  state = jax.tree.map(lambda x: jnp.asarray(x[0]), random_rollout[0])  # upright: no reset
  step = jax.jit(relief.step)
  action = jnp.zeros((relief.action_size,))
  for timer, age, want_age in ((1, 7, 0), (3, 7, 8), (3, env_lib._KICK_AGE_CAP,
                                                      env_lib._KICK_AGE_CAP)):
    info = dict(state.info, kick=jnp.zeros(3), kick_timer=jnp.asarray(timer, jnp.int32),
                kick_age=jnp.asarray(age, jnp.int32))
    _, kept = relief._kick(state.replace(info=info), jax.random.key(timer))
    assert int(kept["kick_age"]) == want_age, (timer, age)
    after = step(state.replace(info=info), action)
    assert int(after.info["kick_age"]) == want_age
    assert not bool(after.done)
    values = {n: float(after.metrics[f"reward/{n}"]) for n in params.relieved_terms}
    if want_age < 5:
      assert all(v == 0.0 for v in values.values()), values
    else:  # the clearance term is 0 whenever no swing foot is at its height: not a witness
      assert values["joint_pos"] > 0 and values["feet_contact_number"] != 0, values
  # Before the kick curriculum starts its kicks are of size 0: no relief.
  late = env_lib.make_env("bipedal", "mash", episode_length=EPISODE_LENGTH, actor_history=2,
                          randomization=dataclasses.replace(KICKS, kick_ramp_start_steps=100),
                          reward_params=params)
  info = dict(state.info, kick=jnp.zeros(3), kick_timer=jnp.asarray(1, jnp.int32),
              kick_age=jnp.asarray(7, jnp.int32), env_steps=jnp.asarray(50, jnp.int32))
  assert int(late._kick(state.replace(info=info), jax.random.key(1))[1]["kick_age"]) == 8


def test_kick_scale_hand_values():
  ramp = randomize.DomainRandConfig(kick_ramp_steps=200)
  for steps, scale in ((0, 0.0), (50, 0.25), (200, 1.0), (10_000, 1.0)):
    assert float(randomize.kick_scale(ramp, jnp.asarray(steps))) == scale, steps
  assert float(randomize.kick_scale(randomize.DomainRandConfig(), jnp.asarray(0))) == 1.0
  late = randomize.DomainRandConfig(kick_ramp_steps=200, kick_ramp_start_steps=100)
  for steps, scale in ((0, 0.0), (100, 0.0), (150, 0.25), (300, 1.0)):
    assert float(randomize.kick_scale(late, jnp.asarray(steps))) == scale, steps
  sudden = randomize.DomainRandConfig(kick_ramp_start_steps=100)
  for steps, scale in ((99, 0.0), (100, 1.0)):
    assert float(randomize.kick_scale(sudden, jnp.asarray(steps))) == scale, steps


@pytest.mark.parametrize("standing", [0.0, 1.0])
def test_left_right_mirror_symmetry(armswing_env, standing):
  """Left agent's obs of the mirrored state == right agent's obs of the state, mirror signs
  applied (joint mirror_sign, roll/yaw, wx/wz, vy, yaw rate), one-hot id swapped; both groups."""
  sensors, info, contact = _random_inputs(armswing_env, seed=4, phase=0.37, standing=standing)
  obs = _observe(armswing_env, sensors, info, contact)
  obs_m = _observe(armswing_env, *_mirror_inputs(armswing_env, sensors, info), contact)
  shared_sign = np.array([-1, 1, -1, -1, 1, -1, 1, 1, -1, -1.0])  # euler, angvel, command
  for group in ("legs", "arms"):
    left_limb = T1.limbs_of(group)[0]
    m = np.array([T1.mirror_sign[r] for r in left_limb.roles])
    sign = np.concatenate([m, m, m, [1.0, 1.0], shared_sign])
    for a, b in ((0, 1), (1, 0)):
      np.testing.assert_allclose(obs_m[group][a][:-2], sign * obs[group][b][:-2], atol=1e-5,
                                 err_msg=f"{group}: agent {a} of mirror vs agent {b}")
      np.testing.assert_array_equal(obs_m[group][a][-2:], obs[group][a][-2:])  # id: by slot
    np.testing.assert_array_equal(obs[group][:, -2:], np.eye(2))


def test_gait_reference_and_stance(dr_env):
  """Swing leg bends (hip -, knee +, ankle -) with the swing amplitude x multipliers; standing:
  none."""
  # Phase 0.25: left leg angle pi/2, sin = 1 (full swing); right leg sin(3pi/2) = -1 (stance).
  q_ref, stance = map(np.asarray, dr_env.gait(jnp.asarray(0.25), jnp.asarray(0.0)))
  amplitude = dr_env.config.swing_amplitude
  np.testing.assert_allclose(q_ref[:6], amplitude * np.array([-1, 0, 0, 2, -1, 0]), atol=1e-6)
  np.testing.assert_allclose(q_ref[6:], 0.0, atol=1e-6)  # right leg; arms held in bipedal
  np.testing.assert_array_equal(stance, [0.0, 1.0])
  q_ref, stance = map(np.asarray, dr_env.gait(jnp.asarray(0.25), jnp.asarray(1.0)))
  np.testing.assert_allclose(q_ref, 0.0)
  np.testing.assert_array_equal(stance, [1.0, 1.0])


# ------------------------------------------------------------------------ domain randomization
RANGES = {  # DomainParams field -> DomainRandConfig field
    "friction": "friction", "mass_scale": "mass_scale", "com_offset": "com_offset",
    "gravity": "gravity", "joint_damping": "joint_damping", "joint_friction": "joint_friction",
    "armature": "armature", "kp_scale": "kp_scale", "kd_scale": "kd_scale"
}


def test_reference_swing_reaches_the_clearance_height(dr_env):
  """At full swing the reference pose lifts the swing sole into the feet-clearance window, so
  following the temporal director earns the clearance term (MuJoCo C kinematics, torso fixed)."""
  m = dr_env.mj_model
  data = mujoco.MjData(m)
  data.qpos[:] = m.key("home").qpos
  q_ref, _ = dr_env.gait(jnp.asarray(0.25), jnp.asarray(0.0))  # left leg at sin = 1
  data.qpos[dr_env.joint_addresses().qpos] += np.asarray(q_ref)
  mujoco.mj_kinematics(m, data)
  sole_z = data.geom_xpos[dr_env._soles][..., 2]  # [2 feet, n_sole]
  lift = sole_z[0].min() - sole_z[1].min()
  p = dr_env.config.reward_params
  assert abs(lift - p.feet_height_target) < p.feet_height_tolerance, (lift, p.feet_height_target)


def test_stride_reference_carries_the_feet_at_the_commanded_velocity():
  """stride_reference: applying the reference at touchdown and at lift-off to the default pose
  (forward kinematics), each foot goes from ahead to behind the torso by the distance the torso
  covers in a half cycle, v * 0.64 / 2 (vx 0.4: 0.128 m; vy 0.2: 0.064 m), with the sole level
  within 0.02 rad; a yaw rate turns the foot by w * 0.32. Off, or standing, nothing strides."""
  env = env_lib.make_env("bipedal", "mash", stride_reference=True)
  m = env.mj_model
  data = mujoco.MjData(m)
  home = m.key("home").qpos.copy()
  qadr = [m.jnt_qposadr[m.joint(j).id] for j in T1.joints]

  def foot(phase, command, body):
    q_ref, _ = env.gait(jnp.asarray(phase), jnp.asarray(command[0]), jnp.asarray(command))
    data.qpos[:] = home
    data.qpos[qadr] += np.asarray(q_ref)
    mujoco.mj_kinematics(m, data)
    mat = data.xmat[m.body(body).id].reshape(3, 3)
    pitch, roll = -np.arcsin(mat[2, 0]), np.arctan2(mat[2, 1], mat[2, 2])
    return data.xpos[m.body(body).id].copy(), np.arctan2(mat[1, 0], mat[0, 0]), pitch, roll

  # Left leg: touchdown at phase 0.5 (angle pi), lift-off at phase 0 (its swing is sin > 0).
  # The swing bend is 0 at both (sin = 0), so only the stride moves the foot.
  for command, axis, distance in (([0, 0.4, 0, 0], 0, 0.128), ([0, 0, 0.2, 0], 1, 0.064)):
    ahead, _, p1, r1 = foot(0.5, command, T1.feet[0])
    behind, _, p0, r0 = foot(0.0, command, T1.feet[0])
    assert ahead[axis] - behind[axis] == pytest.approx(distance, rel=0.05)
    assert max(abs(p1 - p0), abs(r1 - r0)) < 0.02
  _, yaw1, _, _ = foot(0.5, [0, 0, 0, 0.5], T1.feet[0])
  _, yaw0, _, _ = foot(0.0, [0, 0, 0, 0.5], T1.feet[0])
  assert yaw1 - yaw0 == pytest.approx(0.5 * 0.32, rel=0.05)
  # Standing, or the reference of the paper (off): no stride.
  still = np.asarray(env.gait(jnp.asarray(0.5), jnp.asarray(1.0), jnp.array([1.0, 0, 0, 0]))[0])
  np.testing.assert_array_equal(still, 0.0)
  plain = env_lib.make_env("bipedal", "mash")
  np.testing.assert_allclose(
      plain.gait(jnp.asarray(0.3), jnp.asarray(0.0), jnp.array([0, 0.4, 0.1, 0.3]))[0],
      env.gait(jnp.asarray(0.3), jnp.asarray(0.0), jnp.zeros(4))[0], atol=1e-7)


def test_stride_feedback_plans_the_stride_at_the_measured_velocity():
  """stride_feedback k: the stride is planned at command + k (measured - command) in the plane
  (hand values), so the reference is the plain stride reference's at that velocity; at k = 0, or
  with the torso at the command, it is the command's."""
  k = 1.5
  env = env_lib.make_env("bipedal", "mash", stride_reference=True, stride_feedback=k)
  plain = env_lib.make_env("bipedal", "mash", stride_reference=True)
  command, lin_vel = jnp.array([0.0, 0.4, 0.0, 0.3]), jnp.array([0.1, -0.5, 0.02])
  np.testing.assert_allclose(env.stride_velocity(command, lin_vel), [-0.05, -0.75, 0.3], atol=1e-6)
  np.testing.assert_array_equal(plain.stride_velocity(command, lin_vel), command[1:])
  phase = jnp.asarray(0.3)
  planned = jnp.array([0.0, -0.05, -0.75, 0.3])
  np.testing.assert_allclose(
      env.gait(phase, jnp.asarray(0.0), command, lin_vel)[0],
      plain.gait(phase, jnp.asarray(0.0), planned)[0], atol=1e-6)
  np.testing.assert_allclose(
      env.gait(phase, jnp.asarray(0.0), command, command[1:])[0],
      plain.gait(phase, jnp.asarray(0.0), command)[0], atol=1e-6)


def test_randomize_sample_in_ranges_and_varies():
  """vmapped sample over 256 keys: every draw inside its configured range, different across envs."""
  cfg = randomize.DomainRandConfig()
  n, nbody, nj = 256, 25, 20
  params = jax.jit(jax.vmap(lambda k: randomize.sample(k, cfg, nbody, nj)))(jax.random.split(
      jax.random.key(0), n))
  assert set(RANGES) | {"motor_strength"} == {f for f in params.__dataclass_fields__}
  np.testing.assert_array_equal(params.motor_strength, 1.0)  # weak motors: the battery's only
  for field, cfg_field in RANGES.items():
    lo, hi = getattr(cfg, cfg_field)
    v = np.asarray(getattr(params, field))
    assert v.shape[0] == n
    assert v.min() >= lo and v.max() <= hi, field
    assert np.all(v.std(axis=0) > 0.1 * (hi - lo) / np.sqrt(12)), f"{field} does not vary"
    assert len(np.unique(v.reshape(n, -1), axis=0)) > 0.95 * n, f"{field} repeats across envs"
  rows = np.concatenate([np.asarray(x).reshape(n, -1) for x in jax.tree.leaves(params)], axis=1)
  assert len(np.unique(rows, axis=0)) == n  # no two envs get the same robot


def test_friction_curriculum_range_hand_values():
  """friction_range blends linearly from friction_initial to friction over friction_ramp_steps,
  then holds; off (None start or 0 steps) it is the final range; evaluation never ramps."""
  cfg = randomize.DomainRandConfig(friction=(0.1, 1.2), friction_initial=(0.3, 0.5),
                                   friction_ramp_steps=1000)
  for steps, want in ((0, (0.3, 0.5)), (250, (0.25, 0.675)), (1000, (0.1, 1.2)), (5000, (0.1,
                                                                                         1.2))):
    np.testing.assert_allclose(randomize.friction_range(cfg, jnp.int32(steps)), want, rtol=1e-6)
  assert randomize.friction_range(cfg, None) == (0.1, 1.2)
  off = (dataclasses.replace(cfg, friction_ramp_steps=0),
         dataclasses.replace(cfg, friction_initial=None))
  assert all(randomize.friction_range(c, jnp.int32(0)) == (0.1, 1.2) for c in off)
  env_cfg = env_config.EnvConfig(randomization=cfg)
  assert evaluation.eval_env_config(env_cfg,
                                    evaluation.EvalConfig()).randomization.friction_ramp_steps == 0


def test_slippery_share_draws_that_share_of_floors_from_its_range():
  """With slippery_share p, a floor is below 0.3 with probability p + (1 - p) 0.2 / 1.1 (its
  own range U[0.1, 0.3] plus the paper's U[0.1, 1.2]); the other parameters' draws are those
  without it; evaluation never applies it."""
  keys = jax.random.split(jax.random.key(0), 20_000)
  draw = lambda cfg: jax.jit(jax.vmap(lambda k: randomize.sample(k, cfg, 5, 3)))(keys)
  plain = draw(randomize.DomainRandConfig())
  mixed = draw(randomize.DomainRandConfig(slippery_share=0.25))
  f = np.asarray(mixed.friction)
  assert f.min() >= 0.1 and f.max() <= 1.2
  np.testing.assert_allclose((f < 0.3).mean(), 0.25 + 0.75 * 0.2 / 1.1, atol=0.01)
  np.testing.assert_allclose((np.asarray(plain.friction) < 0.3).mean(), 0.2 / 1.1, atol=0.01)
  for field in ("mass_scale", "com_offset", "armature", "kp_scale"):
    np.testing.assert_array_equal(getattr(mixed, field), getattr(plain, field))
  env_cfg = env_config.EnvConfig(randomization=randomize.DomainRandConfig(slippery_share=0.25))
  assert evaluation.eval_env_config(env_cfg,
                                    evaluation.EvalConfig()).randomization.slippery_share == 0.0


def test_friction_curriculum_follows_each_env_slot_through_resets():
  """Fresh episodes (every auto-reset, and a reset told the clock) draw the floor friction from
  the range of the curriculum at that slot's env step count: U[0.1, 0.2] at 0, U[0.1, 0.7]
  half-way, U[0.1, 1.2] at the end (1-step episodes, so every step resets)."""
  cfg = randomize.DomainRandConfig(friction_initial=(0.1, 0.2), friction_ramp_steps=100)
  env = env_lib.make_env("bipedal", "mash", randomization=cfg, episode_length=1)
  b = 32
  reset = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))
  state = reset(jax.random.split(jax.random.key(5), b), 0)
  step = jax.jit(jax.vmap(env.step))
  frictions = [np.asarray(state.info["dr"].friction)]
  resumed = reset(jax.random.split(jax.random.key(6), b), 50)  # a resume's first episodes
  np.testing.assert_array_equal(resumed.info["env_steps"], 50)
  f = np.asarray(resumed.info["dr"].friction)
  assert f.max() <= 0.7 + 1e-6 and f.max() > 0.5, f
  for before in (49, 99):
    state.info["env_steps"] = jnp.full((b,), before, jnp.int32)
    nxt = step(state, jnp.zeros((b, env.action_size)))
    np.testing.assert_array_equal(nxt.done, 1.0)
    np.testing.assert_array_equal(nxt.info["env_steps"], before + 1)
    frictions.append(np.asarray(nxt.info["dr"].friction))
  for f, hi in zip(frictions, (0.2, 0.7, 1.2)):
    assert f.min() >= 0.1 and f.max() <= hi + 1e-6
    assert f.max() > hi - 0.4 * (hi - 0.1), "draws do not fill the curriculum's range"


def test_randomize_disabled_is_nominal():
  """enabled=False: every key gives the nominal robot (friction 1, scales 1, g 9.81, ...)."""
  params = jax.vmap(lambda k: randomize.sample(k, DR_OFF, 25, 20))(jax.random.split(
      jax.random.key(0), 3))
  nominal = randomize.nominal(25, 20)
  for i in range(3):
    chex.assert_trees_all_close(jax.tree.map(lambda x: x[i], params), nominal)
  assert float(nominal.gravity) == pytest.approx(9.81)
  assert float(nominal.friction) == 1.0


def test_randomize_apply_writes_fields(dr_env):
  """apply: body_mass/inertia scaled, gravity set, sole-floor pair_friction set, torso CoM moved,
  joint damping/frictionloss/armature written at the actuated dofs; nothing else touched."""
  params = randomize.sample(jax.random.key(3), dr_env.config.randomization, dr_env.mj_model.nbody,
                            dr_env.n_joints)
  base, model = dr_env.mjx_model, dr_env.model_for(params)
  m = dr_env.mj_model
  np.testing.assert_allclose(model.body_mass, base.body_mass * params.mass_scale, rtol=1e-6)
  np.testing.assert_allclose(model.body_inertia, base.body_inertia * params.mass_scale[:, None],
                             rtol=1e-6)
  np.testing.assert_allclose(model.opt.gravity, [0.0, 0.0, -float(params.gravity)], rtol=1e-6)
  soles = np.array([
      m.pair(f"{s}_sole_{k}_floor").id
      for s in ("left", "right")
      for k in range(len(T1.sole_points[0]))
  ])
  others = np.array([i for i in range(m.npair) if i not in soles])
  np.testing.assert_allclose(model.pair_friction[soles, :2], float(params.friction), rtol=1e-6)
  np.testing.assert_allclose(model.pair_friction[soles, 2:], base.pair_friction[soles, 2:])
  np.testing.assert_allclose(model.pair_friction[others], base.pair_friction[others])
  root = m.body(T1.root_body).id
  np.testing.assert_allclose(model.body_ipos[root], base.body_ipos[root] + params.com_offset,
                             atol=1e-7)
  dofs = np.array([m.jnt_dofadr[m.joint(j).id] for j in T1.joints])
  np.testing.assert_allclose(model.dof_damping[dofs], params.joint_damping, rtol=1e-6)
  np.testing.assert_allclose(model.dof_frictionloss[dofs], params.joint_friction, rtol=1e-6)
  np.testing.assert_allclose(model.dof_armature[dofs], params.armature, rtol=1e-6)
  np.testing.assert_allclose(model.dof_damping[:6], base.dof_damping[:6])  # free joint untouched


# ------------------------------------------------------------------------------ MJX rollouts
def test_reset_state(random_rollout, dr_env):
  """Batched reset: obs shapes, home pose, step 0, one metric per reward term, DR per env."""
  state0, _, _ = random_rollout
  chex.assert_shape(state0.obs["legs"], (4, 2, 64))  # 2 steps of 32
  chex.assert_shape(state0.obs["critic"], (4, 106))
  np.testing.assert_array_equal(state0.obs["legs"][..., 32:], state0.obs["legs"][..., :32])
  np.testing.assert_allclose(
      state0.pipeline_state.qpos,
      np.broadcast_to(dr_env.mj_model.key("home").qpos, (4, dr_env.mj_model.nq)))
  np.testing.assert_array_equal(state0.info["step"], 0)
  assert set(state0.metrics) == {f"reward/{t}" for t in rewards.TERMS} | {"paper_reward"}
  assert len(np.unique(state0.info["dr"].friction)) == 4


def test_torque_noise_is_applied_within_its_range_and_not_rewarded(random_rollout, standing_rollout,
                                                                   dr_env):
  """DR on: the last substep's applied torque is the commanded one plus U[-1, 1] x 2 % of the
  limit (mean |noise| / bound 1/2 over 9,600 draws); the rewards' torque is the commanded one. DR
  off (the nominal robot): applied = commanded exactly."""
  act = np.array([dr_env.mj_model.actuator(j).id for j in T1.joints])
  limit = np.array([T1.torque_limit[j] for j in T1.joints])
  bound = dr_env.config.randomization.torque_noise * limit
  assert dr_env.config.randomization.torque_noise == 0.02
  _, _, trace = random_rollout
  commanded, applied = trace["torque"], trace["ctrl"][..., act]
  free = np.abs(commanded) < limit - bound  # away from the clip
  noise = (applied - commanded)[free] / np.broadcast_to(bound, commanded.shape)[free]
  assert noise.size > 5000 and np.abs(noise).max() <= 1.0 + 1e-4
  assert 0.45 < np.abs(noise).mean() < 0.55
  assert np.all(np.abs(applied) <= limit + 1e-4)
  _, _, still = standing_rollout
  np.testing.assert_array_equal(still["ctrl"][..., act], still["torque"])


def test_standing_default_pose_zero_action(standing_rollout):
  """T1 at the default pose, zero action, DR off: upright for 2 s (no fall, z within 3 cm of
  0.665, |roll| < 0.1, pitch < 0.1 on average and never above 0.15 rad)."""
  _, _, tr = standing_rollout
  assert tr["done"].shape == (STAND_STEPS, 2)
  assert not tr["done"].any() and not tr["fall"].any()
  assert np.all(np.abs(tr["z"] - T1.home_height) < 0.03), tr["z"].min(0)
  roll, pitch = tr["euler"][..., 0], tr["euler"][..., 1]
  assert np.all(np.abs(roll) < 0.1), np.abs(roll).max()
  # Measured: the CoM is 2.4 cm ahead of the ankles and the ankle PD (kp 150) gives a bit, so the
  # T1 leans ~0.055 rad forward and rocks lightly damped on its ankles (peak 0.107 at t = 1.5 s,
  # 0.088 at t = 4.5 s), never falling. Hence the mean / peak bounds rather than |pitch| < 0.1.
  assert np.abs(pitch).mean() < 0.1 and np.abs(pitch).max() < 0.15, np.abs(pitch).max()
  np.testing.assert_array_equal(tr["push"], 0.0)  # DR off: no pushes
  np.testing.assert_array_equal(tr["step"][-1], STAND_STEPS)


def test_random_rollout_is_finite(random_rollout, dr_env):
  """200 steps of uniform random actions with DR on: no NaN anywhere, finite reward and obs."""
  _, last, tr = random_rollout
  for name in ("qpos", "qvel", "reward", "euler"):
    assert np.all(np.isfinite(tr[name])), name
  for name, obs in tr["obs"].items():
    assert np.all(np.isfinite(obs)), name
  chex.assert_shape(tr["obs"]["legs"], (RANDOM_STEPS, 4, 2, 64))
  assert np.all(np.isfinite(np.asarray(last.pipeline_state.qpos)))
  # Applied torques within the motor limits; pushes within the configured ranges.
  tau_max = np.array([T1.torque_limit[j] for j in T1.joints])
  assert np.all(np.abs(tr["torque"]) <= tau_max + 1e-4)
  assert np.all(np.abs(tr["push"][..., :2]) <= 20.0) and np.all(np.abs(tr["push"][..., 2:]) <= 5.0)
  assert np.any(tr["push"] != 0.0)
  # By default a new push every control step (the paper: "at each simulation step"), not held.
  assert np.all(np.any(tr["push"][1:] != tr["push"][:-1], axis=-1))


def test_step_carries_the_previous_observation_into_the_history(random_rollout):
  """In the env step, an agent's older half is the newest half of its previous observation,
  except on a step that reset the episode, where the fresh frame is repeated."""
  state0, _, tr = random_rollout
  legs = np.concatenate([state0.obs["legs"][None], tr["obs"]["legs"]])  # [T + 1, B, 2, 64]
  done = tr["done"] > 0  # [T, B]
  carried = legs[1:, ..., 32:] == legs[:-1, ..., :32]
  assert np.all(carried[~done]) and done.any()
  np.testing.assert_array_equal(legs[1:][done][..., 32:], legs[1:][done][..., :32])
  assert not np.all(legs[1:, ..., 32:] == legs[1:, ..., :32])  # frames do differ


def test_a_finished_episode_keeps_its_terminal_critic_observation(random_rollout):
  """Seam between the env's auto-reset and GAE's time-out bootstrap: on a step that ends an
  episode, ``info['next_critic_obs']`` is the critic's view of the terminal state (its step
  counter at the episode's end), not of the fresh episode the state now holds; on every other
  step it is the state's own critic observation."""
  _, _, tr = random_rollout
  done = tr["done"] > 0
  fresh, terminal = tr["obs"]["critic"], tr["next_critic_obs"]
  assert done.any()
  np.testing.assert_array_equal(terminal[~done], fresh[~done])
  assert not np.any(np.all(terminal[done] == fresh[done], axis=-1))
  # A reset episode starts at the home pose: its joint velocities (critic entries 20-39) are 0;
  # the terminal state's are not.
  np.testing.assert_array_equal(fresh[done][:, 20:40], 0.0)
  assert np.all(np.any(terminal[done][:, 20:40] != 0.0, axis=-1))


def test_done_and_auto_reset(random_rollout, dr_env):
  """Episodes end by fall or by time-out at step 50; a done step returns a fresh state (step 0,
  home pose, zero velocity) with truncation = 1 exactly on time-outs."""
  _, _, tr = random_rollout
  done, step, trunc, fall = tr["done"], tr["step"], tr["truncation"], tr["fall"]
  home = dr_env.mj_model.key("home").qpos
  assert trunc.any(), "no episode reached the 50-step time-out"
  np.testing.assert_array_equal(done, np.maximum(trunc, fall))
  assert not np.any((trunc > 0) & (fall > 0))
  np.testing.assert_array_equal(step[done > 0], 0)
  np.testing.assert_allclose(tr["qpos"][done > 0], np.broadcast_to(home,
                                                                   tr["qpos"][done > 0].shape))
  np.testing.assert_array_equal(tr["qvel"][done > 0], 0.0)
  # Step counter: +1 each step, previous counter 49 exactly when truncated.
  prev = np.concatenate([np.zeros((1, 4), step.dtype), step[:-1]], axis=0)
  np.testing.assert_array_equal(step[done == 0], prev[done == 0] + 1)
  # A fall on the last step counts as a fall, not a time-out.
  np.testing.assert_array_equal(trunc > 0, (done > 0) & (fall == 0) & (prev == EPISODE_LENGTH - 1))
  # The curriculum's clock runs on through resets: step t of the rollout is env step t + 1.
  np.testing.assert_array_equal(
      tr["env_steps"], np.broadcast_to(np.arange(1, RANDOM_STEPS + 1)[:, None], done.shape))
  assert step.max() < EPISODE_LENGTH


def test_metrics_sum_to_reward(random_rollout):
  """metrics hold reward/<term> for all 16 terms; reward = max(sum of terms, 0) (only_positive)."""
  _, _, tr = random_rollout
  terms = {k: v for k, v in tr["metrics"].items() if k.startswith("reward/")}
  assert set(terms) == {f"reward/{t}" for t in rewards.TERMS}
  assert set(tr["metrics"]) == set(terms) | {"paper_reward"}
  total = sum(terms.values())
  np.testing.assert_allclose(tr["reward"], np.maximum(total, 0.0), rtol=1e-5, atol=1e-6)
  # No curriculum in this env: the paper-weight reward is the reward.
  np.testing.assert_allclose(tr["metrics"]["paper_reward"], tr["reward"], rtol=1e-6)
  assert np.all(tr["reward"] >= 0.0)
  assert np.any(total > 0.0)  # the unclipped branch is exercised too


def test_assemble_action_puts_each_agent_on_its_own_joints(armswing_env):
  """Seam between the agents' actions and the env's joints, by hand: legs agent k acts 100 k + j
  on its joint j, arms agent k 200 + 10 k + j. Armswing controls the T1's joints in spec order
  (left leg 6, right leg 6, left arm 4, right arm 4), so the flat action reads those numbers in
  that order, and each lands on a joint of its own limb."""
  from mash.sim import agents
  legs = np.array([[100 * k + j for j in range(6)] for k in range(2)], np.float32)
  arms = np.array([[200 + 10 * k + j for j in range(4)] for k in range(2)], np.float32)
  flat = np.asarray(
      agents.assemble_action(armswing_env.agent_groups,
                             {"legs": jnp.asarray(legs), "arms": jnp.asarray(arms)}))
  expected = [
      0, 1, 2, 3, 4, 5, 100, 101, 102, 103, 104, 105, 200, 201, 202, 203, 210, 211, 212, 213
  ]
  np.testing.assert_array_equal(flat, expected)
  names = _controlled_joints(armswing_env)
  assert names[:6] == list(T1.limbs[0].joints) and names[6:12] == list(T1.limbs[1].joints)
  assert all(n.startswith("Left_") for n in names[:6] + names[12:16])
  assert all(n.startswith("Right_") for n in names[6:12] + names[16:])
  # The env's joint targets: each value scaled onto the joint it names (default pose + 0.25 a).
  target = np.asarray(armswing_env.joint_targets(jnp.asarray(flat) / 1000.0))
  default = np.array([T1.default_pose[j] for j in T1.joints])
  np.testing.assert_allclose(target - default, 0.25 * np.asarray(expected) / 1000.0, atol=1e-6)
