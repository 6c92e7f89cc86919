"""``python -m experiments.robot check FILE``: a robot file checked against its model before
training.

Reads the file (every joint and body name checked against its MJCF), builds the model, compares
the mirror signs with the joint axes, holds the default pose at zero action for --seconds in
MuJoCo C and in MJX, plays one gait cycle of the reference (each foot's clearance, left against
right; each joint's reference against its limits), measures each foot's frame and draws the
default pose and both swing peaks (--out DIR/<name>_check.png, with a JSON of the figures).
Each finding that would spoil training is an `error:` line naming the field to change; the exit
status is 1 when there is one, 2 when the file cannot be read.

Examples:
  python -m experiments.robot check booster_t1
  python -m experiments.robot check path/to/my_robot.toml --out checks/
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mash import cli
from mash.analysis import robot_check


def main(argv=None) -> None:
  p = cli.Parser(prog="python -m experiments.robot", description=__doc__.splitlines()[0],
                 formatter_class=argparse.RawDescriptionHelpFormatter,
                 epilog="\n".join(__doc__.splitlines()[2:]))
  p.add_argument("action", choices=["check"], help="what to do with the robot file")
  p.add_argument("robot", metavar="FILE", help="a robot file (.toml) or a shipped robot's name")
  p.add_argument("--seconds", type=float, default=10.0, help="how long it must stand (s)")
  p.add_argument("--out", default=".", metavar="DIR",
                 help="folder for <name>_check.png and <name>_check.json (default: here)")
  p.add_argument("--no-mjx", action="store_true", help="skip the MJX stand test (its compile)")
  args = p.parse_args(argv)
  with cli.user_errors():
    cli.check_paths({"FILE": args.robot, "--out": args.out})
    if not 0 < args.seconds <= 600:
      raise cli.UserError(f"--seconds must be in (0, 600], got {args.seconds}")
    cli.check_writable_dir(args.out, "--out")
    print(
        f"checking {args.robot}: stand {args.seconds:g} s in MuJoCo C" +
        ("" if args.no_mjx else " and in MJX (compiling takes about a minute on a CPU)") +
        ", one gait cycle of the reference", flush=True)
    findings, _ = robot_check.check(args.robot, args.seconds, Path(args.out), not args.no_mjx)
  for f in findings:
    where = f" [{f.field}]" if f.field and f.level != "ok" else ""
    print(f"{f.level}: {f.text}{where}", file=sys.stderr if f.level == "error" else sys.stdout)
  if any(f.level == "error" for f in findings):
    sys.exit(1)


if __name__ == "__main__":
  main()
