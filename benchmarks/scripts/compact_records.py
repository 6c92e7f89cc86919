"""Compacts the committed records of training runs: progress logs become gzip files, plots palette
PNGs.

  python benchmarks/scripts/compact_records.py [--no-plots] PATH [PATH ...]

Walks each PATH (a folder, walked recursively, or a single ``.png`` file) and, in every folder that
holds a run's progress logs:

- ``progress.csv`` is replaced by ``progress.csv.gz``, gzip-compressed deterministically (no file
  name, mtime 0, level 9), so a rerun gives identical bytes, with each float32 metric written
  with 9 significant digits instead of the float64 text of up to 19 (read back by
  ``read_progress`` as the very values logged; a ``progress.csv.gz`` compacted before this is
  rewritten so);
- ``progress_seeds.csv`` (the per-seed log) is dropped when the run has one seed (its
  ``config.json`` says ``"seeds": 1``, or, without one, the file holds a single seed value) and
  the run's ``progress.csv(.gz)`` is there: it then repeats that log's columns. Any other run
  (several seeds, or none found) keeps it as ``progress_seeds.csv.gz``, compressed the same way.

Unless ``--no-plots`` is given, every ``*.png`` found is also rewritten as a 256-colour palette PNG
(Pillow: converted to RGB, median-cut quantized without dithering, saved with ``optimize=True``;
its dpi is kept, its text chunks are not). A file is replaced only when the result is smaller; one
already in palette mode is skipped, and one with any transparent pixel is left as it is (its alpha
would be lost), so a rerun changes no byte.

Prints one line per file changed and, for logs and for plots, the total of their bytes before and
after. Running it again changes nothing. Nothing inside a ``checkpoints/``,
``checkpoints_unrestorable/``, ``tensorboard/`` or ``cut_off/`` folder is touched. A folder holding
both ``X.csv`` and ``X.csv.gz`` loses the ``.csv`` when the two hold the same values (a
compaction cut short); when they differ, it is reported as an error and both are left as they are
(exit status 1). A PATH that is neither an existing folder nor an existing ``.png`` file is refused
(exit status 2) before anything is changed. The work is :mod:`mash.runs.records`'s.

Do not run it on a folder a training run is still writing.
"""

import argparse
import sys
from pathlib import Path

from mash.runs.records import PLOT_SUFFIX, Tally, compact_tree, is_file


def main(argv: list[str] | None = None) -> int:
  parser = argparse.ArgumentParser(
      description=__doc__.split("\n", 1)[0],
      epilog="Replaces progress.csv by progress.csv.gz; drops or compresses progress_seeds.csv; "
      "rewrites PNG plots as 256-colour palette PNGs.")
  parser.add_argument("dirs", metavar="PATH", nargs="+", type=Path,
                      help="a folder to walk for run records and plots, or one .png file")
  parser.add_argument("--no-plots", action="store_true",
                      help="leave PNG files as they are (logs only)")
  args = parser.parse_args(argv)
  for d in args.dirs:
    if not (d.is_dir() or (is_file(d) and d.name.lower().endswith(PLOT_SUFFIX))):
      print(f"error: '{d}' is neither an existing folder nor a .png file", file=sys.stderr)
      return 2
  logs = Tally()
  plots = None if args.no_plots else Tally()
  for d in args.dirs:
    compact_tree(d, logs, plots)
  errors = 0
  for what, tally in (("logs", logs), ("plots", plots)):
    if tally is None:
      continue
    errors += tally.errors
    print(f"total {what}: {tally.files} files changed, {tally.before} bytes before, {tally.after} "
          f"bytes after" + (f"; {tally.errors} errors" if tally.errors else ""))
  return 1 if errors else 0


if __name__ == "__main__":
  sys.exit(main())
