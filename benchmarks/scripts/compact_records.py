"""Compacts the committed records of training runs: progress logs become gzip files, plots palette PNGs.

  python benchmarks/scripts/compact_records.py [--no-plots] PATH [PATH ...]

Walks each PATH (a folder, walked recursively, or a single ``.png`` file) and, in every folder that
holds a run's progress logs:

- ``progress.csv`` is replaced by ``progress.csv.gz``, the same bytes gzip-compressed
  deterministically (no file name, mtime 0, level 9), so a rerun gives identical bytes;
- ``progress_seeds.csv`` (the per-seed log) is dropped when the run has one seed (its
  ``config.json`` says ``"seeds": 1``, or, without one, the file holds a single seed value) and
  the run's ``progress.csv(.gz)`` is there: it then repeats that log's columns. Any other run (several
  seeds, or none found) keeps it as ``progress_seeds.csv.gz``, compressed the same way.

Unless ``--no-plots`` is given, every ``*.png`` found is also rewritten as a 256-colour palette PNG
(Pillow: converted to RGB, median-cut quantized without dithering, saved with ``optimize=True``;
its dpi is kept, its text chunks are not). A file is replaced only when the result is smaller; one
already in palette mode is skipped, and one with any transparent pixel is left as it is (its alpha
would be lost), so a rerun changes no byte. Pillow (a dependency of matplotlib) is imported only
for this step.

Prints one line per file changed and, for logs and for plots, the total of their bytes before and
after. Running it again changes nothing. Nothing inside a ``checkpoints/``,
``checkpoints_unrestorable/``, ``tensorboard/`` or ``cut_off/`` folder is touched. A folder holding
both ``X.csv`` and ``X.csv.gz`` loses the ``.csv`` when the two hold the same bytes (a compaction
cut short); when they differ, it is reported as an error and both are left as they are (exit
status 1). A PATH that is neither an existing folder nor an existing ``.png`` file is refused
(exit status 2) before anything is changed.

Do not run it on a folder a training run is still writing.
"""

import argparse
import csv
import gzip
import io
import json
import os
import shutil
import sys
from pathlib import Path

SKIPPED_FOLDERS = frozenset({"checkpoints", "checkpoints_unrestorable", "tensorboard", "cut_off"})
PROGRESS = "progress.csv"
PER_SEED = "progress_seeds.csv"
PLOT_SUFFIX = ".png"
CHUNK = 1 << 20


class Tally:
  """Files changed, their bytes before and after, and the errors met."""

  def __init__(self):
    self.files = 0
    self.before = 0
    self.after = 0
    self.errors = 0

  def changed(self, path: Path, before: int, after: int, what: str) -> None:
    self.files += 1
    self.before += before
    self.after += after
    print(f"{path}: {what} ({before} -> {after} bytes)", flush=True)

  def error(self, message: str) -> None:
    self.errors += 1
    print(f"error: {message}", file=sys.stderr, flush=True)


def write_gzip(source: Path, target: Path) -> None:
  """Writes ``source`` gzip-compressed to ``target`` (through a temporary file, then a rename):
  no file name, mtime 0, level 9, so equal inputs give equal bytes."""
  tmp = target.with_name(f".{target.name}.tmp")
  with open(source, "rb") as src, open(tmp, "wb") as raw:
    with gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0, compresslevel=9) as out:
      shutil.copyfileobj(src, out, CHUNK)
    raw.flush()
    os.fsync(raw.fileno())
  os.replace(tmp, target)


def same_content(plain: Path, compressed: Path) -> bool:
  """Whether ``compressed`` decompresses to exactly the bytes of ``plain``."""
  try:
    with open(plain, "rb") as a, gzip.open(compressed, "rb") as b:
      while True:
        x, y = a.read(CHUNK), b.read(CHUNK)
        if x != y:
          return False
        if not x:
          return True
  except (OSError, EOFError):  # a truncated or corrupt .gz
    return False


def is_file(path: Path) -> bool:
  return path.is_file() and not path.is_symlink()


def seed_count(folder: Path, log: Path) -> int | None:
  """The run's number of seeds: ``config.json``'s ``seeds``, else the distinct values of the
  ``seed`` column of the per-seed log ``log`` (plain or gzip); None when neither tells."""
  config = folder / "config.json"
  if is_file(config):
    try:
      seeds = json.loads(config.read_text()).get("seeds")
    except (OSError, ValueError, AttributeError):
      seeds = None
    if isinstance(seeds, int) and not isinstance(seeds, bool):
      return seeds
  opener = gzip.open if log.name.endswith(".gz") else open
  try:
    with opener(log, "rt", newline="") as f:
      reader = csv.DictReader(f)
      if not reader.fieldnames or "seed" not in reader.fieldnames:
        return None
      values = {row["seed"] for row in reader}
  except (OSError, EOFError, csv.Error, UnicodeDecodeError):
    return None
  return len(values) or None


