"""``python -m experiments.armswing``: train the arm-swing task (2 leg and 2 arm agents)."""

from __future__ import annotations

import argparse

from mash import cli
from mash.runs import launch


def main(argv: list[str] | None = None) -> None:
  parser = cli.Parser(prog="python -m experiments.armswing", description=__doc__.splitlines()[0],
                      formatter_class=argparse.RawDescriptionHelpFormatter,
                      epilog=launch.TRAIN_EPILOG)
  launch.add_train_args(parser)
  launch.train_main("armswing", parser.parse_args(argv), argv)


if __name__ == "__main__":
  main()
