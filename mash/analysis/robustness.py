"""The robustness battery: survival and speed of a policy under shoves, floors, masses, weak motors,
sensor noise and latency, walking at a fixed forward command.

The battery is a list of :class:`Condition` s (:func:`conditions`), each ``episodes`` episodes with
the rest of the randomization as the policy trained with it; episodes and their seed are fixed,
so a figure is reproducible to every digit. This module defines the battery and runs it in MJX
(:func:`run`, one compiled program for every condition); :mod:`mash.deploy.native_battery` runs
the same conditions in MuJoCo C.

- **kick**: the torso's horizontal velocity jumps by the given size (m/s, world frame) once, at
  ``kick_at_s``, in one of ``kick_directions`` directions evenly spread in the plane (the
  episodes split evenly over them);
- **friction**: the floor-sole friction drawn from a band instead of the trained range;
- **torso mass**: the root body's mass times ``1 + value``;
- **motor strength**: every motor's torque (its limit included) times the value, on every joint
  or on one leg's;
- **sensor noise**: uniform noise on what the policy reads: the IMU's Euler angles and angular
  velocity, or the joint encoders' angles and velocities;
- **latency**: the policy's action reaches the motors the given time (whole control steps) late.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from mash.analysis import evaluation
from mash.checks import Bound, check_bounds
from mash.sim import env as env_lib
from mash.sim import env_config, robots

GROUPS = ("kick", "friction", "torso mass", "motor strength", "sensor noise", "latency")


@dataclasses.dataclass(frozen=True)
class BatteryConfig:
  """The battery's conditions and episodes.

  Attributes:
    command_vx: forward command of every episode (m/s).
    episode_s: episode duration (s).
    episodes: episodes per condition (rolled out in parallel; a multiple of ``kick_directions``).
    seed: the episodes' seed (the same for every condition).
    kick_at_s: when the kick comes (s after the start).
    kick_sizes: the kicks' sizes (m/s).
    kick_directions: directions of the kicks, evenly spread in the plane.
    friction_bands: floor-friction ranges ``(lo, hi)``.
    torso_mass: relative changes of the torso's mass.
    motor_strength_all: every motor's strength.
    motor_strength_one_leg: the left leg's motors' strength (the others at 1).
    imu_noise: uniform noise bounds of the Euler angles (rad) and angular velocity (rad/s).
    encoder_noise: uniform noise bounds of the joint angles (rad) and velocities (rad/s).
    latency_ms: action delays (ms; rounded to whole control steps).
  """

  command_vx: float = 0.4
  episode_s: float = 8.0
  episodes: int = 64
  seed: int = 2026
  kick_at_s: float = 2.0
  kick_sizes: tuple[float, ...] = (0.25, 0.5, 0.75, 1.0)
  kick_directions: int = 8
  friction_bands: tuple[tuple[float, float], ...] = ((0.1, 0.2), (0.2, 0.3), (0.3, 1.2))
  torso_mass: tuple[float, ...] = (-0.2, 0.2)
  motor_strength_all: float = 0.8
  motor_strength_one_leg: float = 0.6
  imu_noise: tuple[float, float] = (0.05, 0.2)
  encoder_noise: tuple[float, float] = (0.03, 1.5)
  latency_ms: tuple[float, ...] = (0.0, 20.0, 40.0)


BOUNDS = (
    Bound("command_vx", -10.0, 10.0, "m/s"),
    Bound("episode_s", 0.0, 3600.0, "s", open_low=True),
    Bound("episodes", 1, 100_000),
    Bound("kick_at_s", 0.0, 3600.0, "s"),
    Bound("kick_directions", 1, 360),
    Bound("motor_strength_all", 0.0, 2.0, open_low=True),
    Bound("motor_strength_one_leg", 0.0, 2.0, open_low=True),
)


def check_config(cfg: BatteryConfig) -> None:
  """Checks a :class:`BatteryConfig` (one ``ValueError`` line naming the field)."""
  check_bounds(cfg, BOUNDS)
  if cfg.episodes % cfg.kick_directions:
    raise ValueError(f"episodes {cfg.episodes} must be a multiple of kick_directions "
                     f"{cfg.kick_directions} (each direction gets as many episodes)")
  if cfg.kick_at_s >= cfg.episode_s:
    raise ValueError(f"kick_at_s {cfg.kick_at_s} must come before the episode ends "
                     f"({cfg.episode_s} s)")


class Condition(NamedTuple):
  """One condition of the battery: its name, group and value, and what it changes (the rest as
  trained).

  Attributes:
    name: e.g. ``'kick 0.5 m/s'``.
    group: one of :data:`GROUPS`.
    value: the condition's number (m/s, a fraction, ms; for a friction band its low end).
    kick: the kick's size (m/s; 0: none).
    friction: the floor-friction band, or None (the trained range).
    mass: the torso mass's relative change.
    strength: every motor's strength, and the left leg's (1, 1: as trained).
    imu_noise: noise bounds of Euler angles and angular velocity (0, 0: none).
    encoder_noise: noise bounds of joint angles and velocities (0, 0: none).
    latency_s: the action's delay (s).
  """

  name: str
  group: str
  value: float
  kick: float = 0.0
  friction: tuple[float, float] | None = None
  mass: float = 0.0
  strength: tuple[float, float] = (1.0, 1.0)
  imu_noise: tuple[float, float] = (0.0, 0.0)
  encoder_noise: tuple[float, float] = (0.0, 0.0)
  latency_s: float = 0.0


def conditions(cfg: BatteryConfig = BatteryConfig()) -> list[Condition]:
  """The battery's conditions, in report order."""
  out = [Condition(f"kick {s:g} m/s", "kick", s, kick=s) for s in cfg.kick_sizes]
  out += [
      Condition(f"friction {lo:g}-{hi:g}", "friction", lo, friction=(lo, hi))
      for lo, hi in cfg.friction_bands
  ]
  out += [
      Condition(f"torso mass {100 * m:+.0f} %", "torso mass", m, mass=m) for m in cfg.torso_mass
  ]
  a, leg = cfg.motor_strength_all, cfg.motor_strength_one_leg
  out += [
      Condition(f"motor strength {100 * a:.0f} % (all)", "motor strength", a, strength=(a, a)),
      Condition(f"motor strength {100 * leg:.0f} % (left leg)", "motor strength", leg,
                strength=(1.0, leg))
  ]
  out += [
      Condition("IMU noise", "sensor noise", cfg.imu_noise[0], imu_noise=cfg.imu_noise),
      Condition("encoder noise", "sensor noise", cfg.encoder_noise[0],
                encoder_noise=cfg.encoder_noise)
  ]
  out += [
      Condition(f"latency {ms:g} ms", "latency", ms, latency_s=ms / 1000.0) for ms in cfg.latency_ms
  ]
  return out


