"""Deterministic evaluation rollouts of a trained policy and the paper's metrics on them.

``rollout`` runs ``E`` episodes of ``T`` control steps at a fixed forward command (no auto-reset;
a fallen episode is masked from its fall on) and returns the trajectories that SPEC §8 names, so
anyone can recompute the metrics from ``trajectories.npz``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from mash.analysis import metrics as metrics_lib
from mash.checks import MAX_INT32, Bound, check_bounds
from mash.sim import env as env_lib
from mash.sim import env_config, geometry, randomize


@dataclasses.dataclass(frozen=True)
class EvalConfig:
  """Attributes:
    command_vx: fixed forward command (m/s).
    num_episodes: episodes, rolled out in parallel.
    episode_s: episode duration (s).
    randomization: keep domain randomization on (the robustness we report).
    pushes: keep the randomized torso pushes on (with ``randomization``); False separates what the
      pushes cost from what the other randomized parameters cost.
    push_interval_s: how long each push is held (s; 0: a new push every control step); None keeps
      the run's own (``DomainRandConfig.push_interval_s``), e.g. 1.0 to test a per-step-trained
      policy against held pushes, or 0 to evaluate an older held-push run as runs now train.
    friction: floor-friction range ``(lo, hi)`` drawn from instead of the run's own; None keeps
      the run's. E.g. (0.1, 1.2), the paper's, for a run trained on a narrower range.
    kicks: keep the training's velocity kicks of the torso on (``DomainRandConfig.kick_*``). Off
      by default: evaluation reports the paper's randomization, so a figure means the same for a
      run trained with kicks and one without; the robustness battery measures shoves.
    seed: rollout seed.

  The sane range of every number is checked by :func:`check_config`.
  """

  command_vx: float = 0.4
  num_episodes: int = 32
  episode_s: float = 20.0
  randomization: bool = True
  pushes: bool = True
  push_interval_s: float | None = None
  friction: tuple[float, float] | None = None
  kicks: bool = False
  seed: int = 1234


MAX_EPISODES = 100_000
MAX_EPISODE_S = 3600.0
BOUNDS = (
    Bound("command_vx", -env_config.MAX_COMMAND, env_config.MAX_COMMAND, "m/s"),
    Bound("num_episodes", 1, MAX_EPISODES),
    Bound("episode_s", 0.0, MAX_EPISODE_S, "s", open_low=True),
    Bound("push_interval_s", 0.0, randomize.MAX_INTERVAL_S, "s"),
    Bound("friction", 0.0, 10.0, open_low=True, pair=True),
    Bound("seed", 0, MAX_INT32),
)


def check_config(cfg: EvalConfig, labels: Mapping[str, str] | None = None) -> None:
  """Checks an :class:`EvalConfig` without building anything: a forward command within the
  commands' bounds (+-10 m/s), 1 to 100 000 episodes of (0, 3600] s, a push interval in [0, 1e5]
  s, a friction range with 0 < lo <= hi <= 10 and a seed in [0, 2**31 - 1]. NaN and inf never pass.

  Args:
    cfg: the settings.
    labels: how to name a field in the message (a command line passes its flags, e.g.
      ``{'num_episodes': '--episodes'}``); a field not in it is named as it is.

  Raises:
    ValueError: one line naming the field, its value and what was expected.
  """
  check_bounds(cfg, BOUNDS, labels)


def eval_env_config(env_cfg: env_config.EnvConfig, cfg: EvalConfig) -> env_config.EnvConfig:
  """The training env config at a fixed forward command, no auto-reset, long enough episodes,
  the training's kicks off unless ``cfg.kicks``."""
  steps = int(round(cfg.episode_s / env_cfg.ctrl_dt))
  commands = env_config.CommandConfig(vx=(cfg.command_vx, cfg.command_vx), vy=(0.0, 0.0),
                                      yaw_rate=(0.0, 0.0), standing_prob=0.0,
                                      resample_s=10 * cfg.episode_s)
  # Evaluation draws from the friction range (and, with --kicks, the kicks) training ends on, not
  # the curricula's start nor the slippery floors' extra share.
  randomization = dataclasses.replace(env_cfg.randomization, enabled=cfg.randomization,
                                      friction_ramp_steps=0, slippery_share=0.0, kick_ramp_steps=0,
                                      kick_ramp_start_steps=0)
  if not cfg.pushes:
    randomization = dataclasses.replace(randomization, push_force=(0.0, 0.0),
                                        push_torque=(0.0, 0.0))
  if cfg.push_interval_s is not None:
    randomization = dataclasses.replace(randomization, push_interval_s=cfg.push_interval_s)
  if cfg.friction is not None:
    randomization = dataclasses.replace(randomization, friction=tuple(cfg.friction))
  if not cfg.kicks:
    randomization = dataclasses.replace(randomization, kick_velocity=(0.0, 0.0),
                                        kick_yaw_rate=(0.0, 0.0))
  return dataclasses.replace(env_cfg, commands=commands, randomization=randomization,
                             episode_length=steps + 1, auto_reset=False)


