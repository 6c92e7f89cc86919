"""The public layout (``mash.sim.layout``): sizes against hand counts for the T1's tasks, partitions
and switches; segments that tile each observation; the env reporting the layout's sizes; each named
segment of a real observation holding what its name says (one env build per task and robot); and
no module but ``mash/sim/env.py`` reading a ``MashEnv``'s private fields.
"""

from __future__ import annotations

import ast
import itertools
import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mash.sim import env as env_lib
from mash.sim import env_config, layout, randomize, robots, tasks

T1 = robots.load("booster_t1")
REPO = Path(__file__).resolve().parents[1]
CONFIGS = list(itertools.product(tasks.names(), env_config.PARTITIONS, (True, False),
                                 (True, False)))


def _config(task="bipedal", partition="mash", agent_id=True, temporal_director=True, **kw):
  return env_config.EnvConfig(task=task, partition=partition, agent_id=agent_id,
                              temporal_director=temporal_director, **kw)


def _hand_sizes(task, partition, agent_id):
  """The observation sizes counted by hand: an agent sees q, dq and last action of its n joints,
  sin/cos of its phase, euler 3 + angular velocity 3 + command 4 = 10, and with agent_id a one-hot
  over its group's agents; the PPO body sees all acting joints and each acting limb's phase, no
  id; the critic 4 x 20 joints + phase 2 + command 4 + lin_vel, euler, ang_vel 3 x 3 + push 5 +
  friction 1 + mass 1 + stance 2 + contact 2 = 80 + 26 = 106. The temporal director only zeroes
  the phase."""
  arms = task == "armswing"
  if partition == "ppo":
    # bipedal: 3 x 12 + 2 x 2 + 10 = 50; armswing: 3 x 20 + 2 x 4 + 10 = 78.
    sizes = {"body": (1, 78 if arms else 50)}
  elif partition == "mash":
    # legs 3 x 6 + 2 + 10 (+ 2) = 30 (32); arms 3 x 4 + 2 + 10 (+ 2) = 24 (26).
    sizes = {"legs": (2, 32 if agent_id else 30)}
    if arms:
      sizes["arms"] = (2, 26 if agent_id else 24)
  else:
    # One agent per group: the one-hot has one entry; legs 30 (+ 1), arms 24 (+ 1).
    leg, arm = (31, 25) if agent_id else (30, 24)
    sizes = {"left_leg": (1, leg), "right_leg": (1, leg)}
    if arms:
      sizes.update(left_arm=(1, arm), right_arm=(1, arm))
  sizes["critic"] = (106,)
  return sizes


# ----------------------------------------------------------------------------- sizes by hand
@pytest.mark.parametrize("task,partition,agent_id,temporal_director", CONFIGS)
def test_sizes_match_the_hand_count_and_the_env(task, partition, agent_id, temporal_director):
  cfg = _config(task, partition, agent_id, temporal_director)
  lay = layout.build(T1, cfg)
  expected = _hand_sizes(task, partition, agent_id)
  assert lay.observation_size == expected
  assert lay.n_actions == (20 if task == "armswing" else 12)
  assert lay.n_joints == 20 and lay.n_limbs == 4
  # The env reports the layout's sizes.
  env = env_lib.MashEnv(cfg)
  assert env.observation_size == lay.observation_size
  assert env.action_size == lay.n_actions and env.critic_obs_size == lay.critic.size
  assert env.agent_groups == lay.groups


def test_actor_history_and_local_critic_sizes():
  """H frames per agent (3 x 32 = 96 per leg); the local critic is every agent's own frame padded
  to the largest: bipedal 2 legs x 32 = 64, armswing 4 x 32 = 128, PPO 1 x 50."""
  assert layout.build(T1, _config(actor_history=3)).observation_size == {
      "legs": (2, 96), "critic": (106,)
  }
  assert layout.build(T1, _config(actor_history=3)).frame_dims == {"legs": 32}
  assert layout.build(T1, _config(critic="local")).critic.size == 64
  assert layout.build(T1, _config("armswing", critic="local")).critic.size == 128
  assert layout.build(T1, _config(partition="ppo", critic="local")).critic.size == 50


