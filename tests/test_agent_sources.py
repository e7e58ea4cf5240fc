"""Sources: spec parsing, frames, the version gate, CARMEN replay and map-file following."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.ndimage import maximum_filter

from agent.evaluate import link_error, true_matrix
from agent.sources import (
    CarmenSource,
    ChangeGate,
    MapFileSource,
    RosbagGridSource,
    RosTopicSource,
    SourceSpec,
    compress_gaps,
    epoch_due,
    frame_for_robot,
    load_scans,
    make_source,
    parse_frame,
    parse_source,
)
from pgvd.grid import Grid
from pgvd.io import read_map
from protocol.ros2.occupancy import RosMap

INTEL = Path(__file__).resolve().parents[1] / "agent" / "data" / "intel-corrected.log.gz"


def test_parse_source() -> None:
    spec = parse_source("carmen:logs/x.log.gz@0.25-0.5")
    assert (spec.kind, spec.path, spec.segment) == ("carmen", Path("logs/x.log.gz"), (0.25, 0.5))
    assert parse_source("carmen:a.log").segment == (0.0, 1.0)
    assert parse_source("map:m.yaml").kind == "map"
    for bad in ("nope:x", "map:", "carmen:x@0.5-0.2", "carmen:x@0-1.5"):
        with pytest.raises(ValueError):
            parse_source(bad)


def test_a_malformed_segment_is_named_not_taken_for_part_of_the_file_name(
    tmp_path: Path,
) -> None:
    # "carmen:LOG@0.5" once read as a log called "LOG@0.5" and failed as a missing file
    for bad in ("0.5", "abc", "1..2-3", "0.2-", "-0.6"):
        with pytest.raises(ValueError, match=f"must be @FROM-TO, .* got @{re.escape(bad)}$"):
            parse_source(f"carmen:{INTEL}@{bad}")
    with pytest.raises(ValueError, match=re.escape("needs a log before @0.1-0.2")):
        parse_source("carmen:@0.1-0.2")
    # a log whose own name holds an "@" is still read whole
    odd = tmp_path / "run@home.log"
    odd.write_text("")
    assert parse_source(f"carmen:{odd}") == SourceSpec("carmen", odd)


def test_parse_ros_sources() -> None:
    assert parse_source("ros2:/robot1/map") == SourceSpec("ros2", None, topic="/robot1/map")
    bag = SourceSpec("rosbag", Path("b/run1"), topic="/scan")
    assert parse_source("rosbag:b/run1:/scan") == bag
    assert parse_source("rosbag:/data/a:b/run1").path == Path("/data/a:b/run1")
    assert parse_source("rosbag:run1").topic is None
    for bad in ("ros2:", "ros2:robot1/map", "ros2:/robot1//map", "rosbag:", "rosbag:b:/2scan"):
        with pytest.raises(ValueError):
            parse_source(bad)


@given(st.text(max_size=40))
def test_any_source_text_parses_or_is_refused_in_one_line(text: str) -> None:
    try:
        spec = parse_source(text)
    except ValueError as exc:
        assert "\n" not in str(exc)
    else:
        assert spec.kind in ("carmen", "rosbag", "map", "ros2")


def test_ros_topic_source_takes_each_new_map_once() -> None:
    grids = [Grid(np.full((4, 4), v, np.float32), 0.05) for v in (1.0, 1.0, -1.0)]
    queue = [RosMap(g, "map", i) for i, g in enumerate(grids)]
    src = make_source(parse_source("ros2:/robot1/map"), "r1", None, 0.1, 1.0)
    assert isinstance(src, RosTopicSource) and not src.step(0.0)  # not attached yet
    src.attach(lambda: queue.pop(0) if queue else None)
    assert src.step(0.0) and src.grid() is grids[0]
    assert not src.step(0.1)  # the same map sent again is no news
    assert src.step(0.2) and src.grid() is grids[2]
    assert not src.step(0.3)
    assert src.describe()["received"] == 3 and src.describe()["topic"] == "/robot1/map"


def test_a_map_in_another_frame_than_the_robots_map_frame_is_said_once(caplog) -> None:
    # slam_toolbox left at its default map_frame "map": the agent places r1/map, so the
    # robot's own TF tree would hang apart from the merged frame, silently
    grids = [Grid(np.full((4, 4), v, np.float32), 0.05) for v in (1.0, -1.0, 2.0, 3.0)]
    queue = [RosMap(g, f, 0) for g, f in zip(grids, ("map", "map", "r1/map", "odom"), strict=True)]
    src = make_source(parse_source("ros2:/r1/map"), "r1", None, 0.1, 1.0)
    src.attach(lambda: queue.pop(0) if queue else None)
    with caplog.at_level("WARNING", logger="pgvd.agent"):
        while src.step(0.0):
            pass
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2, said
    assert "frame 'map'" in said[0] and "as 'r1/map'" in said[0] and "map_frame" in said[0]
    assert "frame 'odom'" in said[1]


def test_a_rosbag_replays_like_the_carmen_log_it_was_written_from(tmp_path: Path) -> None:
    """The same scans through a rosbag2 (LaserScan + TF) and through the log: the same map."""
    pytest.importorskip("rosbags")
    import bags

    from pgvd.carmen import read_carmen
    from pgvd.integrate import select_segment

    bags.write_scan_bag(tmp_path / "bag", select_segment(read_carmen(INTEL), (0.0, 0.05)))
    frame = (1.0, -2.0, 0.3)
    log = CarmenSource(parse_source(f"carmen:{INTEL}@0.0-0.05"), frame, 0.1, 1e9)
    bag = make_source(parse_source(f"rosbag:{tmp_path / 'bag'}"), "r1", frame, 0.1, 1e9)
    assert isinstance(bag, CarmenSource) and bag.kind == "rosbag"
    for src in (log, bag):
        src.step(0.0)
        assert src.step(1.0) and src.done
    a, b = log.grid(), bag.grid()
    assert a.shape == b.shape and a.origin == pytest.approx(b.origin)
    assert np.mean(np.sign(a.logodds) == np.sign(b.logodds)) > 0.99


def test_a_rosbag_of_a_growing_slam_map_replays_its_maps_in_bag_time(tmp_path: Path) -> None:
    """slam_toolbox's /map recorded as it grew (the Intel map's lower-left corner, then more),
    and last a map a live topic would refuse: each map is taken when its bag time comes."""
    pytest.importorskip("rosbags")
    import bags
    import ros2_peer

    grid = read_map(Path(__file__).resolve().parents[1] / "examples" / "intel_a.yaml")
    p = grid.probability()
    cells = np.where(p > 0.65, 100, np.where(p < 0.196, 0, -1)).astype(np.int8)
    ros = np.flipud(cells)  # row 0 is the lowest row: a crop [:h, :w] keeps the origin
    h, w = ros.shape
    sizes = [(h // 2, w // 3), (h * 3 // 4, w * 2 // 3), (h, w)]
    recorded = [
        (
            100.0 + 10 * i,
            ros2_peer.grid_cdr(ros[:hh, :ww].ravel(), ww, hh, grid.resolution, grid.origin[:2]),
        )
        for i, (hh, ww) in enumerate(sizes)
    ]
    bad = ros2_peer.grid_cdr(ros.ravel(), w, h, 0.0, grid.origin[:2])  # resolution 0
    bags.write_grid_bag(tmp_path / "bag", [*recorded, (130.0, bad)])

    spec = parse_source(f"rosbag:{tmp_path / 'bag'}:/map")
    src = make_source(spec, "r1", None, 0.1, 1.0)
    assert isinstance(src, RosbagGridSource) and src.kind == "rosbag"
    assert src.step(0.0) and src.grid().shape == sizes[0]
    assert not src.step(9.0)  # the next map is 10 s later in the bag
    assert src.step(10.0) and src.grid().shape == sizes[1]
    assert src.step(20.0) and not src.done, src.describe()
    got = src.grid()
    assert got.shape == (h, w) and got.origin[:2] == pytest.approx(grid.origin[:2])
    np.testing.assert_array_equal(got.probability() > 0.5, cells == 100)
    np.testing.assert_array_equal(got.probability() < 0.5, cells == 0)
    assert src.step(30.0) and src.done  # refused; the map before it is the final one
    assert src.grid() is got
    status = src.describe()
    assert status["progress"] == [4, 4] and status["refused"] == 1
    assert status["last_error"].startswith("resolution:")
    assert src.resume_state() == {"cursor": 4}

    # A restart resumes after the maps already taken, on the replay clock of the next one.
    resume = type("Stored", (), {"grid": got, "extra": {"cursor": 1}})()
    again = make_source(spec, "r1", None, 0.1, 1.0, resume)
    assert again.step(50.0) and again.grid().shape == sizes[1]
    assert not again.step(59.0) and again.step(60.0) and again.grid().shape == (h, w)


def test_a_rosbag_topic_that_holds_no_maps_gets_one_line(tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    import bags

    from pgvd.rosbag import BagFormatError, read_rosbag_grids

    bags.write_grid_bag(tmp_path / "bag", [])
    with pytest.raises(ValueError, match="no map recorded on /map"):
        make_source(parse_source(f"rosbag:{tmp_path / 'bag'}:/map"), "r1", None, 0.1, 1.0)
    with pytest.raises(BagFormatError, match=r"no OccupancyGrid topic /scan \(has: \['/map'\]\)"):
        read_rosbag_grids(tmp_path / "bag", "/scan")


def test_frames() -> None:
    assert frame_for_robot("r1") == frame_for_robot("r1") != frame_for_robot("r2")
    assert parse_frame("1,-2,90") == pytest.approx((1.0, -2.0, np.pi / 2))
    with pytest.raises(ValueError):
        parse_frame("1,2")


def test_change_gate() -> None:
    lo = np.zeros((10, 10), np.float32)
    gate = ChangeGate(min_fraction=0.1, min_interval=1.0)
    lo[:5] = -1.0
    assert gate.due(Grid(lo.copy()), now=10.0)
    lo[5, 0] = 1.0  # 1 of 51 known cells: too small a change
    assert not gate.due(Grid(lo.copy()), now=20.0)
    assert gate.due(Grid(lo.copy()), now=20.0, final=True)  # the final map always goes out
    lo[6:] = 1.0
    assert not gate.due(Grid(lo.copy()), now=20.5)  # big change, but too soon
    assert gate.due(Grid(lo.copy()), now=21.5)
    assert not gate.due(Grid(lo.copy()), now=30.0, final=True)  # nothing changed


def _replay(
    frame: tuple[float, float, float], spec: str = f"carmen:{INTEL}@0.0-0.1", **kw: object
) -> CarmenSource:
    src = CarmenSource(parse_source(spec), frame, 0.1, 1e9, **kw)
    src.step(0.0)
    src.step(1.0)
    return src


@pytest.mark.parametrize(
    "run", [f"carmen:{INTEL}@0.0-0.1", "sim:{shared}/maps/intel/intel.yaml@0.0-0.5"]
)
def test_replay_in_own_frame_reports_the_truth(request, run: str) -> None:
    if "{shared}" in run:
        run = run.format(shared=request.getfixturevalue("shared"))
    a = _replay((0.0, 0.0, 0.0), run)
    b = _replay((4.0, -3.0, 1.0), run)
    assert a.done and b.done and a.grid().logodds.any()
    truth = true_matrix(a.describe()["world_to_pixel"], b.describe()["world_to_pixel"])
    # Warp B's walls into A with the reported truth: they land on A's walls.
    gb, ga = b.grid(), a.grid()
    ys, xs = np.nonzero(gb.logodds > 2.0)
    pts = truth @ np.vstack([xs, ys, np.ones_like(xs)])
    walls = maximum_filter(ga.logodds > 0, size=3)  # one cell of rasterisation slack
    assert walls[np.rint(pts[1]).astype(int), np.rint(pts[0]).astype(int)].mean() > 0.97
    assert link_error(truth, truth, gb.shape) == (0.0, 0.0)


def test_a_sim_run_is_one_drive_that_every_robot_splits_alike(shared: Path) -> None:
    spec = parse_source(f"sim:{shared}/maps/intel/intel.yaml@0.2-0.6")
    assert (spec.kind, spec.segment) == ("sim", (0.2, 0.6))
    whole = load_scans(SourceSpec("sim", spec.path))
    # the same tour and noise on every robot: segments of it overlap as a log's do
    again = load_scans(SourceSpec("sim", spec.path))
    np.testing.assert_array_equal(whole[-1].ranges, again[-1].ranges)
    src = make_source(spec, "r1", None, 0.1, 1e9)
    assert len(src.scans) == int(0.6 * len(whole)) - int(0.2 * len(whole))
    with pytest.raises(ValueError, match=re.escape("needs a map before @0.1-0.2")):
        parse_source("sim:@0.1-0.2")


def test_gaps_in_the_timestamps_cost_at_most_a_second_of_replay() -> None:
    stamps = np.array([5.0, 6.0, 10_006.0, 10_007.0, 10_006.5])
    np.testing.assert_allclose(
        compress_gaps(stamps, speed=50.0), [5.0, 6.0, 56.0, 57.0, 56.5]
    )  # 10,000 s cut to the 50 s one wall second replays; steps back kept
    np.testing.assert_array_equal(compress_gaps(stamps, np.inf), stamps)
    assert compress_gaps(np.array([]), 10.0).size == 0


def test_carmen_replay_follows_the_clock_and_resumes() -> None:
    spec = parse_source(f"carmen:{INTEL}@0.0-0.1")
    src = CarmenSource(spec, (0.0, 0.0, 0.0), 0.1, speed=100.0)
    src.step(0.0)
    span = src.scans[-1].timestamp - src.scans[0].timestamp
    src.step(span / 100.0 / 2)
    half = src.cursor
    assert 0 < half < len(src.scans)
    again = CarmenSource(spec, (0.0, 0.0, 0.0), 0.1, 100.0, resume=(src.logodds, half))
    assert again.cursor == half
    np.testing.assert_array_equal(again.logodds, src.logodds)
    again.step(0.0)
    assert again.cursor == half + 1  # the next scan is due at once, not the first one
    again.step(1e6)
    full = _replay((0.0, 0.0, 0.0))
    np.testing.assert_allclose(again.logodds, full.logodds, atol=1e-5)


def test_map_file_source_waits_for_stable_files_and_survives_bad_ones(
    shared: Path, tmp_path: Path
) -> None:
    src_dir = shared / "maps" / "intel_split_gt"
    yaml = tmp_path / "map.yaml"
    text = (src_dir / "intel_partA.yaml").read_text().replace("intel_partA.pgm", "map.pgm")
    source = MapFileSource(parse_source(f"map:{yaml}"), poll=0.0)
    assert not source.step(0.0)  # nothing there yet
    yaml.write_text(text)
    (tmp_path / "map.pgm").write_bytes(b"P5\n10 10\n255\n")  # half-written image
    assert not source.step(1.0)  # first sight: wait one poll
    assert not source.step(2.0) and source.errors == 1  # parse fails: counted, retried
    shutil.copy(src_dir / "intel_partA.pgm", tmp_path / "map.pgm")
    assert not source.step(3.0)
    assert source.step(4.0)
    assert source.grid().shape[0] > 100 and not source.step(5.0)


def _follow(yaml: Path) -> MapFileSource:
    """A map source that has polled ``yaml`` twice: long enough to read a stable file."""
    source = MapFileSource(parse_source(f"map:{yaml}"), poll=0.0)
    source.step(0.0)
    source.step(1.0)
    return source


@pytest.mark.parametrize("case", ["byte-order mark", "moved absolute image"])
def test_map_file_source_reads_what_read_map_reads(shared: Path, tmp_path: Path, case) -> None:
    """A YAML with a BOM, or naming an absolute image path that moved beside it (a map
    copied from another machine): read_map reads both, so the source must too."""
    src_dir = shared / "maps" / "intel_split_gt"
    shutil.copy(src_dir / "intel_partA.pgm", tmp_path / "intel_partA.pgm")
    text = (src_dir / "intel_partA.yaml").read_text()
    yaml = tmp_path / "map.yaml"
    if case == "byte-order mark":
        yaml.write_bytes(b"\xef\xbb\xbf" + text.encode())
    else:
        yaml.write_text(text.replace("intel_partA.pgm", "/gone/robot1/maps/intel_partA.pgm"))
    expected = read_map(yaml)
    source = _follow(yaml)
    assert source.errors == 0 and source.last_error is None
    np.testing.assert_array_equal(source.grid().logodds, expected.logodds)


def test_map_file_source_counts_a_yaml_whose_image_is_missing(shared: Path, tmp_path: Path) -> None:
    yaml = tmp_path / "map.yaml"
    yaml.write_text((shared / "maps/intel_split_gt/intel_partA.yaml").read_text())
    source = _follow(yaml)
    assert source.errors == 1 and "intel_partA.pgm: no such file" in source.last_error
    assert source.describe()["read_errors"] == 1
    source.step(2.0)  # still missing: retried and counted again
    assert source.errors == 2
    shutil.copy(shared / "maps/intel_split_gt/intel_partA.pgm", tmp_path)
    assert not source.step(3.0)  # the image appeared: wait one poll, then read it
    assert source.step(4.0) and source.errors == 2
    assert source.last_error is None  # read: no error now (read_errors keeps the count)


def test_epoch_due_on_big_change_or_moved_canvas() -> None:
    lo = np.zeros((10, 10), np.float32)
    lo[:5] = -1.0
    base = Grid(lo.copy(), 0.1)
    assert epoch_due(None, base, 0.15)
    lo[5, :5] = 1.0  # 5 of 55 known cells changed: < 15 %
    assert not epoch_due(base, Grid(lo.copy(), 0.1), 0.15)
    lo[6:8] = 1.0  # 25 of 75 changed
    assert epoch_due(base, Grid(lo.copy(), 0.1), 0.15)
    assert epoch_due(base, Grid(base.logodds, 0.1, (1.0, 0.0, 0.0)), 0.15)  # canvas moved