def shoulder_pitch_index(env: env_lib.MashEnv) -> np.ndarray:
  """[2] positions of the left and right arm-swing joints (role ``spec.arm_swing_role``, the
  shoulder pitch) in ``env.spec.joints``."""
  names = env.spec.role_joints(env.spec.arm_swing_role, "arms")
  return np.array([env.spec.joints.index(n) for n in names])


Perturbation = Callable[[Any, jax.Array, jax.Array], Any]


def rollout(env: env_lib.MashEnv, policy: Callable[[dict[str, jax.Array]], jax.Array],
            cfg: EvalConfig, perturb: Perturbation | None = None, values: np.ndarray | None = None,
            commands: np.ndarray | None = None) -> dict[str, np.ndarray]:
  """Runs ``cfg.num_episodes`` deterministic episodes.

  Args:
    env: an env built with :func:`eval_env_config`.
    policy: ``obs {group: [n_agents, obs_dim], ...} -> flat action [A]`` (unbatched).
    cfg: the evaluation settings.
    perturb: optional ``(state, step, value) -> state`` applied before every step (robustness
      sweeps: :func:`friction_and_push`).
    values: ``[num_episodes, ...]`` the per-episode value handed to ``perturb``.
    commands: optional ``[num_episodes, 4]`` command of each episode (standing flag, vx, vy,
      yaw rate; :func:`tracking`) instead of the env config's.

  Returns:
    ``actions [E,T,A]``, ``base_height [E,T]`` (torso above the soles, m), ``euler [E,T,3]``,
    ``hip_pitch [E,T,2]`` and ``hip_pitch_ref [E,T,2]`` (left, right; rad, absolute),
    ``shoulder_pitch [E,T,2]`` (left, right; rad),
    ``forward_velocity [E,T]`` (torso frame, m/s), ``world_velocity [E,T,3]`` (torso vx, vy in
    the world frame, m/s, and the world-frame yaw rate, rad/s), ``command [E,T,4]`` (the command
    in force), ``alive [E,T]`` (1 until the fall), ``contact [E,T,2]``, ``friction [E]`` (the
    episode's floor-sole friction), ``dt`` (s).
  """
  steps = int(round(cfg.episode_s / env.dt))
  hips = env.spec.role_indices("hip_pitch", "legs")
  shoulders = shoulder_pitch_index(env)
  q_default = jnp.asarray(env.layout.default_pose, jnp.float32)

  def one_step(carry, t):
    state, value = carry
    if perturb is not None:
      state = perturb(state, t, value)
    action = policy(state.obs)
    nxt = env.step(state, action)
    s = env.sensors(nxt.pipeline_state)
    q_ref, _ = env.gait(nxt.info["phase"], nxt.info["command"][0], nxt.info["command"])
    contact, _ = env.contacts(nxt.pipeline_state)
    qvel = nxt.pipeline_state.qvel
    # The free joint's linear velocity is in the world frame, its angular velocity in the torso's.
    conj = s["quat"] * jnp.array([1.0, -1.0, -1.0, -1.0])
    yaw_rate = geometry.quat_rotate_inverse(conj, qvel[3:6])[2]
    out = dict(actions=action, base_height=s["base_height"], euler=s["euler"],
               hip_pitch=s["q"][hips], hip_pitch_ref=(q_default + q_ref)[hips],
               shoulder_pitch=s["q"][shoulders], forward_velocity=s["lin_vel"][0],
               world_velocity=jnp.stack([qvel[0], qvel[1], yaw_rate]), command=nxt.info["command"],
               done=nxt.done, contact=contact, friction=nxt.info["dr"].friction)
    return (nxt, value), out

  def episode(key, value, command):
    state = env.reset(key) if commands is None else env.reset(key, command=command)
    _, traj = jax.lax.scan(one_step, (state, value), jnp.arange(steps))
    return traj

  keys = jax.random.split(jax.random.PRNGKey(cfg.seed), cfg.num_episodes)
  values = jnp.zeros(cfg.num_episodes) if values is None else jnp.asarray(values, jnp.float32)
  if values.shape[:1] != (cfg.num_episodes,):
    raise ValueError(f"values must have a leading axis of {cfg.num_episodes} (one per episode), "
                     f"got shape {values.shape}")
  cmds = jnp.zeros(
      (cfg.num_episodes, 4)) if commands is None else jnp.asarray(commands, jnp.float32)
  if cmds.shape != (cfg.num_episodes, 4):
    raise ValueError(f"commands must have shape ({cfg.num_episodes}, 4), got {cmds.shape}")
  traj = jax.device_get(jax.jit(jax.vmap(episode))(keys, values, cmds))
  traj = {k: np.asarray(v) for k, v in traj.items()}
  done = traj.pop("done")
  traj["friction"] = traj["friction"][:, 0]
  traj["alive"] = alive_mask(done)
  traj["dt"] = np.asarray(env.dt)
  return traj


