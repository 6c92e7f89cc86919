"""``python -m experiments.evaluate --run DIR``: the paper's metrics of a trained run.

Deterministic rollouts of the latest checkpoint at a fixed forward command (domain randomization
on) -> ``DIR/eval/metrics.json``, ``DIR/eval/trajectories.npz`` and ``DIR/eval/hip_pitch.png``.
``metrics.json`` also splits the falls by floor friction (``fall_rate_by_friction``), and the
trajectories keep each episode's ``friction``.
With ``--no-dr`` or ``--no-push`` the same files go to ``DIR/eval_no_dr/`` or ``DIR/eval_no_push/``,
with ``--push-interval S`` to ``DIR/eval_push_interval_<S>s/`` (``--friction LO HI``, another
floor-friction range, appends ``_friction_<LO>-<HI>``), so a diagnostic never replaces the
evaluation as trained. ``--iteration N`` evaluates the checkpoint saved at iteration N instead of
the latest (a learning curve's earlier policies) and appends ``_it<N>`` to the directory's name;
``--seed S`` draws other episodes (floors, robots, pushes) and appends ``_seed<S>``. A run trained
with velocity kicks is evaluated without them (the paper's randomization; the robustness battery
measures shoves); ``--kicks`` keeps them and appends ``_kicks``.
``DIR`` may also be a policy folder (:mod:`mash.deploy.policy`): its one policy, no ``T_conv`` (no
learning curve), the same files in the folder.

``--tracking`` measures how the policy follows its commands instead: ``--episodes`` (default 64)
episodes per command of ``mash.analysis.evaluation.TRACKING_GRID`` (standing; vx -0.3 to 0.8;
vy +-0.2; yaw rate +-0.5), randomization and pushes as trained, into ``DIR/eval_tracking/``:
``tracking.json`` (per command: falls and the achieved heading-frame velocities; the mean |error|
per axis, the fall rate and the standing drift), ``tracking.png`` (commanded against achieved)
and ``tracking_trajectories.npz`` (``commands [E,4]``, ``velocity [E,T,3]``, ``alive [E,T]``).
"""

from __future__ import annotations

from mash import cli
from mash.analysis import evaluation, reports, robustness


def main(argv=None) -> None:
  p = cli.Parser(prog="python -m experiments.evaluate", description=__doc__.splitlines()[0])
  p.add_argument("--run", required=True,
                 help="run directory, or policy folder (mash.deploy.policy)")
  p.add_argument("--episodes", type=int, default=None,
                 help="episodes (default 32), or episodes per command with --tracking (default 64)")
  p.add_argument("--seconds", type=float, default=20.0, help="episode duration")
  p.add_argument("--command-vx", type=float, default=None,
                 help="forward command (m/s, default 0.4)")
  p.add_argument("--no-dr", action="store_true",
                 help="evaluate without domain randomization (writes DIR/eval_no_dr/)")
  p.add_argument("--no-push", action="store_true",
                 help="domain randomization without the torso pushes (writes DIR/eval_no_push/)")
  p.add_argument(
      "--push-interval", type=float, default=None, metavar="S",
      help="hold each push S seconds (0: a new push every control step) instead of the "
      "run's own setting (writes DIR/eval_push_interval_<S>s/)")
  p.add_argument(
      "--kicks", action="store_true",
      help="keep the training's velocity kicks on (off by default: evaluation reports "
      "the paper's randomization; appends _kicks to the output directory)")
  p.add_argument(
      "--iteration", type=int, default=None, metavar="N",
      help="evaluate the checkpoint saved at iteration N, not the latest (appends "
      "_it<N> to the output directory)")
  p.add_argument(
      "--friction", type=float, nargs=2, default=None, metavar=("LO", "HI"),
      help="draw the floor friction from U[LO, HI] instead of the run's own range, e.g. "
      "0.1 1.2 (the paper's) for a run trained on a narrower one (appends "
      "_friction_<LO>-<HI> to the output directory)")
  p.add_argument(
      "--seed", type=int, default=None, metavar="S",
      help="rollout seed: the floors, robots, pushes and start phases drawn (default: "
      "the evaluation's fixed seed; another one appends _seed<S> to the output "
      "directory, e.g. to confirm on fresh episodes a checkpoint picked among "
      "several)")
  p.add_argument(
      "--robot", default=None, metavar="NAME|FILE.toml",
      help="the robot file to use instead of the run's env.robot (the same robot, "
      "e.g. a user's file that has moved)")
  p.add_argument(
      "--robustness", action="store_true",
      help="the robustness battery instead: at vx 0.4, kicks of 0.25-1 m/s in 8 "
      "directions, friction bands, torso mass +-20 %%, weak motors, sensor noise, "
      "latency 0-40 ms, --episodes per condition (default 64), the rest as trained; "
      "writes DIR/eval_robustness/robustness.json, robustness.png")
  p.add_argument(
      "--tracking", action="store_true",
      help="command tracking instead: every command of the grid (standing; vx -0.3 to "
      "0.8; vy +-0.2; yaw rate +-0.5), --episodes per command (default 64), "
      "writes DIR/eval_tracking/tracking.json, tracking.png")
  args = p.parse_args(argv)
  with cli.user_errors():
    if args.robustness:
      _robustness(args)
      return
    cfg = _eval_config(args)
    dr = reports.describe(cfg, args.seed is not None)
    which = "" if args.iteration is None else f" (checkpoint of iteration {args.iteration})"
    if args.tracking:
      print(
          f"tracking {args.run}{which}: {len(evaluation.TRACKING_GRID)} commands x "
          f"{args.episodes} episodes x {args.seconds:g} s, DR {dr}", flush=True)
      reports.print_tracking(
          reports.tracking_run(args.run, cfg, iteration=args.iteration, robot=args.robot))
      out = f"{args.run}/{reports.tracking_dir_name(cfg, args.iteration)}"
      print(f"wrote {out}/tracking.json, tracking.png, tracking_trajectories.npz")
      return
    print(
        f"evaluating {args.run}{which}: {args.episodes} episodes x {args.seconds:g} s at vx = "
        f"{args.command_vx} m/s, DR {dr}", flush=True)
    reports.print_metrics(
        reports.evaluate_run(args.run, cfg, iteration=args.iteration, robot=args.robot))
    out = f"{args.run}/{reports.eval_dir_name(cfg, args.iteration)}"
    print(f"wrote {out}/metrics.json, trajectories.npz, hip_pitch.png")


