"""``python -m experiments.bipedal``: train the bipedal task (2 leg agents; arms held by PD)."""

from __future__ import annotations

import argparse

from mash import cli
from mash.runs import launch


def main(argv: list[str] | None = None) -> None:
  parser = cli.Parser(prog="python -m experiments.bipedal", description=__doc__.splitlines()[0],
                      formatter_class=argparse.RawDescriptionHelpFormatter,
                      epilog=launch.TRAIN_EPILOG)
  launch.add_train_args(parser)
  launch.train_main("bipedal", parser.parse_args(argv), argv)


if __name__ == "__main__":
  main()
