"""MuJoCo Warp as MJX's implementation of the physics (``env.physics.impl``).

The first tests run everywhere: without Warp (the default install, CI) the setting is refused in
one line that says how to install it, and an unknown implementation is refused too. The others
need Warp (``pytest.importorskip('warp')``): they run where ``pip install -e ".[warp]"`` was done,
on whatever device JAX has (Warp's CPU device on a machine without a GPU), and are skipped
elsewhere. They check Warp against MJX's JAX implementation on the T1: the env's state after a
few control steps, the penalty-pair contact forces the env reads from each implementation's own
contact layout, and that per-env model fields (domain randomization) reach Warp under ``vmap``.
"""

import importlib.util
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from mujoco import mjx

from mash.runs import experiment
from mash.sim import env as env_lib
from mash.sim import model as model_lib
from mash.sim import randomize

DR_OFF = randomize.DomainRandConfig(enabled=False)
STEPS = 10  # control steps (0.2 s) of the agreement test


def _physics(impl: str, **fields) -> model_lib.PhysicsConfig:
  return model_lib.PhysicsConfig(impl=impl, warp_max_envs=4, **fields)


# ------------------------------------------------------------------------------ without Warp
def test_the_warp_probe_matches_the_installed_packages():
  """``model_lib.warp_installed`` reads MJX's probe: true exactly where warp-lang can be
  imported."""
  assert model_lib.warp_installed() == (importlib.util.find_spec("warp") is not None)


def test_warp_without_warp_is_one_config_error_with_the_install_hint(monkeypatch):
  """``--set env.physics.impl=warp`` where Warp is missing: one ConfigError line naming the
  setting and the fix (Warp made missing here, so this runs where it is installed too)."""
  monkeypatch.setattr(model_lib, "warp_installed", lambda: False)
  with pytest.raises(experiment.ConfigError) as e:
    experiment.make_config("bipedal", overrides=["env.physics.impl=warp"])
  assert str(e.value) == ("env.physics.impl 'warp' needs MuJoCo Warp, which is not installed "
                          'here: pip install -e ".[warp]" (or leave impl at jax)')


@pytest.mark.parametrize("override, words", [
    ("env.physics.impl=bogus", "env.physics.impl 'bogus' is unknown; expected one of jax, warp"),
    ("env.physics.warp_max_envs=0", "env.physics.warp_max_envs must be in [1, 1048576] envs"),
])
def test_a_bad_implementation_setting_is_refused(override, words):
  with pytest.raises(experiment.ConfigError,
                     match=r"^" + words.replace("[", r"\[").replace("]", r"\]")):
    experiment.make_config("bipedal", overrides=[override])


def test_a_batch_larger_than_the_warp_contact_buffer_is_refused(monkeypatch):
  """Warp's contact buffer is sized for warp_max_envs: a bigger batch would drop contacts."""
  monkeypatch.setattr(model_lib, "warp_installed", lambda: True)
  with pytest.raises(
      experiment.ConfigError, match=r"warp_max_envs=256 must be at least the envs "
      r"stepped at once, train.num_envs x seeds = 512"):
    experiment.make_config(
        "bipedal", preset="cpu",
        overrides=["train.num_envs=512", "env.physics.impl=warp", "env.physics.warp_max_envs=256"])
  experiment.make_config(
      "bipedal", preset="cpu",
      overrides=["train.num_envs=512", "env.physics.impl=warp", "env.physics.warp_max_envs=512"])


@pytest.mark.skipif(model_lib.warp_installed(), reason="Warp is installed here")
def test_the_cli_without_warp_prints_one_line_and_nothing_else():
  """No MJX probe lines ('Failed to import warp') on a default install: the command that asks for
  Warp prints exactly one line, the error, and exits 2."""
  out = subprocess.run(
      [sys.executable, "-m", "experiments.bipedal", "--set", "env.physics.impl=warp"],
      capture_output=True, text=True, timeout=120)
  assert out.returncode == 2 and out.stdout == "", out
  assert out.stderr.splitlines() == [
      "error: env.physics.impl 'warp' needs MuJoCo Warp, which is not installed here: "
      'pip install -e ".[warp]" (or leave impl at jax)'
  ], out.stderr


# --------------------------------------------------------------------------------- with Warp
@pytest.fixture(scope="module")
def warp():
  return pytest.importorskip(
      "warp", reason="MuJoCo Warp is not installed here (an optional extra: "
      'pip install -e ".[warp]"); the default install runs the JAX physics')


def _rollout(impl: str, steps: int) -> list:
  """One env (DR off), reset with key 0, ``steps`` control steps of zero action: the states.

  Traced at the highest matmul precision: on a GPU, JAX's default float32 matmul is TF32 (about
  3 decimal digits), which the JAX implementation uses and Warp's kernels do not. At the default
  precision on an H200 the two parted by more than the tolerances below (1.2e-3 in one
  observation, 2.8 % in a contact force; ``benchmarks/results/2026-12-04_h200_warp_vs_jax/``);
  at the highest one they have not been run on a GPU yet. On a CPU it changes nothing."""
  env = env_lib.make_env("bipedal", "mash", randomization=DR_OFF, physics=_physics(impl))
  states = []
  with jax.default_matmul_precision("highest"):
    step = jax.jit(env.step)
    state = env.reset(jax.random.key(0))
    for _ in range(steps):
      state = step(state, jnp.zeros(env.action_size))
      states.append(jax.device_get(state))
  return states