def test_segment_names_and_sizes_by_hand():
  lay = layout.build(T1, _config("armswing"))
  assert lay.actor["legs"].parts == (("q", 6), ("dq", 6), ("last_action", 6), ("phase", 2),
                                     ("euler", 3), ("ang_vel", 3), ("command", 4), ("agent_id", 2))
  assert lay.actor["arms"].slice("q") == slice(0, 4)
  assert lay.actor["arms"].offset("agent_id") == 24  # 3 x 4 + 2 + 10
  assert lay.critic.parts == (("q_rel", 20), ("dq", 20), ("last_action", 20),
                              ("q_rel_minus_ref", 20), ("phase", 2), ("command", 4), ("lin_vel", 3),
                              ("euler", 3), ("ang_vel", 3), ("push", 5), ("friction", 1),
                              ("mass_offset", 1), ("stance", 2), ("contact", 2))
  assert lay.critic.offset("command") == 82  # 4 x 20 + 2
  assert lay.critic.slice("contact") == slice(104, 106)
  ppo = layout.build(T1, _config("armswing", "ppo", agent_id=True))
  assert "agent_id" not in ppo.actor["body"].names
  assert ppo.actor["body"].slice("phase") == slice(60, 68)  # after 3 x 20; 4 limbs x (sin, cos)


# ------------------------------------------------------------------------------ tiling
def _all_segments(lay):
  return [*lay.actor.values(), lay.critic]


@pytest.mark.parametrize("critic", ["global", "local"])
def test_segments_tile_each_observation_without_gaps(critic):
  for task, partition, agent_id, td in CONFIGS:
    lay = layout.build(T1, _config(task, partition, agent_id, td, critic=critic))
    for segments in _all_segments(lay):
      stop = 0
      for name, (start, end) in segments.offsets().items():
        assert start == stop and end > start, (task, partition, name)
        assert segments.slice(name) == slice(start, end)
        assert segments.offset(name) == start
        stop = end
      assert stop == segments.size
      # Splitting 0..size-1 and joining the pieces gives every index once, in order.
      pieces = segments.split(np.arange(segments.size))
      assert list(pieces) == list(segments.names)
      np.testing.assert_array_equal(np.concatenate(list(pieces.values())), np.arange(segments.size))
    for g in lay.groups:
      assert g.obs_dim == lay.actor[g.name].size


def test_segments_reject_duplicates_and_empty_parts():
  with pytest.raises(ValueError, match="not unique"):
    layout.Segments((layout.Segment("q", 2), layout.Segment("q", 3)))
  with pytest.raises(ValueError, match="size 0"):
    layout.Segments((layout.Segment("q", 0),))
  with pytest.raises(ValueError, match="size 5"):
    layout.Segments((layout.Segment("q", 2),)).split(np.zeros(5))


# ------------------------------------------------------------------------- joint tables
def test_joint_tables_groups_and_phase_offsets():
  lay = layout.build(T1, _config("armswing"))
  assert lay.joints == T1.joints
  np.testing.assert_array_equal(lay.default_pose, [T1.default_pose[j] for j in T1.joints])
  np.testing.assert_array_equal(lay.kp, [T1.kp[j] for j in T1.joints])
  np.testing.assert_array_equal(lay.kd, [T1.kd[j] for j in T1.joints])
  np.testing.assert_array_equal(lay.torque_limit, [T1.torque_limit[j] for j in T1.joints])
  assert lay.limbs == ("left_leg", "right_leg", "left_arm", "right_arm")
  # Legs 0 / 0.5; each arm with the opposite leg.
  np.testing.assert_array_equal(lay.phase_offset, [0.0, 0.5, 0.5, 0.0])
  np.testing.assert_array_equal(lay.limb_joints["right_leg"], range(6, 12))
  np.testing.assert_array_equal(lay.limb_joints["left_arm"], range(12, 16))
  np.testing.assert_array_equal(lay.controlled, range(20))
  legs, arms = lay.groups
  assert (legs.name, legs.members, legs.act_dim) == ("legs", ("left_leg", "right_leg"), 6)
  assert legs.action_index == (tuple(range(6)), tuple(range(6, 12)))
  assert arms.action_index == (tuple(range(12, 16)), tuple(range(16, 20)))
  with pytest.raises(ValueError, match="read-only"):
    lay.default_pose[0] = 1.0

  bipedal_ppo = layout.build(T1, _config("bipedal", "ppo"))
  (body,) = bipedal_ppo.groups
  assert (body.members, body.action_index) == (("body",), (tuple(range(12)),))
  assert bipedal_ppo.group_limbs["body"] == ("left_leg", "right_leg")
  np.testing.assert_array_equal(bipedal_ppo.controlled, range(12))  # the arms are held
  per_limb = layout.build(T1, _config("armswing", "per_limb"))
  assert [g.name for g in per_limb.groups] == ["left_leg", "right_leg", "left_arm", "right_arm"]


