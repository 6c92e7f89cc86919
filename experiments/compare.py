"""``python -m experiments.compare --task bipedal --seeds 5``: MASH vs single-agent PPO.

The same learning-rate search for both methods (seed 0 at each of ``--learning-rates``, one rule
picks each method's rate), then one run per method and seed at the picked rate, paired by seed
(``OUT/<algo>/lr<rate>/seed<s>/``), each evaluated on ``--episodes`` episodes and kept as a policy
folder (``seed<s>/policy/``); after each pair ``report.md``, ``report.json``, ``reward_curves.png``
and ``hip_pitch.png`` (:mod:`mash.analysis.compare`: the paper's four metrics decide, Holm over
those four; the rest is a secondary family). The same command again continues the comparison on
its folder's own config (:mod:`mash.runs.comparison`). ``--readme-table DIR [DIR ...]`` prints the
README's table from finished reports.
"""

from __future__ import annotations

from pathlib import Path

from mash import cli
from mash.analysis import compare as compare_lib
from mash.analysis import evaluation
from mash.runs import comparison, experiment
from mash.sim import robots


def main(argv=None) -> None:
  p = cli.Parser(prog="python -m experiments.compare", description=__doc__.splitlines()[0])
  p.add_argument("--task", default="bipedal", help="bipedal | armswing")
  p.add_argument("--seeds", type=int, default=5)
  p.add_argument(
      "--preset", default=None,
      help="smoke | cpu | gpu for a new comparison (default: from the backend); a "
      "continued one trains on its folder's own config")
  p.add_argument(
      "--out", default=None,
      help="output directory; run the same command again to continue it (default: "
      "runs/compare_<task>_<preset>)")
  p.add_argument("--episodes", type=int, default=128, help="evaluation episodes per seed")
  p.add_argument("--eval-seconds", type=float, default=20.0)
  p.add_argument("--set", action="append", default=[], metavar="PATH=VALUE",
                 help="override a config field of both methods (repeatable; a new comparison)")
  p.add_argument(
      "--learning-rates", default="1e-3,3e-4", metavar="LR,LR",
      help="the search both methods get: seed 0 at each rate, the same rule picks "
      "each method's (default 1e-3,3e-4)")
  p.add_argument(
      "--robot", default=None, metavar="NAME|FILE.toml",
      help=f"a shipped robot ({', '.join(robots.names())}) or a robot file (default: "
      "booster_t1; the same as --set env.robot=...)")
  p.add_argument(
      "--seeds-at-once", type=int, default=1, metavar="K",
      help="train up to K seeds of a method without a run yet in one vmapped call "
      "(for a GPU; default 1: one run per seed)")
  p.add_argument("--no-progress", action="store_true")
  p.add_argument(
      "--readme-table", nargs="+", default=None, metavar="DIR",
      help="print the README's table from these comparison folders' report.json "
      "(one per task) instead of running anything")
  args = p.parse_args(argv)
  with cli.user_errors():
    if args.readme_table is not None:
      print(compare_lib.readme_block(args.readme_table), end="")
      return
    plan = _plan(args)
    given = bool(args.preset or args.set)
    print(
        f"preset: {plan.preset}; MASH vs PPO on {plan.task}, seeds 0-{plan.seeds - 1}, one run "
        f"per method and seed -> {plan.out} (a finished seed is reused, an interrupted one "
        "resumed; a continued comparison keeps its own config)", flush=True)
    md = comparison.run(plan, given)
    print(md)
    print(f"wrote {plan.out}/report.md, report.json, reward_curves.png, hip_pitch.png")


def _plan(args) -> comparison.Plan:
  """The comparison the flags ask for, checked before any work (one ``error:`` line)."""
  cli.check_paths({"--out": args.out})
  cli.check_task(args.task)
  if args.seeds < 1 or args.episodes < 1 or not args.eval_seconds > 0:
    raise cli.UserError("--seeds and --episodes must be >= 1 and --eval-seconds > 0")
  if args.seeds_at_once < 1:
    raise cli.UserError(f"--seeds-at-once must be >= 1, got {args.seeds_at_once}")
  eval_cfg = evaluation.EvalConfig(num_episodes=args.episodes, episode_s=args.eval_seconds)
  try:
    evaluation.check_config(eval_cfg, {"num_episodes": "--episodes", "episode_s": "--eval-seconds"})
  except ValueError as e:
    raise cli.UserError(str(e)) from None
  try:
    learning_rates = sorted({float(x) for x in args.learning_rates.split(",") if x.strip()})
  except ValueError:
    learning_rates = []
  if not learning_rates or not all(0 < lr < 1 for lr in learning_rates):
    raise cli.UserError(f"--learning-rates '{args.learning_rates}': expected rates in (0, 1) "
                        "separated by commas, e.g. 1e-3,3e-4")
  if args.robot is not None:  # before the --set overrides, so that those still win
    args.set = [f"env.robot={cli.robot_arg(args.robot)}", *args.set]
  preset = args.preset or cli.default_preset()[0]
  for algo in ("mash", "ppo"):  # a bad --set is one line before any work
    experiment.make_config(args.task, algo, preset, 1, "none", args.set)
  out = Path(args.out or f"runs/compare_{args.task}_{preset}")
  cli.check_writable_dir(out, "--out")
  return comparison.Plan(task=args.task, out=out, preset=preset, overrides=tuple(
      args.set), seeds=args.seeds, learning_rates=tuple(learning_rates), eval_config=eval_cfg,
                         seeds_at_once=args.seeds_at_once, show_progress=not args.no_progress)


if __name__ == "__main__":
  main()