def alive_mask(done: np.ndarray) -> np.ndarray:
  """``[E, T]`` 1 up to and including the step that ended the episode (its fall), 0 after."""
  return (np.cumsum(done, axis=1) - done == 0).astype(np.float32)


def friction_and_push(start_s: float, duration_s: float, dt: float) -> Perturbation:
  """Perturbation of value ``[2]``: the episode's floor-sole friction is ``value[0]``, and a forward
  push of ``value[1]`` newtons acts on the torso from ``start_s`` for ``duration_s`` (build the
  env with randomization off, so no other push is drawn)."""
  first, last = int(round(start_s / dt)), int(round((start_s + duration_s) / dt))

  def perturb(state, step, value):
    info = dict(state.info)
    info["dr"] = info["dr"].replace(friction=value[0])
    active = (step >= first) & (step < last)
    info["push"] = jnp.zeros(5).at[0].set(jnp.where(active, value[1], 0.0))
    return state.replace(info=info)

  return perturb


def robustness(env_config: env_config.EnvConfig, policy: Callable, frictions: np.ndarray,
               pushes: np.ndarray, episodes_per_value: int = 4,
               cfg: EvalConfig = EvalConfig(episode_s=6.0), nominal_friction: float = 1.0,
               push_start_s: float = 2.0, push_duration_s: float = 0.2) -> dict[str, dict]:
  """Friction and push sweeps of one policy, in one jitted rollout.

  Args:
    env_config: the run's env config (evaluated on the nominal robot, no random pushes).
    policy: as in :func:`rollout`.
    frictions: ``[F]`` floor friction coefficients (no push).
    pushes: ``[P]`` forward push forces (N), held ``push_duration_s`` from ``push_start_s``, at
      ``nominal_friction``.
    episodes_per_value: episodes per value (different gait phases).

  Returns:
    ``{'friction': ..., 'push': ...}``, each with ``values``, ``fall_rate`` and ``forward_speed``
    (m/s over the steps alive), one entry per value.
  """
  frictions = np.asarray(frictions, np.float32).reshape(-1)
  pushes = np.asarray(pushes, np.float32).reshape(-1)
  grid = np.concatenate([
      np.stack([frictions, np.zeros_like(frictions)], -1),
      np.stack([np.full_like(pushes, nominal_friction), pushes], -1)
  ])
  cfg = dataclasses.replace(cfg, num_episodes=len(grid) * episodes_per_value, randomization=False)
  env_cfg = eval_env_config(env_config, cfg)
  env_cfg = dataclasses.replace(
      env_cfg, randomization=dataclasses.replace(env_cfg.randomization, push_interval_s=1e5))
  env = env_lib.MashEnv(env_cfg)
  traj = rollout(env, policy, cfg, friction_and_push(push_start_s, push_duration_s, env.dt),
                 np.repeat(grid, episodes_per_value, axis=0))
  alive = traj["alive"].reshape(len(grid), episodes_per_value, -1)
  speed = traj["forward_velocity"].reshape(alive.shape)
  fall = 1.0 - alive.min(axis=-1).mean(axis=-1)
  fwd = (speed * alive).sum(axis=(1, 2)) / np.maximum(alive.sum(axis=(1, 2)), 1)
  n = len(frictions)
  return {
      "friction": {"values": frictions, "fall_rate": fall[:n], "forward_speed": fwd[:n]},
      "push": {"values": pushes, "fall_rate": fall[n:], "forward_speed": fwd[n:]}
  }


