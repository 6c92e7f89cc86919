"""``python -m experiments.play --policy NAME``: a trained policy walking in native MuJoCo.

NAME is a shipped policy (a folder of mash/assets/policies/, e.g. t1_bipedal_mash), a policy folder
holding policy.onnx, an ONNX file, or a run directory (its policy.onnx, exported first when it is
missing or older than the run's latest checkpoint). It plays the ONNX file in MuJoCo C through
the controller a robot would run (mash.deploy.sim2sim), without the training code.

With a display, MuJoCo's viewer opens with keyboard commands (up/down: forward speed +-0.1 m/s,
left/right: yaw rate +-0.1 rad/s, space: stand / walk, backspace: reset). Without one, or with
--video, the policy plays --seconds at --command and writes an MP4 or a GIF (software rendering:
about 0.1 s per frame on a CPU).

Examples:
  python -m experiments.play --policy t1_bipedal_mash
  python -m experiments.play --policy t1_bipedal_mash --video walk.mp4 --seconds 10 \
--command 0.6,0,0
  python -m experiments.play --policy runs/bipedal_mash_cpu_X --stand --video stand.mp4
"""

from __future__ import annotations

import argparse

from mash import cli as common
from mash.deploy import play


def main(argv=None) -> None:
  p = common.Parser(prog="python -m experiments.play", description=__doc__.splitlines()[0],
                    formatter_class=argparse.RawDescriptionHelpFormatter,
                    epilog="\n".join(__doc__.splitlines()[2:]))
  p.add_argument("--policy", required=True,
                 help="shipped policy name, policy folder, .onnx file or run directory")
  p.add_argument("--command", type=play.command_arg, default=(0.4, 0.0, 0.0), metavar="VX[,VY,YAW]",
                 help="velocity command when playing headless (default "
                 "0.4,0,0)")
  p.add_argument("--stand", action="store_true", help="the standing command instead")
  p.add_argument("--seconds", type=play.seconds_arg, default=10.0, help="how long to play headless")
  p.add_argument(
      "--video", default=None, metavar="OUT.mp4",
      help="write an MP4 (or an animated GIF: OUT.gif, 400x300 at 12.5 fps) instead of "
      "opening the viewer (the default without a display: <policy name>.mp4)")
  p.add_argument("--phase", type=float, default=0.0, help="initial gait phase in [0, 1)")
  p.add_argument("--robot", default=None, metavar="NAME|FILE.toml",
                 help="the robot file to play on (default: the shipped robot the policy names)")
  args = p.parse_args(argv)
  say = lambda msg: print(msg, flush=True)
  try:
    options, backend = play.prepare(play.Options(**vars(args)), say)
  except common.UserError as e:
    p.error(str(e))
  with common.user_errors():
    play.run(options, backend, say)


if __name__ == "__main__":
  main()