class Episodes(NamedTuple):
  """Every episode's perturbation, ``[E, ...]`` arrays (conditions stacked).

  Attributes:
    kick: ``[E, 2]`` the kick's velocity change (m/s, world frame).
    friction: ``[E]`` the floor friction, or -1 to keep the episode's trained draw.
    mass: ``[E]`` the torso mass's factor.
    strength: ``[E, J]`` each motor's strength.
    noise: ``[E, 4]`` noise bounds: Euler, angular velocity, joint angle, joint velocity.
    delay: ``[E]`` int, the action's delay in control steps.
  """

  kick: np.ndarray
  friction: np.ndarray
  mass: np.ndarray
  strength: np.ndarray
  noise: np.ndarray
  delay: np.ndarray


def episodes(conds: list[Condition], cfg: BatteryConfig, left_leg: np.ndarray,
             ctrl_dt: float) -> Episodes:
  """The perturbations of ``cfg.episodes`` episodes per condition; ``left_leg`` ``[J]`` bool
  marks the joints the one-leg motor condition weakens. Friction draws come from ``cfg.seed``."""
  n, k = cfg.episodes, cfg.kick_directions
  angle = 2 * np.pi * (np.arange(n) % k) / k
  rng = np.random.default_rng(cfg.seed)
  rows = []
  for c in conds:
    friction = (np.full(n, -1.0) if c.friction is None else rng.uniform(
        c.friction[0], c.friction[1], n))
    strength = np.where(left_leg, c.strength[1], c.strength[0])
    rows.append(
        Episodes(kick=c.kick * np.stack([np.cos(angle), np.sin(angle)], -1), friction=friction,
                 mass=np.full(n, 1.0 + c.mass), strength=np.tile(strength, (n, 1)),
                 noise=np.tile([*c.imu_noise, *c.encoder_noise],
                               (n, 1)), delay=np.full(n, int(round(c.latency_s / ctrl_dt)))))
  return Episodes(*(np.concatenate(parts).astype(np.int32 if name == "delay" else np.float32)
                    for name, parts in zip(Episodes._fields, zip(*rows))))


def _noisy(env: env_lib.MashEnv, obs: dict[str, jax.Array], noise: jax.Array,
           key: jax.Array) -> dict[str, jax.Array]:
  """What the policy reads: ``obs`` with uniform noise of bounds ``noise`` ``[4]`` (Euler, angular
  velocity, joint angle, joint velocity) on those segments of every agent's newest frame."""
  out = dict(obs)
  for g in env.agent_groups:
    segments = env.layout.actor[g.name]
    names = dict(segments.parts)
    x = obs[g.name]
    for i, name in enumerate(("euler", "ang_vel", "q", "dq")):
      if name in names:
        sl = segments.slice(name)
        u = jax.random.uniform(jax.random.fold_in(key, i), (x.shape[0], sl.stop - sl.start),
                               minval=-1.0, maxval=1.0)
        x = x.at[:, sl].add(noise[i] * u)
    out[g.name] = x
  return out


