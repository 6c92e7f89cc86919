"""The shipped policy's falls on slippery floors under other MJX solver settings.

  python benchmarks/scripts/2026-12-01_solver_iterations_probe.py ITERATIONS LS LO HI N

rolls ``mash/assets/policies/t1_bipedal_mash`` as it was shipped until 2026-12-05 (trained with 1
Newton iteration, 4 line-search iterations; run the script in a checkout of commit b46426c to get
that policy: the folder holds the 2-iteration preset's seed 0 since) for N randomized 20 s
episodes at vx 0.4 m/s on floors of friction U[LO, HI], with the env's solver set to
ITERATIONS / LS, and prints one JSON line. The script now imports the current package layout
(``mash.analysis``, ``mash.deploy``, ``mash.sim``), so run it in the current tree with only commit
b46426c's ``mash/assets/policies/t1_bipedal_mash/`` brought in (``git show
b46426c:mash/assets/policies/t1_bipedal_mash/<file> > mash/assets/policies/t1_bipedal_mash/<file>``
for ``card.md``, ``config.json``, ``policy.json``, ``policy.npz``, ``policy.onnx``).
"""

import dataclasses
import json
import sys

from mash.analysis import evaluation
from mash.deploy import policy as policy_lib
from mash.sim import env as env_lib

iterations, ls_iterations, lo, hi, n = (int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]),
                                        float(sys.argv[4]), int(sys.argv[5]))
policy = policy_lib.load("mash/assets/policies/t1_bipedal_mash")
physics = dataclasses.replace(policy.config.env.physics, iterations=iterations,
                              ls_iterations=ls_iterations)
eval_cfg = evaluation.EvalConfig(num_episodes=n, friction=(lo, hi))
env = env_lib.MashEnv(
    evaluation.eval_env_config(dataclasses.replace(policy.config.env, physics=physics), eval_cfg))
traj = evaluation.rollout(env, policy_lib.make_inference_fn(policy, env), eval_cfg)
alive = traj["alive"].min(axis=1) > 0
print(
    json.dumps({
        "iterations": iterations, "ls_iterations": ls_iterations, "friction": [lo, hi],
        "episodes": n, "fall_rate": float(1 - alive.mean()),
        "forward_speed_survivors": float(traj["forward_velocity"][alive].mean())
    }))
