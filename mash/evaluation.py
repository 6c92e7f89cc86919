"""Deterministic evaluation rollouts of a trained policy and the paper's metrics on them.

``rollout`` runs ``E`` episodes of ``T`` control steps at a fixed forward command (no auto-reset;
a fallen episode is masked from its fall on) and returns the trajectories that SPEC §8 names, so
anyone can recompute the metrics from ``trajectories.npz``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from mash import env as env_lib
from mash import metrics as metrics_lib


@dataclasses.dataclass(frozen=True)
class EvalConfig:
  """Attributes:
    command_vx: fixed forward command (m/s).
    num_episodes: episodes, rolled out in parallel.
    episode_s: episode duration (s).
    randomization: keep domain randomization on (the robustness we report).
    seed: rollout seed.
  """

  command_vx: float = 0.4
  num_episodes: int = 32
  episode_s: float = 20.0
  randomization: bool = True
  seed: int = 1234


def eval_env_config(env_config: env_lib.EnvConfig, cfg: EvalConfig) -> env_lib.EnvConfig:
  """The training env config at a fixed forward command, no auto-reset, long enough episodes."""
  steps = int(round(cfg.episode_s / env_config.ctrl_dt))
  commands = env_lib.CommandConfig(vx=(cfg.command_vx, cfg.command_vx), vy=(0.0, 0.0),
                                   yaw_rate=(0.0, 0.0), standing_prob=0.0,
                                   resample_s=10 * cfg.episode_s)
  randomization = dataclasses.replace(env_config.randomization, enabled=cfg.randomization)
  return dataclasses.replace(env_config, commands=commands, randomization=randomization,
                             episode_length=steps + 1, auto_reset=False)


def hip_pitch_index(env: env_lib.MashEnv) -> np.ndarray:
  """[2] positions of the left and right hip-pitch joints in ``env.spec.joints``."""
  names = [next(j for j in limb.joints if j.endswith("Hip_Pitch"))
           for limb in env.spec.limbs if limb.group == "legs"]
  return np.array([env.spec.joints.index(n) for n in names])


def rollout(env: env_lib.MashEnv, policy: Callable[[dict[str, jax.Array]], jax.Array],
            cfg: EvalConfig) -> dict[str, np.ndarray]:
  """Runs ``cfg.num_episodes`` deterministic episodes.

  Args:
    env: an env built with :func:`eval_env_config`.
    policy: ``obs {group: [n_agents, obs_dim], ...} -> flat action [A]`` (unbatched).
    cfg: the evaluation settings.

  Returns:
    ``actions [E,T,A]``, ``base_height [E,T]`` (torso above the soles, m), ``euler [E,T,3]``,
    ``hip_pitch [E,T,2]`` and ``hip_pitch_ref [E,T,2]`` (left, right; rad, absolute),
    ``forward_velocity [E,T]`` (torso frame, m/s), ``alive [E,T]`` (1 until the fall),
    ``contact [E,T,2]``, ``dt`` (s).
  """
  steps = int(round(cfg.episode_s / env.dt))
  hips = hip_pitch_index(env)

  def one_step(state, _):
    action = policy(state.obs)
    nxt = env.step(state, action)
    s = env.sensors(nxt.pipeline_state)
    q_ref, _ = env.gait(nxt.info["phase"], nxt.info["command"][0])
    contact, _ = env.contacts(nxt.pipeline_state)
    out = dict(actions=action, base_height=s["base_height"], euler=s["euler"],
               hip_pitch=s["q"][hips], hip_pitch_ref=(env._q_default + q_ref)[hips],
               forward_velocity=s["lin_vel"][0], done=nxt.done, contact=contact)
    return nxt, out

  def episode(key):
    state = env.reset(key)
    _, traj = jax.lax.scan(one_step, state, None, length=steps)
    return traj

  keys = jax.random.split(jax.random.PRNGKey(cfg.seed), cfg.num_episodes)
  traj = jax.device_get(jax.jit(jax.vmap(episode))(keys))
  traj = {k: np.asarray(v) for k, v in traj.items()}
  done = traj.pop("done")
  traj["alive"] = (np.cumsum(done, axis=1) - done == 0).astype(np.float32)
  traj["dt"] = np.asarray(env.dt)
  return traj


def evaluate(traj: dict[str, np.ndarray], command_vx: float,
             rewards_per_iteration: np.ndarray | None = None) -> dict[str, Any]:
  """The SPEC §8 metrics of a rollout.

  Smoothness, torso and coordination metrics use the episodes that did not fall (all episodes if
  every one fell, flagged by ``metrics_on_fallen``). ``fall_rate`` is the share of episodes that
  fell; ``forward_speed`` the mean torso-frame forward velocity over the steps alive.
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
  return out