def settle_pair(plain: Path, tally: Tally) -> bool:
  """Handles ``X.csv`` beside an existing ``X.csv.gz``: drops the ``.csv`` when both hold the same
  bytes, else reports an error and leaves both. Returns whether ``plain`` is still to compact
  (True only when no ``X.csv.gz`` is there)."""
  compressed = plain.with_name(plain.name + ".gz")
  if not is_file(compressed):
    return True
  if same_content(plain, compressed):
    size = plain.stat().st_size
    plain.unlink()
    tally.changed(plain, size, 0, f"removed: {compressed.name} holds the same bytes")
    return False
  tally.error(f"'{plain}' and '{compressed}' differ; left both as they are")
  return False


def compress(plain: Path, tally: Tally) -> None:
  """Replaces ``plain`` by ``plain.gz``."""
  compressed = plain.with_name(plain.name + ".gz")
  size = plain.stat().st_size
  write_gzip(plain, compressed)
  plain.unlink()
  tally.changed(plain, size, compressed.stat().st_size, f"-> {compressed.name}")


def compact_folder(folder: Path, tally: Tally) -> None:
  """Compacts the progress logs of the run record in ``folder`` (if it holds one)."""
  progress, per_seed = folder / PROGRESS, folder / PER_SEED
  if is_file(progress) and settle_pair(progress, tally):
    compress(progress, tally)
  if not is_file(per_seed) or not settle_pair(per_seed, tally):
    return
  has_progress = any(is_file(folder / name) for name in (PROGRESS, PROGRESS + ".gz"))
  if has_progress and seed_count(folder, per_seed) == 1:
    size = per_seed.stat().st_size
    per_seed.unlink()
    tally.changed(per_seed, size, 0, f"removed: one seed, a duplicate of {PROGRESS}")
  else:
    compress(per_seed, tally)


def has_transparency(image) -> bool:
  """Whether ``image`` (a Pillow image) has a pixel that is not fully opaque."""
  if image.mode in ("RGBA", "LA", "PA", "La", "RGBa"):
    return image.getchannel("A").getextrema()[0] < 255
  return "transparency" in image.info


def compact_plot(path: Path, tally: Tally) -> None:
  """Rewrites the PNG ``path`` as a 256-colour palette PNG when that is smaller."""
  from PIL import Image  # pylint: disable=import-outside-toplevel

  size = path.stat().st_size
  try:
    with Image.open(path) as image:
      if image.format != "PNG" or image.mode == "P":
        return
      if has_transparency(image):
        print(f"{path}: kept (has transparent pixels)", flush=True)
        return
      dpi = image.info.get("dpi")
      palette = image.convert("RGB").quantize(
          colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
  except (OSError, ValueError) as e:  # unreadable or truncated
    tally.error(f"'{path}' could not be read as an image: {e}")
    return
  buffer = io.BytesIO()
  palette.save(buffer, format="PNG", optimize=True, **({"dpi": dpi} if dpi else {}))
  data = buffer.getvalue()
  if len(data) >= size:
    print(f"{path}: kept (palette version not smaller: {len(data)} bytes)", flush=True)
    return
  tmp = path.with_name(f".{path.name}.tmp")
  with open(tmp, "wb") as out:
    out.write(data)
    out.flush()
    os.fsync(out.fileno())
  os.replace(tmp, path)
  tally.changed(path, size, len(data), "-> 256-colour palette")


def compact_tree(root: Path, logs: Tally, plots: Tally | None) -> None:
  """Compacts every run record under ``root`` (and, when ``plots`` is given, every PNG),
  skipping the folders that hold run bulk."""
  if SKIPPED_FOLDERS.intersection(root.resolve().parts):
    return
  if is_file(root):
    if plots is not None and root.name.lower().endswith(PLOT_SUFFIX):
      compact_plot(root, plots)
    return
  for dirpath, dirnames, filenames in os.walk(root):
    dirnames[:] = sorted(d for d in dirnames if d not in SKIPPED_FOLDERS)
    if PROGRESS in filenames or PER_SEED in filenames:
      compact_folder(Path(dirpath), logs)
    if plots is not None:
      for name in sorted(filenames):
        path = Path(dirpath) / name
        if name.lower().endswith(PLOT_SUFFIX) and not name.startswith(".") and is_file(path):
          compact_plot(path, plots)


def main(argv: list[str] | None = None) -> int:
  parser = argparse.ArgumentParser(
      description=__doc__.split("\n", 1)[0],
      epilog="Replaces progress.csv by progress.csv.gz; drops or compresses progress_seeds.csv; "
             "rewrites PNG plots as 256-colour palette PNGs.")
  parser.add_argument("dirs", metavar="PATH", nargs="+", type=Path,
                      help="a folder to walk for run records and plots, or one .png file")
  parser.add_argument("--no-plots", action="store_true",
                      help="leave PNG files as they are (logs only; standard library only)")
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