# Bands of the floor friction for ``fall_rate_by_friction``, over the paper's range U[0.1, 1.2].
FRICTION_BANDS = (0.1, 0.2, 0.3, 0.6, 0.9, 1.2)


def falls_by_friction(friction: np.ndarray, survived: np.ndarray,
                      edges: tuple[float, ...] = FRICTION_BANDS) -> list[dict[str, Any]]:
  """Fall rate per band of floor friction: where a policy's falls come from.

  Args:
    friction: ``[E]`` each episode's floor-sole friction.
    survived: ``[E]`` bool, the episode did not fall.
    edges: band edges, increasing; a friction below the first edge counts in the first band, one
      at or above the last in the last band.

  Returns:
    One ``{'friction': [lo, hi], 'episodes': n, 'fall_rate': share or None}`` per band.
  """
  friction, survived = np.asarray(friction).reshape(-1), np.asarray(survived, bool).reshape(-1)
  band = np.clip(np.searchsorted(edges, friction, side="right") - 1, 0, len(edges) - 2)
  out = []
  for b in range(len(edges) - 1):
    n = int((band == b).sum())
    falls = float(1.0 - survived[band == b].mean()) if n else None
    out.append({"friction": [edges[b], edges[b + 1]], "episodes": n, "fall_rate": falls})
  return out


def evaluate(traj: dict[str, np.ndarray], command_vx: float,
             rewards_per_iteration: np.ndarray | None = None,
             arms_act: bool = False) -> dict[str, Any]:
  """The SPEC §8 metrics of a rollout; with ``arms_act`` (the armswing task) also
  ``C_limb_arm_leg``: how far each arm's shoulder pitch is from the phase of the opposite leg's
  hip pitch (:func:`mash.analysis.metrics.arm_leg_coordination`, target 0: in phase).

  Smoothness, torso and coordination metrics use the episodes that did not fall (all episodes if
  every one fell, flagged by ``metrics_on_fallen``). ``fall_rate`` is the share of episodes that
  fell; ``forward_speed`` the mean torso-frame forward velocity over the steps alive;
  ``fall_rate_by_friction`` (when ``traj`` has ``friction``) splits the falls by floor friction.
  """
  alive = traj["alive"]
  survived = alive.min(axis=1) > 0
  pick = survived if survived.any() else np.ones_like(survived)
  sub = {k: traj[k][pick] for k in ("actions", "base_height", "euler", "hip_pitch")}
  out = metrics_lib.all_metrics(sub, rewards_per_iteration)
  out.setdefault("T_conv", None)
  out.update(
      fall_rate=float(1.0 - survived.mean()),
      forward_speed=float((traj["forward_velocity"] * alive).sum() / max(alive.sum(), 1.0)),
      command_vx=float(command_vx),
      episodes=int(len(survived)),
      metrics_on_fallen=bool(not survived.any()),
  )
  if "friction" in traj:
    out["fall_rate_by_friction"] = falls_by_friction(traj["friction"], survived)
  out["all_episodes"] = metrics_up_to_the_fall(traj)
  if arms_act and "shoulder_pitch" in traj:
    out["C_limb_arm_leg"] = metrics_lib.arm_leg_coordination(traj["shoulder_pitch"][pick],
                                                             traj["hip_pitch"][pick])
  return out


