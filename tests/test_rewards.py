"""Tests for mash.sim.rewards: each of the sixteen terms against a hand computation (arithmetic in
the comments) on one constructed ``RewardInputs``, the scaling convention, signs and the clip."""

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mash.sim import rewards, robots

# The T1's clearance target (a RewardParams default of None means the robot's; the env fills it).
P = rewards.RewardParams(feet_height_target=robots.load("booster_t1").feet_height_target)
DT = 0.02
PAPER_TERMS = ("joint_pos", "tracking_lin_vel", "tracking_ang_vel", "dof_torques", "dof_vel",
               "dof_acc", "feet_air_time", "feet_clearance", "feet_contact_number", "orientation",
               "collision", "feet_slip", "base_height", "action_smoothness_1",
               "action_smoothness_2", "torque_rate")


def _inputs(**overrides) -> rewards.RewardInputs:
  """Two joints, two feet, four penalized pairs; numbers chosen to make the arithmetic short."""
  f = lambda *v: jnp.array(v, jnp.float32)
  base = dict(q_rel=f(0.3, 0.0), q_ref=f(0.0, 0.4), dq=f(1.0, -2.0), last_dq=f(0.5, -1.0), torque=f(
      10.0, -5.0), last_torque=f(8.0, -5.0), torque_limit=f(20.0, 10.0), command=f(
          0.0, 0.5, 0.1, 0.2), base_lin_vel=f(0.3, 0.1, 0.05), base_ang_vel=f(0.1, 0.2, -0.3),
              euler=f(0.02, -0.03, 0.5), gravity_proj=f(0.03, -0.04, -np.sqrt(1 - 0.05**2)),
              base_height=jnp.float32(0.65), base_height_target=jnp.float32(0.66), feet_height=f(
                  0.03, 0.12), feet_vel=f(0.1, 0.2, 0.0, 0.3).reshape(2, 2), contact=f(1.0, 1.0),
              stance=f(0.0, 1.0), first_contact=f(1.0, 0.0), air_time=f(0.3, 0.2), stride_error=f(
                  0.1, 0.5), penalty_force=f(0.05, 2.0,
                                             0.0, 0.2), action=f(0.5, -0.2), last_action=f(
                                                 0.3, 0.1), last_last_action=f(0.0, 0.2), dt=DT)
  base.update(overrides)
  return rewards.RewardInputs(**base)


HAND = {
    # q_rel - q_ref = (0.3, -0.4), norm 0.5 -> exp(-0.5).
    "joint_pos": np.exp(-0.5),
    # (0.5 - 0.3)^2 + (0.1 - 0.1)^2 = 0.04; exp(-0.04 / 0.25) = exp(-0.16).
    "tracking_lin_vel": np.exp(-0.16),
    # (0.2 - (-0.3))^2 = 0.25; exp(-0.25 / 0.25) = exp(-1).
    "tracking_ang_vel": np.exp(-1.0),
    # (10/20)^2 + (-5/10)^2 = 0.25 + 0.25.
    "dof_torques": 0.5,
    # 1^2 + (-2)^2.
    "dof_vel": 5.0,
    # ((1 - 0.5)/0.02)^2 + ((-2 + 1)/0.02)^2 = 25^2 + 50^2 = 625 + 2500.
    "dof_acc": 3125.0,
    # Left foot lands after 0.3 s with stride error 0.1: 0.3 exp(-5 * 0.1); right not landing: 0.
    "feet_air_time": 0.3 * np.exp(-0.5),
    # Left foot swings (stance 0) at |0.03 - 0.04| = 0.01 < 0.02: 1; right foot in stance: 0.
    "feet_clearance": 1.0,
    # Left: contact 1 vs stance 0 -> -0.3; right: 1 vs 1 -> +1.
    "feet_contact_number": 0.7,
    # exp(-10 (0.02 + 0.03)) + exp(-20 * ||(0.03, -0.04)||) = exp(-0.5) + exp(-20 * 0.05).
    "orientation": np.exp(-0.5) + np.exp(-1.0),
    # Forces 0.05, 2.0, 0.0, 0.2 N: two above 0.1 N.
    "collision": 2.0,
    # Both feet in contact: (0.1^2 + 0.2^2) + (0^2 + 0.3^2) = 0.05 + 0.09.
    "feet_slip": 0.14,
    # exp(-100 |0.65 - 0.66|) = exp(-1).
    "base_height": np.exp(-1.0),
    # (0.5 - 0.3)^2 + (-0.2 - 0.1)^2 = 0.04 + 0.09.
    "action_smoothness_1": 0.13,
    # (0.5 - 0.6 + 0.0)^2 + (-0.2 - 0.2 + 0.2)^2 = 0.01 + 0.04.
    "action_smoothness_2": 0.05,
    # ((10 - 8) / (20 * 0.02))^2 + 0 = 5^2.
    "torque_rate": 25.0,
}


