"""pgvd.carmen, the CARMEN log reader, on the real intel and freiburg-079 logs and fuzzed input."""

from __future__ import annotations

import gzip
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pgvd.carmen import LaserScan, LogFormatError, read_carmen

FLASER_3 = "FLASER 3 1.0 2.0 81.83 0.5 -1.0 0.25 0.6 -1.1 0.3 12.5 host 12.75\n"


@pytest.mark.parametrize(
    ("log", "count", "beams"),
    [("intel-corrected.log.gz", 910, 180), ("freiburg-079-corrected.log.gz", 4791, 360)],
)
def test_real_logs(shared, log, count, beams):
    scans = read_carmen(shared / "logs" / log)
    assert len(scans) == count
    assert {s.ranges.shape for s in scans} == {(beams,)}
    poses = np.array([s.pose for s in scans])
    assert np.all(np.isfinite(poses)) and np.all(np.isfinite([s.odom for s in scans]))
    stamps = np.array([s.timestamp for s in scans])
    # Nearly in time order: the corrected intel log has 4 small (< 1 s) steps back.
    assert np.mean(np.diff(stamps) >= 0) > 0.99 and stamps[-1] - stamps[0] > 600
    # Consecutive corrected poses of an indoor robot are at most ~1.5 m apart (no garbage jumps).
    assert np.hypot(*np.diff(poses[:, :2], axis=0).T).max() < 2.0
    ranges = np.concatenate([s.ranges for s in scans])
    assert ranges.dtype == np.float32 and ranges.min() > 0 and ranges.max() < 82


def test_fields_and_beam_angles(tmp_path):
    path = tmp_path / "one.log"
    path.write_text("# comment\nODOM 0 0 0 0 0 0 1 host 1\n" + FLASER_3 + "NEFF 15\n")
    (scan,) = read_carmen(path)
    assert isinstance(scan, LaserScan)
    np.testing.assert_allclose(scan.ranges, [1.0, 2.0, 81.83], rtol=1e-6)
    np.testing.assert_allclose(scan.pose, [0.5, -1.0, 0.25])
    np.testing.assert_allclose(scan.odom, [0.6, -1.1, 0.3])
    assert scan.timestamp == 12.5 and scan.fov == math.pi
    np.testing.assert_allclose(scan.beam_angles(), [0.25 - math.pi / 2, 0.25, 0.25 + math.pi / 2])


def test_plain_and_gzip_agree_and_max_scans(shared, tmp_path):
    with gzip.open(shared / "logs" / "intel-corrected.log.gz", "rt") as fh:
        head = "".join(next(fh) for _ in range(400))
    plain = tmp_path / "head.log"
    plain.write_text(head)
    scans = read_carmen(plain)
    gz = read_carmen(shared / "logs" / "intel-corrected.log.gz", max_scans=len(scans))
    assert len(scans) > 5
    for s, g in zip(scans, gz, strict=True):
        np.testing.assert_array_equal(s.ranges, g.ranges)
        np.testing.assert_array_equal(s.pose, g.pose)
    assert len(read_carmen(plain, max_scans=3)) == 3


@pytest.mark.parametrize(
    ("line", "problem"),
    [
        ("FLASER\n", "without a beam count"),
        ("FLASER x 1 2\n", "not an integer"),
        ("FLASER 0 0 0 0 0 0 0 0 0 h 0\n", "outside"),
        (FLASER_3.replace("81.83 ", ""), "needs 14 fields, got 13"),
        (FLASER_3.replace("2.0", "two"), "non-numeric"),
        (FLASER_3.replace("2.0", "nan"), "not finite"),
        (FLASER_3.replace("2.0", "-2.0"), "negative range"),
    ],
)
def test_malformed_line_names_file_and_line(tmp_path, line, problem):
    path = tmp_path / "bad.log"
    path.write_text("PARAM a b c 0\n" + FLASER_3 + line)
    with pytest.raises(LogFormatError, match=rf"^{path}:3: .*{problem}"):
        read_carmen(path)


def test_binary_and_truncated_gzip(tmp_path):
    path = tmp_path / "bin.log"
    path.write_bytes(b"FLASER 1 \xff\xfe 0 0 0 0 0 0 0 h 0\n")
    with pytest.raises(LogFormatError, match=r":1: FLASER line is not ASCII"):
        read_carmen(path)
    gz = tmp_path / "cut.log.gz"
    gz.write_bytes(gzip.compress((FLASER_3 * 2000).encode())[:300])
    with pytest.raises(LogFormatError, match="corrupt gzip"):
        read_carmen(gz)


_token = st.one_of(
    st.sampled_from(["FLASER", "ODOM", "nan", "inf", "-1", "0", "3", "1e400", "host", ""]),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-5, 400).map(str),
    st.text(max_size=6),
)
_line = st.one_of(
    st.lists(_token, max_size=20).map(" ".join),
    st.integers(0, len(FLASER_3)).map(lambda n: FLASER_3[:n]),
    st.binary(max_size=40).map(lambda b: b.decode("latin-1")),
)


@settings(max_examples=150, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(lines=st.lists(_line, max_size=8), gzipped=st.booleans())
def test_fuzz_only_log_format_error(tmp_path, lines, gzipped):
    data = "\n".join([FLASER_3.strip(), *lines]).encode("utf-8")
    path = tmp_path / ("f.log.gz" if gzipped else "f.log")
    path.write_bytes(gzip.compress(data) if gzipped else data)
    try:
        scans = read_carmen(path)
    except LogFormatError as exc:
        assert str(exc).startswith(f"{path}:") and "\n" not in str(exc)
    else:
        assert scans and all(np.all(np.isfinite(s.pose)) for s in scans)