def metrics_up_to_the_fall(traj: dict[str, np.ndarray], min_steps: int = 50) -> dict[str, Any]:
  """S_action, S_action_2nd, S_torso and C_limb over every episode, a fallen one up to its fall
  (so that falling early cannot make a policy look smooth), each episode weighted equally.

  Episodes alive fewer than ``min_steps`` steps (1 s at 50 Hz: less than a gait cycle and a half)
  are left out and counted in ``episodes_too_short``; all metrics are None when none is left.
  """
  alive_steps = traj["alive"].sum(axis=1).astype(int)
  keep = np.flatnonzero(alive_steps >= min_steps)
  per = []
  for e in keep:
    n = alive_steps[e]
    per.append(
        metrics_lib.all_metrics({
            k: traj[k][e:e + 1, :n] for k in ("actions", "base_height", "euler", "hip_pitch")
        }))
  keys = ("S_action", "S_action_2nd", "S_torso", "C_limb")
  out = {k: (float(np.mean([m[k] for m in per])) if per else None) for k in keys}
  out.update(episodes=int(len(keep)), episodes_too_short=int(len(alive_steps) - len(keep)))
  return out


# The command-tracking grid (standing flag, vx m/s, vy m/s, yaw rate rad/s): standing, forward
# speeds across the training range at vy = yaw rate = 0 (vx = 0 steps in place), then the lateral
# and turning commands at the ends of their training ranges.
TRACKING_GRID = (
    (1.0, 0.0, 0.0, 0.0),
    (0.0, -0.3, 0.0, 0.0),
    (0.0, 0.0, 0.0, 0.0),
    (0.0, 0.2, 0.0, 0.0),
    (0.0, 0.4, 0.0, 0.0),
    (0.0, 0.6, 0.0, 0.0),
    (0.0, 0.8, 0.0, 0.0),
    (0.0, 0.0, 0.2, 0.0),
    (0.0, 0.0, -0.2, 0.0),
    (0.0, 0.0, 0.0, 0.5),
    (0.0, 0.0, 0.0, -0.5),
)
TRACKING_AXES = ("vx", "vy", "yaw_rate")


def heading_velocity(world_velocity: np.ndarray, yaw: np.ndarray) -> np.ndarray:
  """Torso velocity in the heading frame (the world frame turned by the torso's yaw alone).

  Args:
    world_velocity: ``[..., 3]`` world-frame vx, vy (m/s) and yaw rate (rad/s).
    yaw: ``[...]`` torso yaw (rad).

  Returns:
    ``[..., 3]``: forward and leftward speed along the heading (m/s), yaw rate (rad/s).
  """
  c, s = np.cos(yaw), np.sin(yaw)
  vx, vy = world_velocity[..., 0], world_velocity[..., 1]
  return np.stack([c * vx + s * vy, -s * vx + c * vy, world_velocity[..., 2]], axis=-1)


