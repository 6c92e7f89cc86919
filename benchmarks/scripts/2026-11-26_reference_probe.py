"""Open-loop probe: play the temporal director's reference as the action, versus zero action.

Run from the repository root: python benchmarks/scripts/2026-11-26_reference_probe.py [SCALE]
SCALE multiplies the reference (1.0 = the env's swing_amplitude, 0.17 rad hip pitch). DR off,
command 0.4 m/s forward, 8 envs x 150 control steps (3 s); an env stops counting when it falls.
"""
import dataclasses
import sys

import jax
import jax.numpy as jnp
import numpy as np

from mash.sim import env as env_lib
from mash.sim import randomize

scale = float(sys.argv[1]) if len(sys.argv) > 1 else 1.0
cfg = env_lib.EnvConfig(
    task="bipedal", auto_reset=False,
    randomization=dataclasses.replace(randomize.DomainRandConfig(), enabled=False),
    commands=dataclasses.replace(env_lib.CommandConfig(), vx=(0.4, 0.4), vy=(0.0, 0.0),
                                 yaw_rate=(0.0, 0.0), standing_prob=0.0, resample_s=1000.0))
env = env_lib.MashEnv(cfg)
ctrl = jnp.asarray(env._ctrl)
T, B = 150, 8


def policy(state, mode):
  q_ref, _ = env.gait(state.info["phase"], state.info["command"][0])
  a = scale * q_ref[ctrl] / cfg.action_scale
  return jnp.where(mode > 0, a, 0.0)


@jax.jit
def run(keys, mode):
  s0 = jax.vmap(env.reset)(keys)

  def body(s, _):
    a = jax.vmap(lambda st: policy(st, mode))(s)
    s2 = jax.vmap(env.step)(s, a)
    alive = 1.0 - s.done
    s2 = s2.replace(done=jnp.maximum(s.done, s2.done))
    return s2, (s2.reward * alive, {k: v * alive for k, v in s2.metrics.items()}, alive,
                s2.pipeline_state.qpos[:, 0], s2.info["last_contact"])

  _, out = jax.lax.scan(body, s0, None, length=T)
  return out


keys = jax.random.split(jax.random.PRNGKey(0), B)
for mode in (0, 1):
  r, m, alive, x, contact = jax.device_get(run(keys, mode))
  steps = alive.sum(0)
  print(f"== {'reference' if mode else 'zero action'} (scale {scale}): "
        f"survived {steps.mean():.0f}/{T} steps, "
        f"x travelled {np.mean(x[-1] - x[0]):+.3f} m, reward/step {r.sum() / alive.sum():.4f}, "
        f"feet in contact {contact[alive > 0].mean():.2f}")
  for k in sorted(m):
    print(f"   {k:32s} {m[k].sum() / alive.sum():+.5f}")
