"""Compacting run records: the 9-digit float32 cells read back as the very values logged."""

import gzip
import shutil

import numpy as np
import pytest

from mash.deploy.policy import read_progress
from mash.runs import records


@pytest.mark.parametrize("value", [0.1, -2.3302842e-05, 17.003122, 3.0e38, 1.0e-40, 0.5, 0.0])
def test_a_float32_metric_round_trips_through_nine_digits(value):
  single = float(np.float32(value))
  logged = repr(single)  # what training writes: the float64 text of the float32 value
  short = records.compact_cell(logged, "entropy")
  assert len(short) <= len(logged)
  assert len(short.lstrip("-").replace(".", "").split("e")[0].lstrip("0")) <= 9
  assert np.float64(records.read_cell(short, "entropy")).tobytes() == np.float64(single).tobytes()
  assert records.compact_cell(short, "entropy") == short  # compacting again changes nothing


def test_float64_columns_and_values_float32_cannot_hold_are_kept():
  # wall_s is a Python float with 3 decimals: '170.347' is the 9-digit form of the float32
  # nearest to it, but its column says float64, so it stays 170.347.
  assert records.compact_cell("170.347", "wall_s") == "170.347"
  assert records.read_cell("170.347", "wall_s") == 170.347
  assert records.read_cell("170.347", "entropy") == float(np.float32(170.347))
  # A float64 value in a metric column that float32 does not hold is left as it is.
  assert records.compact_cell("0.1", "entropy") == "0.1"
  assert records.read_cell("0.1", "entropy") == 0.1
  assert records.compact_cell("nan", "entropy") == "nan"
  assert records.compact_cell("-0.0", "entropy") == "-0"
  assert np.signbit(records.read_cell("-0", "entropy"))


def test_compact_csv_keeps_line_endings_and_refuses_ragged_rows():
  text = "iteration,wall_s,entropy\r\n1,170.347,0.10000000149011612\r\n"
  assert records.compact_csv(text) == "iteration,wall_s,entropy\r\n1,170.347,0.100000001\r\n"
  ragged = "iteration,entropy\n1,0.10000000149011612,7\n"
  assert records.compact_csv(ragged) == ragged


def _columns_equal(a: dict, b: dict) -> bool:
  return a.keys() == b.keys() and all(a[k].tobytes() == b[k].tobytes() for k in a)


def test_a_compacted_training_log_reads_back_bit_for_bit(smoke_run, tmp_path):
  """The smoke run's own log: every metric column holds float32 values (the assumption behind
  FLOAT64_COLUMNS), the compacted record is smaller, reads the same to the bit, and compacting
  it again, or an older record gzipped with the full digits, gives the same bytes."""
  logged = read_progress(smoke_run)
  for column, values in logged.items():
    if column not in records.FLOAT64_COLUMNS:
      assert np.array_equal(values.astype(np.float32).astype(np.float64), values), column
  record = tmp_path / "record"
  record.mkdir()
  shutil.copy(smoke_run / "progress.csv", record / "progress.csv")
  size = (record / "progress.csv").stat().st_size
  tally = records.Tally()
  records.compact_tree(record, tally, None)
  compacted = record / "progress.csv.gz"
  assert not (record / "progress.csv").exists() and tally.errors == 0
  assert len(gzip.decompress(compacted.read_bytes())) < 0.8 * size
  assert _columns_equal(read_progress(record), logged)
  first = compacted.read_bytes()
  records.compact_tree(record, records.Tally(), None)
  assert compacted.read_bytes() == first
  # An older record: the full digits, gzipped; compacting rewrites it to the same bytes.
  compacted.write_bytes(gzip.compress((smoke_run / "progress.csv").read_bytes()))
  assert _columns_equal(read_progress(record), logged)
  records.compact_tree(record, records.Tally(), None)
  assert compacted.read_bytes() == first
  # A compaction cut short: the plain log beside its compacted copy is dropped as the same values.
  shutil.copy(smoke_run / "progress.csv", record / "progress.csv")
  records.compact_tree(record, records.Tally(), None)
  assert not (record / "progress.csv").exists() and compacted.read_bytes() == first