def tracking(traj: dict[str, np.ndarray], commands: np.ndarray) -> dict[str, Any]:
  """How a rollout over a grid of commands followed them.

  Each episode's velocity is its heading-frame velocity averaged over the steps it was alive; a
  command's ``vx``, ``vy`` and ``yaw_rate`` average that over the steps alive of its episodes, and
  its ``abs_error`` is the mean over its episodes of |episode velocity - command|, so an
  oscillating gait is not an error but one that walks at the wrong speed is, on every floor.

  Args:
    traj: a :func:`rollout` with ``world_velocity [E,T,3]``, ``euler [E,T,3]``, ``alive [E,T]``.
    commands: ``[E, 4]`` each episode's command; episodes with equal commands form one grid entry
      (in order of first appearance).

  Returns:
    ``grid``: one entry per distinct command: ``command`` [standing, vx, vy, yaw_rate],
    ``episodes``, ``fall_rate``, ``vx``, ``vy``, ``yaw_rate``, ``abs_error`` {axis: ...} and
    ``episode_std`` {axis: standard deviation of the episodes' velocities};
    ``mean_abs_error`` {axis: mean over the grid of ``abs_error``}; ``fall_rate`` over all
    episodes; ``standing_drift`` (m/s): over the standing command's episodes, the mean norm of
    the planar velocity (net displacement over time alive), ``None`` without a standing command;
    ``reach`` {axis: :func:`command_reach`}.
  """
  commands = np.asarray(commands, np.float64).reshape(-1, 4)
  alive = np.asarray(traj["alive"], np.float64)
  if commands.shape[0] != alive.shape[0]:
    raise ValueError(f"commands has {commands.shape[0]} rows for {alive.shape[0]} episodes")
  vel = heading_velocity(np.asarray(traj["world_velocity"], np.float64), traj["euler"][..., 2])
  steps_alive = np.maximum(alive.sum(axis=1), 1.0)  # [E]
  episode_vel = (vel * alive[..., None]).sum(axis=1) / steps_alive[:, None]  # [E, 3]
  survived = alive.min(axis=1) > 0

  grid, drift = [], None
  _, first = np.unique(commands, axis=0, return_index=True)
  for command in commands[np.sort(first)]:
    pick = np.all(commands == command, axis=1)
    w = steps_alive[pick] / steps_alive[pick].sum()
    achieved = (episode_vel[pick] * w[:, None]).sum(axis=0)
    errors = np.abs(episode_vel[pick] - command[1:]).mean(axis=0)
    entry = {
        "command": [round(float(c), 6) for c in command], "episodes": int(pick.sum()),
        "fall_rate": float(1.0 - survived[pick].mean())
    }
    entry.update({axis: float(achieved[i]) for i, axis in enumerate(TRACKING_AXES)})
    entry["abs_error"] = {axis: float(errors[i]) for i, axis in enumerate(TRACKING_AXES)}
    spread = episode_vel[pick].std(axis=0)
    entry["episode_std"] = {axis: float(spread[i]) for i, axis in enumerate(TRACKING_AXES)}
    grid.append(entry)
    if command[0] > 0:
      drift = float(np.linalg.norm(episode_vel[pick, :2], axis=-1).mean())
  return {
      "grid": grid,
      "mean_abs_error": {
          axis: float(np.mean([g["abs_error"][axis] for g in grid])) for axis in TRACKING_AXES
      },
      "fall_rate": float(1.0 - survived.mean()),
      "standing_drift": drift,
      "reach": command_reach(grid),
  }


def command_reach(grid: list[dict[str, Any]]) -> dict[str, float | None]:
  """Per axis, how much of a command along that axis alone is achieved: the mean over the walking
  grid commands that move along it alone of achieved / commanded (1: on command, 0: not at all;
  ``None`` when the grid has no such command). A mean error over a grid whose commands mostly ask
  for no turning can pass a policy that does not turn; this cannot.

  Args:
    grid: :func:`tracking`'s ``grid`` entries (``command`` [standing, vx, vy, yaw_rate] and the
      achieved ``vx``, ``vy``, ``yaw_rate``).
  """
  reach = {}
  for i, axis in enumerate(TRACKING_AXES):
    ratios = [g[axis] / g["command"][1 + i] for g in grid if _walks_along_only(g["command"], i)]
    reach[axis] = float(np.mean(ratios)) if ratios else None
  return reach


def _walks_along_only(command: list[float], axis: int) -> bool:
  """Whether ``command`` [standing, vx, vy, yaw_rate] walks along axis ``axis`` and no other."""
  velocity = np.asarray(command[1:])
  return not command[0] and velocity[axis] != 0 and np.count_nonzero(velocity) == 1


def tracking_commands(episodes_per_command: int, grid: tuple[tuple[float, ...],
                                                             ...] = TRACKING_GRID) -> np.ndarray:
  """``[len(grid) * episodes_per_command, 4]`` episode commands, each grid entry repeated."""
  return np.repeat(np.asarray(grid, np.float32), episodes_per_command, axis=0)