def test_warp_env_steps_as_the_jax_env(warp):
  """The env through Warp and through JAX, nominal robot, holding the default pose for 10 control
  steps (40 physics steps): measured on CPU (Warp's CPU device) the largest gaps are 6.6e-7 in
  qpos, 5.0e-5 in qvel and the observations, 3e-7 in the reward; the tolerances, 2e-5 (qpos),
  1e-3 (qvel, obs) and 1e-4 (reward), leave 20x room or more for other devices and versions.

  Why not random actions: at the solver's one Newton iteration (``PhysicsConfig.iterations``) the
  two implementations' single steps differ where a contact starts or ends (measured: 0.27 and
  0.35 rad/s from the converged step); with 20 iterations they agree to 1e-4 rad/s there too.
  """
  for jax_state, warp_state in zip(_rollout("jax", STEPS), _rollout("warp", STEPS)):
    np.testing.assert_allclose(warp_state.pipeline_state.qpos, jax_state.pipeline_state.qpos,
                               atol=2e-5)
    np.testing.assert_allclose(warp_state.pipeline_state.qvel, jax_state.pipeline_state.qvel,
                               atol=1e-3)
    for name in jax_state.obs:
      np.testing.assert_allclose(warp_state.obs[name], jax_state.obs[name], atol=1e-3)
    np.testing.assert_allclose(warp_state.reward, jax_state.reward, atol=1e-4)
    np.testing.assert_array_equal(warp_state.info["last_contact"], jax_state.info["last_contact"])
  assert float(warp_state.done) == 0.0 and np.all(warp_state.info["last_contact"] == 1.0)


def test_penalty_contacts_agree_between_implementations(warp):
  """Hips rolled 0.2 rad inwards from the home pose cross the legs: the shanks and the feet
  overlap. One physics step in each implementation; the env reads the penalty pairs' normal
  forces from each one's contact layout (measured: 176.719 and 11.664 N with JAX, 176.718 and
  11.664 N with Warp). Tolerance 0.1 % of the force, at the highest matmul precision (see
  :func:`_rollout`)."""
  forces = {}
  for impl in ("jax", "warp"):
    env = env_lib.make_env("bipedal", "mash", physics=_physics(impl))
    m = env.mj_model
    qpos = np.array(m.key("home").qpos)
    for side, sign in (("Left", -1.0), ("Right", 1.0)):
      qpos[m.jnt_qposadr[m.joint(f"{side}_Hip_Roll").id]] = sign * 0.2
    with jax.default_matmul_precision("highest"):
      data = jax.jit(mjx.step)(env.mjx_model, env.initial_data().replace(qpos=jnp.array(qpos)))
      forces[impl] = np.asarray(jax.jit(env.contacts)(data)[1])
  assert forces["jax"][0] > 100.0 and forces["jax"][1] > 5.0  # shanks, feet
  np.testing.assert_allclose(forces["warp"], forces["jax"], rtol=1e-3, atol=1e-2)


def test_per_env_model_fields_reach_warp_under_vmap(warp):
  """Domain randomization writes model fields per env (``MashEnv.model_for``) under ``vmap``;
  Warp takes them. Three envs lifted 5 cm, gravity 9.81, 5 and 0 m/s^2, no torque, 10 physics
  steps of 5 ms: a free fall (no contact yet) in which semi-implicit Euler drops the robot
  g dt^2 (1 + ... + 10) = g * 25e-6 * 55 m = 13.49 mm, 6.88 mm and 0."""
  env = env_lib.make_env("bipedal", "mash", physics=_physics("warp"))
  params = jax.vmap(
      lambda k: randomize.sample(k, env.config.randomization, env.mj_model.nbody, env.n_joints))(
          jax.random.split(jax.random.key(0), 3))
  params = params.replace(gravity=jnp.array([9.81, 5.0, 0.0]))
  data = jax.vmap(lambda _: env.initial_data())(jnp.arange(3))
  z0 = float(data.qpos[0, 2]) + 0.05
  data = data.replace(qpos=data.qpos.at[:, 2].set(z0))

  def fall(p, d):
    model = env.model_for(p)
    return jax.lax.fori_loop(0, 10, lambda _, d: mjx.step(model, d), d).qpos[2]

  z = np.asarray(jax.jit(jax.vmap(fall))(params, data))
  np.testing.assert_allclose(z0 - z, 25e-6 * 55 * np.array([9.81, 5.0, 0.0]), atol=1e-5)


def test_warp_env_resets_finished_episodes_under_vmap(warp):
  """Two envs through Warp with domain randomization on and 2-step episodes: the batched step
  runs, time-outs reset (``Data.where`` keeps Warp's shared contact buffer whole) and the state
  stays finite."""
  env = env_lib.make_env("bipedal", "mash", episode_length=2, physics=_physics("warp"))
  state = jax.vmap(env.reset)(jax.random.split(jax.random.key(1), 2))
  step = jax.jit(jax.vmap(env.step))
  actions = 0.3 * jax.random.normal(jax.random.key(2), (3, 2, env.action_size))
  done = []
  for a in actions:
    state = step(state, a)
    done.append(np.asarray(state.done))
  np.testing.assert_array_equal(np.stack(done), [[0, 0], [1, 1], [0, 0]])
  np.testing.assert_array_equal(state.info["step"], [1, 1])
  assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(state.obs))