def test_sixteen_paper_terms():
  """TERMS and RewardScales list exactly the paper's sixteen terms, with the paper's scales."""
  assert tuple(rewards.TERMS) == PAPER_TERMS
  s = rewards.RewardScales()
  assert (s.joint_pos, s.tracking_lin_vel, s.tracking_ang_vel, s.dof_torques, s.dof_vel, s.dof_acc,
          s.feet_air_time, s.feet_clearance, s.feet_contact_number, s.orientation, s.collision,
          s.feet_slip, s.base_height, s.action_smoothness_1, s.action_smoothness_2,
          s.torque_rate) == (3.5, 1.5, 1.4, -2e-3, -5e-4, -1e-7, 2.0, 2.0, 1.2, 1.0, -1.0, -5e-2,
                             0.2, -0.1, -0.1, -2e-4)


@pytest.mark.parametrize("name", PAPER_TERMS)
def test_term_hand_value(name):
  """Each unscaled term equals the hand computation in HAND."""
  value = rewards.TERMS[name](_inputs(), P)
  chex.assert_shape(value, ())
  assert float(value) == pytest.approx(HAND[name], rel=1e-5)


def test_reward_terms_scale_and_dt():
  """reward_terms = term x scale x dt, for all sixteen terms at the paper's scales."""
  scales = rewards.RewardScales()
  terms = rewards.reward_terms(_inputs(), scales, P)
  assert set(terms) == set(PAPER_TERMS)
  for name, value in terms.items():
    # e.g. joint_pos: exp(-0.5) * 3.5 * 0.02 = 0.04245.
    assert float(value) == pytest.approx(HAND[name] * getattr(scales, name) * DT, rel=1e-5), name


def test_feet_air_time_zero_when_standing():
  """Standing command (flag 1): no air-time reward even on a touchdown."""
  x = _inputs(command=jnp.array([1.0, 0.0, 0.0, 0.0]))
  assert float(rewards.feet_air_time(x, P)) == 0.0


def test_upright_and_on_target_maxima():
  """Perfect state: tracking, orientation (2), base height, joint_pos hit their maxima."""
  x = _inputs(q_ref=jnp.array([0.3, 0.0]), base_lin_vel=jnp.array([0.5, 0.1, 0.0]),
              base_ang_vel=jnp.array([0.0, 0.0, 0.2]), euler=jnp.zeros(3),
              gravity_proj=jnp.array([0.0, 0.0, -1.0]), base_height=jnp.float32(0.66))
  for name, best in (("joint_pos", 1.0), ("tracking_lin_vel", 1.0), ("tracking_ang_vel", 1.0),
                     ("orientation", 2.0), ("base_height", 1.0)):
    assert float(rewards.TERMS[name](x, P)) == pytest.approx(best), name