def _robustness(args) -> None:
  """``--robustness``: the battery in MJX (its own episodes, command and seed)."""
  cli.check_path(args.run, "--run")
  flags = {
      "--tracking": args.tracking, "--no-dr": args.no_dr, "--no-push": args.no_push,
      "--friction": args.friction, "--push-interval": args.push_interval,
      "--command-vx": args.command_vx, "--kicks": args.kicks
  }
  given = [f for f, v in flags.items() if v]
  if given:
    raise cli.UserError(f"--robustness runs its own conditions; drop {', '.join(given)}")
  cfg = robustness.BatteryConfig(
      **{k: v for k, v in (("episodes", args.episodes), ("seed", args.seed)) if v is not None})
  try:
    robustness.check_config(cfg)
  except ValueError as e:
    raise cli.UserError(str(e).replace("episodes", "--episodes", 1)) from None
  n = len(robustness.conditions(cfg))
  print(
      f"robustness of {args.run}: {n} conditions x {cfg.episodes} episodes x "
      f"{cfg.episode_s:g} s at vx {cfg.command_vx:g} m/s in MJX (one compiled rollout; "
      "minutes on a CPU)", flush=True)
  result = reports.robustness_run(args.run, cfg, iteration=args.iteration, robot=args.robot)
  reports.print_robustness(result)
  suffix = "" if args.iteration is None else f"_it{args.iteration}"
  print(f"wrote {args.run}/eval_robustness{suffix}/robustness.json, robustness.png")


def _eval_config(args) -> evaluation.EvalConfig:
  """The evaluation the flags ask for, checked (one ``error:`` line for a bad combination)."""
  cli.check_path(args.run, "--run")
  if args.tracking and args.command_vx is not None:
    raise cli.UserError("--tracking rolls out its own grid of commands; drop --command-vx")
  if args.episodes is None:
    args.episodes = 64 if args.tracking else 32
  if args.command_vx is None:
    args.command_vx = 0.4
  if args.episodes < 1 or args.seconds <= 0:
    raise cli.UserError("--episodes must be >= 1 and --seconds > 0")
  if args.iteration is not None and args.iteration < 1:
    raise cli.UserError(f"--iteration must be a saved iteration >= 1, got {args.iteration}")
  if args.push_interval is not None and (args.push_interval < 0 or args.no_dr or args.no_push):
    raise cli.UserError("--push-interval takes seconds >= 0 and needs the pushes on "
                        "(not with --no-dr or --no-push)")
  if args.seed is not None and args.seed < 0:
    raise cli.UserError(f"--seed must be >= 0, got {args.seed}")
  if args.friction is not None and (args.no_dr or not 0 < args.friction[0] <= args.friction[1]):
    raise cli.UserError(f"--friction takes LO HI with 0 < LO <= HI and needs DR on (not with "
                        f"--no-dr), got {args.friction}")
  if args.kicks and args.no_dr:
    raise cli.UserError("--kicks needs the randomization on (not with --no-dr)")
  cfg = evaluation.EvalConfig(
      command_vx=args.command_vx, num_episodes=args.episodes, episode_s=args.seconds,
      randomization=not args.no_dr, pushes=not args.no_push, push_interval_s=args.push_interval,
      friction=None if args.friction is None else tuple(args.friction), kicks=args.kicks,
      **({} if args.seed is None else {"seed": args.seed}))
  try:
    evaluation.check_config(cfg, reports.EVAL_FLAGS)
  except ValueError as e:
    raise cli.UserError(str(e)) from None
  return cfg


if __name__ == "__main__":
  main()
