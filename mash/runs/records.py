"""Compacting a training run's committed record: gzip progress logs and palette PNG plots.

A record in ``benchmarks/results/`` keeps what the plots, reports and T_conv need, small: its
``progress.csv`` becomes ``progress.csv.gz`` (the same values, gzip-compressed deterministically:
no file name, mtime 0, level 9, so compacting again gives identical bytes). Training logs its
float32 metrics as float64 text of up to 19 digits; compacted, each is written with 9 significant
digits, which :func:`read_cell` turns back into the same float64 (the float32 nearest to the
text), so no value a report reads changes and the logs shrink by ~40 %; a one-seed run's
``progress_seeds.csv`` (a repeat of ``progress.csv``) is dropped, a multi-seed run's compressed
the same way; every ``*.png`` is rewritten as a 256-colour palette PNG when that is smaller (one
with transparent pixels is left alone). :func:`mash.deploy.policy.read_progress` reads the
compressed logs. Nothing inside ``checkpoints/``, ``checkpoints_unrestorable/``, ``tensorboard/``
or ``cut_off/`` is touched; a folder holding ``X.csv`` and a different ``X.csv.gz`` is an error,
both kept. ``benchmarks/scripts/compact_records.py`` is its command line.

Do not compact a folder a training run is still writing.
"""

import csv
import gzip
import io
import json
import math
import os
import sys
from pathlib import Path

import numpy as np
from PIL import Image

SKIPPED_FOLDERS = frozenset({"checkpoints", "checkpoints_unrestorable", "tensorboard", "cut_off"})
PROGRESS = "progress.csv"
PER_SEED = "progress_seeds.csv"
PLOT_SUFFIX = ".png"


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


FLOAT32_FORMAT = "%.9g"  # 9 significant digits: every float32 survives the text round trip
FLOAT32_MAX = float(np.finfo(np.float32).max)
# The columns the host loop writes from Python floats (:func:`mash.runs.loop.train`'s rows); every
# other column of a progress log is a float32 metric from the jitted step.
FLOAT64_COLUMNS = frozenset({"iteration", "env_steps", "wall_s", "seed"})


def _as_float32(value: float) -> float | None:
  """``value`` rounded to float32 (as a Python float), or None when float32 cannot hold it."""
  if not math.isfinite(value) or abs(value) > FLOAT32_MAX:
    return None
  return float(np.float32(value))


def read_cell(text: str, column: str) -> float:
  """The value of one progress-log cell. In a float32 column (all but :data:`FLOAT64_COLUMNS`),
  a cell written in the 9-digit form (``text`` is exactly ``'%.9g' % f`` of the float32 ``f``
  nearest to it) is that float32; anything else is read as float64. A float32 value's full
  float64 text (training's own log) reads the same either way."""
  value = float(text)
  if column in FLOAT64_COLUMNS:
    return value
  single = _as_float32(value)
  if single is not None and single != value and FLOAT32_FORMAT % single == text:
    return single
  return value


def compact_cell(text: str, column: str) -> str:
  """A progress-log cell's shortest text that :func:`read_cell` reads as the same value: in a
  float32 column, a value float32 holds exactly is written with 9 digits; any other cell (a
  float64 column, a value float32 cannot hold, a non-number) is kept as it is."""
  if column in FLOAT64_COLUMNS:
    return text
  try:
    value = read_cell(text, column)
  except ValueError:
    return text
  if _as_float32(value) != value:
    return text
  short = FLOAT32_FORMAT % value
  return short if len(short) < len(text) else text


def compact_csv(text: str) -> str:
  """A progress log (CSV text, header first, numeric cells, no quoting) with every cell through
  :func:`compact_cell`; line endings kept. A log with a quoted cell or a row whose length is not
  the header's is returned unchanged."""
  if '"' in text:
    return text
  lines = text.splitlines(keepends=True)
  if not lines:
    return text
  columns = lines[0].rstrip("\r\n").split(",")
  out = lines[:1]
  for line in lines[1:]:
    body = line.rstrip("\r\n")
    cells = body.split(",")
    if len(cells) != len(columns):
      return text
    out.append(",".join(compact_cell(c, k) for c, k in zip(cells, columns)) + line[len(body):])
  return "".join(out)


