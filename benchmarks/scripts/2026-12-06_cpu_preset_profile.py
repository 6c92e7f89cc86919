"""Where the cpu preset's iteration goes, on this machine, in one process (one of the preset's two
local processes: 200 of its 400 envs, 24 steps): the env rollout under the preset's physics and
under cheaper settings (substeps, solver iterations, contact), the updates alone under fewer
epochs or smaller networks, and the whole training iteration. Every figure in one process, so the
ratios hold on a noisy machine.

  python benchmarks/scripts/2026-12-06_cpu_preset_profile.py OUT.json [--only NAME ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time

from mash.bench import benchmark, throughput
from mash.runs import experiment
from mash.sim import env as env_lib

ENVS = 200  # one of the two local processes of the cpu preset
UNROLL = 24


def _env_variants(base):
  phys = base.physics
  rnd = base.randomization
  kicks = dataclasses.replace(rnd, kick_velocity=(0.1, 1.0), kick_interval_s=(3.0, 6.0))
  return {
      "preset (dt 5 ms, 2 it, ls 2)":
          base,
      "kicks on":
          dataclasses.replace(base, randomization=kicks),
      "1 it, ls 2":
          dataclasses.replace(base, physics=dataclasses.replace(phys, iterations=1)),
      "dt 10 ms (2 substeps)":
          dataclasses.replace(base, physics=dataclasses.replace(phys, sim_dt=0.01)),
      "dt 6.67 ms (3 substeps)":
          dataclasses.replace(base, physics=dataclasses.replace(phys, sim_dt=0.02 / 3)),
  }


def _train_variants(base):
  return {
      "preset (4 epochs x 4 minibatches, 256-128-64)": base,
      "2 epochs": dataclasses.replace(base, num_epochs=2),
      "2 minibatches": dataclasses.replace(base, num_minibatches=2),
      "networks 128-64": dataclasses.replace(base, actor_hidden=(128, 64), critic_hidden=(128, 64)),
  }


def main() -> None:
  p = argparse.ArgumentParser()
  p.add_argument("out")
  p.add_argument("--task", default="bipedal")
  p.add_argument("--algo", default="mash")
  args = p.parse_args()
  cfg = experiment.make_config(args.task, args.algo, "cpu")
  train = dataclasses.replace(cfg.train, num_envs=ENVS, iterations_per_call=2)
  result = {
      "machine": f"{platform.processor() or platform.machine()}, {benchmark.device_kind()}",
      "date": benchmark.now(),
      "task": args.task,
      "algo": args.algo,
      "envs": ENVS,
      "unroll": UNROLL,
      "env_rollout_s": {},
      "updates_alone_s": {},
  }

  def save():
    with open(args.out, "w") as f:
      json.dump(result, f, indent=2)

  variants = _env_variants(cfg.env)
  for k, (name, env_cfg) in enumerate(variants.items()):
    print(f"[env {k + 1}/{len(variants)}] {name}", file=sys.stderr, flush=True)
    env = env_lib.MashEnv(env_cfg)
    sps, timing = throughput.env_steps(env, ENVS, UNROLL, repeats=3)
    result["env_rollout_s"][name] = ENVS * UNROLL / sps
    save()
  env = env_lib.MashEnv(cfg.env)
  tvariants = _train_variants(train)
  for k, (name, tcfg) in enumerate(tvariants.items()):
    print(f"[update {k + 1}/{len(tvariants)}] {name}", file=sys.stderr, flush=True)
    result["updates_alone_s"][name] = benchmark.update_seconds(env, tcfg)
    save()
  print("[train] one whole iteration of the preset", file=sys.stderr, flush=True)
  t0 = time.perf_counter()
  sps, compile_s = benchmark.train_throughput(env, train, calls=2)
  result["iteration_s"] = ENVS * UNROLL / sps
  result["train_compile_s"] = compile_s
  result["rest_s"] = (result["iteration_s"] -
                      result["env_rollout_s"]["preset (dt 5 ms, 2 it, ls 2)"] -
                      result["updates_alone_s"]["preset (4 epochs x 4 minibatches, 256-128-64)"])
  result["train_measure_s"] = time.perf_counter() - t0
  save()
  print(json.dumps(result, indent=2))


if __name__ == "__main__":
  main()
