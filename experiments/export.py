"""``python -m experiments.export --run DIR [--out FILE]``: the run's policy as one ONNX file.

Exports the latest checkpoint (default ``DIR/policy.onnx``; see :mod:`mash.deploy.export` and
``docs/deploy.md`` for the inputs, outputs and metadata), then checks it: onnxruntime against the
JAX policy on random observations, max |difference| at most ``--tolerance``. ``DIR`` may also be a
policy folder (:mod:`mash.deploy.policy`).
"""

from __future__ import annotations

from pathlib import Path

from mash import cli as common
from mash.deploy import export
from mash.deploy import policy as policy_lib


def main(argv=None) -> None:
  p = common.Parser(prog="python -m experiments.export", description=__doc__.splitlines()[0])
  p.add_argument("--run", required=True,
                 help="run directory, or policy folder (mash.deploy.policy)")
  p.add_argument("--out", default=None, help="ONNX file to write (default: DIR/policy.onnx)")
  p.add_argument("--seed", type=int, default=0, help="which seed of a multi-seed run")
  p.add_argument("--check", type=int, default=256,
                 help="random observations in the check (0: skip)")
  p.add_argument("--tolerance", type=float, default=1e-5, help="max |onnx - jax| allowed")
  p.add_argument(
      "--robot", default=None, metavar="NAME|FILE.toml",
      help="the robot file to use instead of the run's env.robot (the same robot, "
      "e.g. a user's file that has moved)")
  args = p.parse_args(argv)
  with common.user_errors():
    common.check_paths({"--run": args.run, "--out": args.out})
    if args.check < 0:
      raise common.UserError(f"--check must be >= 0, got {args.check}")
    out = Path(args.out) if args.out else Path(args.run) / "policy.onnx"
    if out.is_dir():
      raise common.UserError(f"--out '{out}' is a directory; expected a file path like policy.onnx")
    policy_lib.load_config(args.run, args.robot)  # a missing run is named before the output path
    common.check_writable_file(out, "--out")
    policy = policy_lib.load(args.run, seed=args.seed, robot=args.robot)
    parts = export.policy_parts(policy)
    path = export.export_policy(parts, out)
    meta = export.read_metadata(path)
    print(
        f"exported {args.run} (iteration {policy.iteration}, seed {policy.seed}, "
        f"{policy.config.task}/{policy.config.algo}) -> {path} "
        f"({path.stat().st_size / 1024:.0f} KiB): "
        f"{len(meta['joint_order'])} joints in, {len(meta['controlled_joints'])} targets out "
        f"at {meta['control_rate_hz']:g} Hz", flush=True)
    if args.check:
      diff = export.verify(path, parts, n=args.check)
      worst = max(diff["action"], diff["q_target"])
      verdict = "OK" if worst <= args.tolerance else "FAILED"
      print(
          f"check on {args.check} random observations: max |onnx - jax| action "
          f"{diff['action']:.2e}, q_target {diff['q_target']:.2e} (tolerance "
          f"{args.tolerance:.0e}): {verdict}", flush=True)
      if worst > args.tolerance:
        raise common.UserError(f"the ONNX policy differs from JAX by {worst:.2e} > "
                               f"{args.tolerance:.0e}; the file is kept at {path} for inspection")


if __name__ == "__main__":
  main()