def test_layout_needs_only_the_spec_and_the_config_fields():
  """No MjModel: any object with the seven fields will do (the randomization says whether the
  critic sees kicks); bad choices are one-line errors."""
  cfg = types.SimpleNamespace(task="bipedal", partition="mash", agent_id=False,
                              temporal_director=True, actor_history=2, critic="global",
                              randomization=randomize.DomainRandConfig())
  assert layout.build(T1, cfg).observation_size == {"legs": (2, 60), "critic": (106,)}
  with pytest.raises(ValueError, match="partition 'pairs' is unknown"):
    layout.build(T1, types.SimpleNamespace(**{**vars(cfg), "partition": "pairs"}))
  with pytest.raises(ValueError, match=r"actor_history must be in \[1, 100\] control steps"):
    layout.build(T1, types.SimpleNamespace(**{**vars(cfg), "actor_history": 0}))


# ------------------------------------------------- segments of a real observation (compiles MJX)
PHASE_OFFSET = {"left_leg": 0.0, "right_leg": 0.5, "left_arm": 0.5, "right_arm": 0.0}


@pytest.fixture(
    scope="module",
    params=[(t, r) for t, r in itertools.product(tasks.names(), robots.names()) if all(
        robots.load(r).limbs_of(g) for g in tasks.get(t).acting)], ids="-".join)
def reset_env(request):
  """One env per task and robot and its reset state (jitted reset)."""
  task, robot = request.param
  env = env_lib.make_env(task, "mash", robot=robot)
  return env, jax.jit(env.reset)(jax.random.PRNGKey(3))


def _expected_segments(env, qpos, qvel, info, contact):
  """What each segment name promises, read straight from qpos/qvel by joint name (MuJoCo
  addresses) and the spec, independent of the layout's tables: ``({group: [per agent {name:
  values}]}, {name: values} of the critic)``."""
  m, spec = env.mj_model, env.spec
  qpos, qvel = np.asarray(qpos, np.float64), np.asarray(qvel, np.float64)
  angle = {j: qpos[m.jnt_qposadr[m.joint(j).id]] - spec.default_pose[j] for j in spec.joints}
  rate = {j: qvel[m.jnt_dofadr[m.joint(j).id]] for j in spec.joints}
  kinds = ("legs",) if env.config.task == "bipedal" else ("legs", "arms")
  acting = [j for l in spec.limbs if l.group in kinds for j in l.joints]
  last = dict(zip(acting, np.asarray(info["last_action"])))
  command = np.asarray(info["command"])
  w, x, y, z = qpos[3:7]
  torso = Rotation.from_quat([x, y, z, w])
  euler = torso.as_euler("ZYX")[::-1]  # roll, pitch, yaw
  ang_vel = qvel[3:6]
  phase = float(info["phase"])

  actors = {}
  for kind in kinds:
    members = [l for l in spec.limbs if l.group == kind]
    rows = []
    for k, limb in enumerate(members):
      a = 2 * np.pi * (phase + PHASE_OFFSET[limb.name])
      rows.append(
          dict(q=[angle[j] for j in limb.joints], dq=[rate[j] for j in limb.joints],
               last_action=[last[j] for j in limb.joints], phase=[np.sin(a), np.cos(a)],
               euler=euler, ang_vel=ang_vel, command=command, agent_id=np.eye(len(members))[k]))
    actors[kind] = rows

  q_ref, stance = map(np.asarray, env.gait(jnp.asarray(phase), command[0], jnp.asarray(command)))
  dr = info["dr"]
  mass = np.asarray(m.body_mass)
  q_rel = np.array([angle[j] for j in spec.joints])
  critic = dict(q_rel=q_rel, dq=[rate[j] for j in spec.joints], last_action=[
      last.get(j, 0.0) for j in spec.joints
  ], q_rel_minus_ref=q_rel - q_ref, phase=[np.sin(2 * np.pi * phase),
                                           np.cos(2 * np.pi * phase)], command=command,
                lin_vel=torso.inv().apply(qvel[0:3]), euler=euler, ang_vel=ang_vel,
                push=np.asarray(info["push"]), friction=[float(dr.friction)], mass_offset=[
                    float(np.sum(mass * np.asarray(dr.mass_scale)) - np.sum(mass))
                ], stance=stance, contact=np.asarray(contact))
  return actors, critic