def _random_batch(n: int, seed: int) -> rewards.RewardInputs:
  """n random inputs (12 controlled / 20 actuated joints, 4 pairs), dt left out (None)."""
  rng = np.random.default_rng(seed)
  nrm = lambda *shape, s=1.0: rng.normal(0.0, s, (n, *shape)).astype(np.float32)
  bit = lambda *shape: rng.integers(0, 2, (n, *shape)).astype(np.float32)
  uni = lambda lo, hi, *shape: rng.uniform(lo, hi, (n, *shape)).astype(np.float32)
  return rewards.RewardInputs(
      q_rel=nrm(12, s=0.3), q_ref=nrm(12, s=0.2), dq=nrm(20, s=3), last_dq=nrm(20, s=3), torque=nrm(
          20, s=20), last_torque=nrm(20, s=20), torque_limit=uni(15, 60, 20),
      command=np.concatenate([bit(1), nrm(3, s=0.5)],
                             -1), base_lin_vel=nrm(3), base_ang_vel=nrm(3), euler=nrm(3, s=0.3),
      gravity_proj=nrm(3), base_height=uni(0.3, 0.8), base_height_target=np.full(
          (n,), 0.66, np.float32), feet_height=uni(0, 0.2, 2),
      feet_vel=nrm(2, 2), contact=bit(2), stance=bit(2), first_contact=bit(2), air_time=uni(
          0, 0.32, 2), stride_error=nrm(2, s=0.2), penalty_force=np.abs(nrm(
              4, s=5)), action=nrm(12), last_action=nrm(12), last_last_action=nrm(12), dt=None)


def test_signs_over_random_inputs():
  """Positive-scale terms are >= 0 and penalties (negative scale) <= 0 after scaling, on 512
  random inputs. Exception by design: feet_contact_number scores -0.3 per mismatched foot
  (humanoid-gym's formula), so its scaled value lies in [-0.6, 2] x 1.2 x dt."""
  scales = rewards.RewardScales()
  terms = jax.jit(jax.vmap(lambda x: rewards.reward_terms(x._replace(dt=DT), scales, P)))(
      _random_batch(512, seed=0))
  for name, value in terms.items():
    value = np.asarray(value)
    assert np.all(np.isfinite(value)), name
    if name == "feet_contact_number":
      assert value.min() >= -0.6 * 1.2 * DT - 1e-7 and value.max() <= 2 * 1.2 * DT + 1e-7
    elif getattr(scales, name) > 0:
      assert value.min() >= 0.0, name
    else:
      assert value.max() <= 0.0, name
      assert value.min() < 0.0, f"{name} never penalizes"


def test_reward_terms_skips_zero_scales(monkeypatch):
  """A zero scale removes the term: no key, and its function is never called (nothing traced)."""

  def boom(x, p):
    raise AssertionError("zero-scale term was evaluated")

  monkeypatch.setitem(rewards.TERMS, "dof_acc", boom)
  monkeypatch.setitem(rewards.TERMS, "collision", boom)
  scales = dataclasses.replace(rewards.RewardScales(), dof_acc=0.0, collision=0.0)
  terms = rewards.reward_terms(_inputs(), scales, P)
  assert set(terms) == set(PAPER_TERMS) - {"dof_acc", "collision"}
  jax.jit(lambda x: rewards.reward_terms(x._replace(dt=DT), scales, P))(_inputs(dt=None))


def test_penalty_ramp_phases_in_the_named_terms():
  """With penalty_ramp_steps = 100 the ramped terms are 0 at step 0, 1/4 at step 25, whole from
  step 100 on; every other term and the default (no curriculum) are untouched."""
  scales = rewards.RewardScales()
  full = rewards.reward_terms(_inputs(), scales, P)
  ramp = dataclasses.replace(P, penalty_ramp_steps=100)
  ramped = set(ramp.ramped_terms)
  assert ramped == {"action_smoothness_1", "action_smoothness_2", "torque_rate"}
  for steps, fraction in ((0, 0.0), (25, 0.25), (100, 1.0), (400, 1.0)):
    terms = rewards.reward_terms(_inputs(env_steps=jnp.int32(steps)), scales, ramp)
    for name in PAPER_TERMS:
      want = full[name] * (fraction if name in ramped else 1.0)
      np.testing.assert_allclose(terms[name], want, rtol=1e-6, err_msg=f"{name} at {steps}")
  assert all(float(full[n]) < 0 for n in ramped)  # they are penalties: the ramp raises the reward


