"""Throughput probes shared by the benchmark and the physics sweep: bare MJX vs the env step.

Each probe compiles once, runs once to warm up, then times ``repeats`` calls and keeps the best,
so one process measures every figure and ratios between them hold on a noisy machine.
"""

from __future__ import annotations

import time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from mujoco import mjx

from mash.sim import env as env_lib


class Timing(NamedTuple):
  """compile_s: first call (trace + compile + run); run_s: best of the timed calls."""

  compile_s: float
  run_s: float


def time_call(fn: Callable, *args, repeats: int = 2) -> Timing:
  """Times a jitted ``fn(*args)``: first call, then the best of ``repeats`` calls."""
  t0 = time.perf_counter()
  jax.block_until_ready(fn(*args))
  compile_s = time.perf_counter() - t0
  best = float("inf")
  for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    best = min(best, time.perf_counter() - t0)
  return Timing(compile_s, best)


def bare_physics(env: env_lib.MashEnv, batch: int, control_steps: int,
                 repeats: int = 2) -> tuple[float, Timing]:
  """Physics steps/s of plain ``mjx.step`` on the env's model: the same substeps, no env around it.

  Starts from the home pose, holds ``ctrl`` at zero torque after the first substep's PD hold.
  Runs the env's MJX implementation (``env.config.physics.impl``).
  """
  model = env.mjx_model
  data0 = env.initial_data()
  # Batched by vmap, not by broadcasting every field: Warp's contact buffer is one for the batch.
  data = jax.vmap(lambda _: data0)(jnp.arange(batch))
  n = control_steps * env.n_substeps

  @jax.jit
  def run(data):

    def body(d, _):
      return jax.vmap(lambda d: mjx.step(model, d))(d), ()

    d, _ = jax.lax.scan(body, data, None, length=n)
    return d.qpos

  timing = time_call(run, data, repeats=repeats)
  return batch * n / timing.run_s, timing


def env_steps(env: env_lib.MashEnv, batch: int, control_steps: int,
              repeats: int = 2) -> tuple[float, Timing]:
  """Control steps/s of the batched env step (PD, DR model, obs, reward, auto-reset included)."""
  state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), batch))
  actions = 0.1 * jax.random.normal(jax.random.PRNGKey(1), (control_steps, batch, env.action_size))

  @jax.jit
  def run(state, actions):

    def body(s, a):
      return jax.vmap(env.step)(s, a), ()

    s, _ = jax.lax.scan(body, state, actions)
    return s.reward

  timing = time_call(run, state, actions, repeats=repeats)
  return batch * control_steps / timing.run_s, timing