def write_gzip(data: bytes, target: Path) -> None:
  """Writes ``data`` gzip-compressed to ``target`` (through a temporary file, then a rename): no
  file name, mtime 0, level 9, so equal inputs give equal bytes."""
  tmp = target.with_name(f".{target.name}.tmp")
  with open(tmp, "wb") as raw:
    with gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0, compresslevel=9) as out:
      out.write(data)
    raw.flush()
    os.fsync(raw.fileno())
  os.replace(tmp, target)


def same_content(plain: Path, compressed: Path) -> bool:
  """Whether ``compressed`` decompresses to the bytes of ``plain``, as they are or with the
  cells compacted (:func:`compact_csv`)."""
  try:
    with gzip.open(compressed, "rb") as f:
      inside = f.read()
    data = plain.read_bytes()
    return inside == data or inside == compact_csv(data.decode()).encode()
  except (OSError, EOFError, UnicodeDecodeError):  # a truncated or corrupt .gz
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
  values (:func:`same_content`), else reports an error and leaves both. Returns whether
  ``plain`` is still to compact (True only when no ``X.csv.gz`` is there)."""
  compressed = plain.with_name(plain.name + ".gz")
  if not is_file(compressed):
    return True
  if same_content(plain, compressed):
    size = plain.stat().st_size
    plain.unlink()
    tally.changed(plain, size, 0, f"removed: {compressed.name} holds the same values")
    return False
  tally.error(f"'{plain}' and '{compressed}' differ; left both as they are")
  return False


def compress(plain: Path, tally: Tally) -> None:
  """Replaces ``plain`` by ``plain.gz``, its cells compacted (:func:`compact_csv`)."""
  compressed = plain.with_name(plain.name + ".gz")
  size = plain.stat().st_size
  text = plain.read_bytes().decode()
  write_gzip(compact_csv(text).encode(), compressed)
  plain.unlink()
  tally.changed(plain, size, compressed.stat().st_size, f"-> {compressed.name}")


def recompact(compressed: Path, tally: Tally) -> None:
  """Rewrites the gzip log ``compressed`` (an older record's) with its cells compacted, when
  that changes its bytes."""
  size = compressed.stat().st_size
  try:
    with gzip.open(compressed, "rb") as f:
      text = f.read().decode()
  except (OSError, EOFError, UnicodeDecodeError) as e:
    tally.error(f"'{compressed}' could not be read as a gzip text file: {e}")
    return
  compact = compact_csv(text)
  if compact == text:
    return
  write_gzip(compact.encode(), compressed)
  tally.changed(compressed, size, compressed.stat().st_size, "cells to 9 digits")


def compact_folder(folder: Path, tally: Tally) -> None:
  """Compacts the progress logs of the run record in ``folder`` (if it holds one)."""
  progress, per_seed = folder / PROGRESS, folder / PER_SEED
  if is_file(progress) and settle_pair(progress, tally):
    compress(progress, tally)
  for log in (progress, per_seed):
    compressed = log.with_name(log.name + ".gz")
    if is_file(compressed) and not is_file(log):
      recompact(compressed, tally)
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

  size = path.stat().st_size
  try:
    with Image.open(path) as image:
      if image.format != "PNG" or image.mode == "P":
        return
      if has_transparency(image):
        print(f"{path}: kept (has transparent pixels)", flush=True)
        return
      dpi = image.info.get("dpi")
      palette = image.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT,
                                              dither=Image.Dither.NONE)
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
    if {PROGRESS, PER_SEED, PROGRESS + ".gz", PER_SEED + ".gz"}.intersection(filenames):
      compact_folder(Path(dirpath), logs)
    if plots is not None:
      for name in sorted(filenames):
        path = Path(dirpath) / name
        if name.lower().endswith(PLOT_SUFFIX) and not name.startswith(".") and is_file(path):
          compact_plot(path, plots)
