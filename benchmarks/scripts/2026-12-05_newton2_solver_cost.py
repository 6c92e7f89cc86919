"""Env-step throughput of the T1 bipedal env at each solver setting tried (2026-12-05).

  python benchmarks/scripts/2026-12-05_newton2_solver_cost.py

One process, 512 envs x 24 control steps, best of 2 timed calls per setting: prints one line per
(Newton iterations, line-search iterations) and writes ``solver_cost.json`` into its result folder,
``benchmarks/results/2026-12-05_cpu_preset_newton2/``.
"""

import json
from pathlib import Path

from mash.bench import throughput
from mash.sim import env as env_lib
from mash.sim import robots

RESULTS = Path(__file__).resolve().parents[1] / "results" / "2026-12-05_cpu_preset_newton2"

rows = []
for iterations, ls in [(1, 4), (2, 4), (2, 2), (1, 2), (2, 1)]:
  physics = robots.PhysicsConfig(iterations=iterations, ls_iterations=ls)
  env = env_lib.MashEnv(env_lib.EnvConfig(physics=physics))
  steps_per_s, timing = throughput.env_steps(env, 512, 24, repeats=2)
  rows.append({
      "iterations": iterations, "ls_iterations": ls, "env_steps_per_s": steps_per_s,
      "compile_s": timing.compile_s
  })
  print(rows[-1], flush=True)
(RESULTS / "solver_cost.json").write_text(json.dumps(rows, indent=1) + "\n")