def _perturbed(state: Any, t: jax.Array, p: Episodes, kick_step: int, root: int) -> Any:
  """The episode's state before step ``t`` (``p``: its row of :class:`Episodes`): at the start
  its floor, torso mass and motors as the condition says; at ``kick_step`` the kick."""
  info = dict(state.info)
  dr = info["dr"]
  first = t == 0
  info["dr"] = dr.replace(
      friction=jnp.where(first & (p.friction >= 0), p.friction, dr.friction),
      mass_scale=jnp.where(first, dr.mass_scale.at[root].multiply(p.mass), dr.mass_scale),
      motor_strength=jnp.where(first, p.strength, dr.motor_strength))
  data = state.pipeline_state
  qvel = data.qvel.at[0:2].add(jnp.where(t == kick_step, p.kick, 0.0))
  return state.replace(pipeline_state=data.replace(qvel=qvel), info=info)


MAX_DELAY = 8  # control steps an action can be held back (160 ms at 50 Hz)


def rollout(env: env_lib.MashEnv, policy: Callable[[dict[str, jax.Array]],
                                                   jax.Array], eps: Episodes, steps: int,
            kick_step: int, seed: int, episodes_per_condition: int) -> dict[str, np.ndarray]:
  """All episodes in one jitted program: ``alive [E, T]`` (1 until the fall) and
  ``forward_velocity [E, T]`` (torso frame, m/s)."""
  root = env.mj_model.body(env.spec.root_body).id

  def episode(key: jax.Array, p: Episodes):

    def step(carry, t):
      state, queue = carry
      state = _perturbed(state, t, p, kick_step, root)
      seen = _noisy(env, state.obs, p.noise, jax.random.fold_in(key, t + 1))
      queue = jnp.concatenate([policy(seen)[None], queue[:-1]])  # newest first
      nxt = env.step(state, queue[p.delay])
      return (nxt, queue), (nxt.done, env.sensors(nxt.pipeline_state)["lin_vel"][0])

    queue = jnp.zeros((MAX_DELAY, env.action_size))
    _, (done, vx) = jax.lax.scan(step, (env.reset(key), queue), jnp.arange(steps))
    return done, vx

  # The same episodes (robots, floors, pushes) under every condition: keys repeat per condition.
  keys = jax.random.split(jax.random.PRNGKey(seed), episodes_per_condition)
  keys = jnp.tile(keys, (len(eps.friction) // episodes_per_condition, 1))
  done, vx = jax.device_get(jax.jit(jax.vmap(episode))(keys, eps))
  return {"alive": evaluation.alive_mask(np.asarray(done)), "forward_velocity": np.asarray(vx)}


def battery_env_config(trained: env_config.EnvConfig, cfg: BatteryConfig) -> env_config.EnvConfig:
  """The trained env config for the battery: randomization as trained (pushes included), a
  fixed forward command, no training kicks (the battery's own kick is the condition)."""
  eval_cfg = evaluation.EvalConfig(command_vx=cfg.command_vx, num_episodes=cfg.episodes,
                                   episode_s=cfg.episode_s, seed=cfg.seed)
  return evaluation.eval_env_config(trained, eval_cfg)


def summarize(conds: list[Condition], alive: np.ndarray, forward_velocity: np.ndarray,
              cfg: BatteryConfig) -> list[dict[str, Any]]:
  """Per condition: ``survival`` (the fraction of its episodes that did not fall), the mean
  ``forward_speed`` over the steps alive (m/s), and for kicks ``survival_by_direction``."""
  n, k = cfg.episodes, cfg.kick_directions
  rows = []
  for i, c in enumerate(conds):
    a, v = alive[i * n:(i + 1) * n], forward_velocity[i * n:(i + 1) * n]
    survived = a.min(axis=1) > 0
    row = {
        "name": c.name, "group": c.group, "value": c.value, "episodes": n,
        "survival": float(survived.mean()), "forward_speed": float(
            (v * a).sum() / max(a.sum(), 1.0))
    }
    if c.kick > 0:
      row["survival_by_direction"] = [float(survived[d::k].mean()) for d in range(k)]
    rows.append(row)
  return rows


def left_leg_mask(spec: robots.RobotSpec) -> np.ndarray:
  """``[J]`` the joints of the left leg (the first limb of group ``legs``), in ``spec.joints``
  order (the env's and the exported policy's)."""
  left = spec.limbs_of("legs")[0]
  return np.array([j in left.joints for j in spec.joints])


def run(
    env: env_lib.MashEnv, policy: Callable[[dict[str, jax.Array]],
                                           jax.Array], cfg: BatteryConfig = BatteryConfig()
) -> list[dict[str, Any]]:
  """The whole battery on ``env`` (built from :func:`battery_env_config`) for ``policy``
  (``obs -> flat action``, unbatched): :func:`summarize`'s rows, one per condition."""
  check_config(cfg)
  conds = conditions(cfg)
  eps = episodes(conds, cfg, left_leg_mask(env.spec), env.dt)
  if eps.delay.max() >= MAX_DELAY:
    raise ValueError(f"latency_ms {max(cfg.latency_ms):g} is more than {MAX_DELAY - 1} control "
                     f"steps of {env.dt * 1000:g} ms")
  steps = int(round(cfg.episode_s / env.dt))
  traj = rollout(env, policy, eps, steps, int(round(cfg.kick_at_s / env.dt)), cfg.seed,
                 cfg.episodes)
  return summarize(conds, traj["alive"], traj["forward_velocity"], cfg)