def _check_segments(env, obs, qpos, qvel, info, contact):
  lay = env.layout
  actors, critic = _expected_segments(env, qpos, qvel, info, contact)
  assert set(lay.actor) == set(actors)
  for group, rows in actors.items():
    for k, expected in enumerate(rows):
      got = lay.actor[group].split(np.asarray(obs[group][k]))
      assert set(got) <= set(expected), set(got) - set(expected)  # every segment is checked
      for name, values in got.items():
        np.testing.assert_allclose(values, expected[name], rtol=1e-5, atol=1e-5,
                                   err_msg=f"{group}[{k}].{name}")
  got = lay.critic.split(np.asarray(obs["critic"]))
  assert set(got) == set(critic)
  for name, values in got.items():
    np.testing.assert_allclose(values, critic[name], rtol=1e-5, atol=1e-4, err_msg=f"critic.{name}")


def test_each_segment_of_a_reset_observation_holds_its_name(reset_env):
  env, state = reset_env
  data = state.pipeline_state
  _check_segments(env, state.obs, data.qpos, data.qvel, state.info, np.ones(2))
  # The named segments read the state's own entries, e.g. the critic's command segment:
  np.testing.assert_array_equal(
      np.asarray(state.obs["critic"])[env.layout.critic.slice("command")],
      np.asarray(state.info["command"]))


def test_each_segment_of_a_moved_state_holds_its_name(reset_env):
  """The reset state with the joints, torso tilt and velocities moved, a walking command, a last
  action and one foot off the floor, observed through the env's sensors (nothing is zero)."""
  env, state = reset_env
  rng = np.random.default_rng(0)
  data = state.pipeline_state
  qpos, qvel = np.array(data.qpos), rng.normal(0.0, 1.0, data.qvel.shape)
  addr = env.joint_addresses()
  qpos[addr.qpos] += rng.normal(0.0, 0.2, env.n_joints)
  x, y, z, w = Rotation.from_euler("ZYX", [0.3, -0.1, 0.15]).as_quat()
  qpos[3:7] = [w, x, y, z]
  moved = data.replace(qpos=jnp.asarray(qpos, jnp.float32), qvel=jnp.asarray(qvel, jnp.float32))
  info = dict(state.info, command=jnp.array([0.0, 0.5, -0.1, 0.2]), phase=jnp.asarray(0.3),
              last_action=jnp.asarray(rng.uniform(-1, 1, env.action_size), jnp.float32))
  contact = jnp.array([1.0, 0.0])
  obs = jax.jit(lambda d, i, c: env.observe(env.sensors(d), i, c))(moved, info, contact)
  _check_segments(env, obs, moved.qpos, moved.qvel, info, contact)


# --------------------------------------------------------------- no reads of private fields
def private_env_reads(source: str) -> list[str]:
  """``'line: owner._field'`` for every read of a private attribute (one underscore, not a
  dunder) of an object named ``env`` or ``*_env`` (``env._x``, ``parts.env._x``, ``dr_env._x``,
  ``getattr(env, '_x')``) in Python ``source``."""

  def env_like(node):
    name = node.id if isinstance(node, ast.Name) else getattr(node, "attr", None)
    return name if name is not None and (name == "env" or name.endswith("_env")) else None

  def private(attr):
    return attr.startswith("_") and not (attr.startswith("__") and attr.endswith("__"))

  hits = []
  for node in ast.walk(ast.parse(source)):
    if isinstance(node, ast.Attribute) and private(node.attr) and env_like(node.value):
      hits.append(f"{node.lineno}: {env_like(node.value)}.{node.attr}")
    elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and
          node.func.id in ("getattr", "hasattr") and len(node.args) >= 2 and
          env_like(node.args[0]) and isinstance(node.args[1], ast.Constant) and
          isinstance(node.args[1].value, str) and private(node.args[1].value)):
      hits.append(f"{node.lineno}: {env_like(node.args[0])}.{node.args[1].value}")
  return sorted(hits, key=lambda h: int(h.split(":")[0]))


def test_the_scan_finds_private_reads():
  source = ("a = env._q_default\nb = parts.env._ctrl[0]\nc = dr_env._qadr\n"
            "d = getattr(env, '_act')\ne = env.layout.controlled\nf = self._ctrl\n"
            "g = env.__class__\nh = environment._x\n")
  assert private_env_reads(source) == [
      "1: env._q_default", "2: env._ctrl", "3: dr_env._qadr", "4: env._act"
  ]


def test_no_module_but_env_reads_a_mash_env_private_field():
  files = sorted((REPO / "mash").rglob("*.py")) + sorted((REPO / "experiments").glob("*.py"))
  assert len(files) > 20
  found = {
      str(f.relative_to(REPO)): private_env_reads(f.read_text())
      for f in files
      if f != REPO / "mash" / "sim" / "env.py"
  }
  assert {f: hits for f, hits in found.items() if hits} == {}