def test_tracking_boost_falls_to_the_paper_scales():
  """tracking_boost 3 over 100 steps: the tracking terms x3 at step 0, x2 at step 50 (1 + 2 * 1/2),
  x1 from step 100 on; every other term untouched; both curricula compose."""
  scales = rewards.RewardScales()
  full = rewards.reward_terms(_inputs(), scales, P)
  boost = dataclasses.replace(P, tracking_boost=3.0, tracking_boost_steps=100,
                              penalty_ramp_steps=100)
  boosted = set(boost.boosted_terms)
  assert boosted == {"tracking_lin_vel", "tracking_ang_vel"}
  for steps, factor, ramp in ((0, 3.0, 0.0), (50, 2.0, 0.5), (100, 1.0, 1.0), (400, 1.0, 1.0)):
    terms = rewards.reward_terms(_inputs(env_steps=jnp.int32(steps)), scales, boost)
    # Without the curricula: the paper's terms at every step.
    paper = rewards.reward_terms(_inputs(env_steps=jnp.int32(steps)), scales, boost,
                                 curricula=False)
    chex.assert_trees_all_close(paper, full, rtol=1e-6)
    for name in PAPER_TERMS:
      want = full[name] * (factor if name in boosted else 1.0) * (ramp if name in boost.ramped_terms
                                                                  else 1.0)
      np.testing.assert_allclose(terms[name], want, rtol=1e-6, err_msg=f"{name} at {steps}")


def test_kick_relief_turns_the_gait_terms_off_for_its_window():
  """kick_relief_s 0.1 at dt 0.02 (5 steps): the three gait terms are 0 for steps 0-4 after a
  kick and whole from step 5 on, every other term untouched at every step; off by default; under
  jit; a name that is no term is refused in one line."""
  terms = rewards.reward_terms(_inputs(), rewards.RewardScales(), P)
  assert rewards.kick_relief(terms, jnp.int32(0), DT, P) is terms  # off: the same dict
  relief = dataclasses.replace(P, kick_relief_s=0.1)
  relieved = set(relief.relieved_terms)
  assert relieved == {"joint_pos", "feet_contact_number", "feet_clearance"}
  assert all(float(terms[n]) != 0.0 for n in relieved)  # so a zero below is the relief's
  relieve = jax.jit(lambda t, age: rewards.kick_relief(t, age, DT, relief))
  for age, on in ((0, False), (4, False), (5, True), (2**28, True)):
    got = relieve(terms, jnp.int32(age))
    for name in PAPER_TERMS:
      want = 0.0 if name in relieved and not on else float(terms[name])
      np.testing.assert_allclose(got[name], want, rtol=1e-6, err_msg=f"{name} at {age}")
  with pytest.raises(ValueError, match="^relieved_terms: 'gait' is not a reward term"):
    rewards.check_params(dataclasses.replace(P, relieved_terms=("gait",)))
  with pytest.raises(ValueError, match="^kick_relief_s"):
    rewards.check_params(dataclasses.replace(P, kick_relief_s=-1.0))


def test_total_reward_only_positive_clip():
  """total_reward sums the terms; only_positive clips a negative sum to 0 and leaves positives."""
  negative = {"a": jnp.float32(-1.0), "b": jnp.float32(0.4)}  # sum -0.6
  positive = {"a": jnp.float32(-0.1), "b": jnp.float32(0.4)}  # sum 0.3
  clip = dataclasses.replace(P, only_positive=True)
  raw = dataclasses.replace(P, only_positive=False)
  assert float(rewards.total_reward(negative, clip)) == 0.0
  assert float(rewards.total_reward(negative, raw)) == pytest.approx(-0.6)
  assert float(rewards.total_reward(positive, clip)) == pytest.approx(0.3)
  assert float(rewards.total_reward(positive, raw)) == pytest.approx(0.3)


def test_total_reward_of_hand_inputs():
  """The step reward of the hand inputs is the dt-scaled sum of HAND (positive, so unclipped)."""
  scales = rewards.RewardScales()
  expected = DT * sum(HAND[n] * getattr(scales, n) for n in PAPER_TERMS)
  # Dominated by joint_pos 3.5 e^-0.5 + lin 1.5 e^-0.16 + ang 1.4 e^-1 + ... > 0.
  assert expected > 0
  total = rewards.total_reward(rewards.reward_terms(_inputs(), scales, P), P)
  assert float(total) == pytest.approx(expected, rel=1e-5)
