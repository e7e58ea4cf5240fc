"""pgvd.rosbag: a bag written from the intel log gives back its scans, poses and map."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

pytest.importorskip("rosbags")
from bags import write_scan_bag

from pgvd.carmen import read_carmen
from pgvd.integrate import frame_for, integrate
from pgvd.rosbag import BagFormatError, read_rosbag_scans, scan_from_ros


@pytest.fixture(scope="module")
def intel(shared):
    return read_carmen(shared / "logs" / "intel-corrected.log.gz", max_scans=120)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_bag_scans_give_back_the_logs_poses_and_map(tmp_path, intel, storage) -> None:
    write_scan_bag(tmp_path / "bag", intel, storage)
    scans = read_rosbag_scans(tmp_path / "bag")
    assert len(scans) == len(intel)
    for got, want in zip(scans, intel, strict=True):
        np.testing.assert_allclose(got.pose[:2], want.pose[:2], atol=1e-6)
        assert np.cos(got.pose[2] - want.pose[2]) == pytest.approx(1.0, abs=1e-9)
        # The log's 81.83 m "no return" is above the bag's range_max: ROS says no return.
        no_return = want.ranges > 81.0
        assert np.all(np.isinf(got.ranges[no_return]))
        np.testing.assert_array_equal(got.ranges[~no_return], want.ranges[~no_return])
    frame = frame_for(intel, 0.1)
    ours, theirs = integrate(scans, frame), integrate(intel, frame)
    # Same cells hit and passed: the maps agree on every cell's class.
    assert np.mean(np.sign(ours.logodds) == np.sign(theirs.logodds)) > 0.999


def test_odometry_stands_in_for_tf_when_the_bag_has_no_tf(tmp_path, intel) -> None:
    write_scan_bag(tmp_path / "bag", intel, odometry=True)
    scans = read_rosbag_scans(tmp_path / "bag")
    assert len(scans) == len(intel)
    for got, want in zip(scans, intel, strict=True):
        np.testing.assert_allclose(got.pose[:2], want.pose[:2], atol=1e-6)
        assert np.cos(got.pose[2] - want.pose[2]) == pytest.approx(1.0, abs=1e-9)


def test_a_bag_without_tf_to_the_laser_is_refused(tmp_path, intel) -> None:
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    write_scan_bag(tmp_path / "full", intel[:5])
    with Writer(tmp_path / "scans_only", version=9) as writer:
        from rosbags.rosbag2 import Reader

        with Reader(tmp_path / "full") as reader:
            conns = [c for c in reader.connections if c.topic == "/scan"]
            out = writer.add_connection("/scan", conns[0].msgtype, typestore=ts)
            for _, t, raw in reader.messages(connections=conns):
                writer.write(out, t, raw)
    with pytest.raises(BagFormatError, match="reached by TF or odometry"):
        read_rosbag_scans(tmp_path / "scans_only")


def test_bad_bags_and_topics_get_one_clear_error(tmp_path, intel) -> None:
    with pytest.raises(BagFormatError, match="not a readable rosbag2"):
        read_rosbag_scans(tmp_path / "missing")
    write_scan_bag(tmp_path / "bag", intel[:5])
    with pytest.raises(BagFormatError, match="no LaserScan topic /front_scan"):
        read_rosbag_scans(tmp_path / "bag", "/front_scan")


@settings(max_examples=80)
@given(
    st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), max_size=40),
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(0.0, 1.0),
    st.floats(0.1, 100.0),
)
@example([0.0, 0.0, 0.0], 0.0, 8.98846567431158e307, 0.0, 1.0)  # finite, but the fov overflows
def test_any_scan_message_becomes_a_castable_scan_or_one_error(
    ranges, angle_min, increment, range_min, range_max
) -> None:
    from bags import T

    msg = T["sensor_msgs/msg/LaserScan"](
        header=T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="laser"
        ),
        angle_min=angle_min,
        angle_max=0.0,
        angle_increment=increment,
        time_increment=0.0,
        scan_time=0.0,
        range_min=range_min,
        range_max=range_max,
        ranges=np.asarray(ranges, dtype=np.float32),
        intensities=np.zeros(0, dtype=np.float32),
    )
    try:
        scan = scan_from_ros(msg, (0.0, 0.0, 0.0), 1.0)
    except BagFormatError as exc:
        assert "no beams or a non-finite angle" in str(exc)
        return
    usable = scan.ranges[np.isfinite(scan.ranges)]
    assert np.all((usable >= range_min) & (usable <= range_max))
    assert np.all(np.isfinite(scan.beam_angles()))
