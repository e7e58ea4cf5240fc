"""``pgvd merge`` through the real console entry (``python -m agent.cli``), on real maps."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pgvd.grid import Grid, matrix_to_pose, relative_matrix
from pgvd.io import read_map, write_map
from pgvd.transform import resample

ROOT = Path(__file__).resolve().parents[1]
CONTRACT_KEYS = {
    "accepted",
    "matrix",
    "rotation_deg",
    "translation_px",
    "covariance",
    "score",
    "timings_ms",
}


def pgvd_merge(*args: str | Path, **kwargs) -> subprocess.CompletedProcess[str]:
    kwargs.setdefault("capture_output", True)
    return subprocess.run(
        [sys.executable, "-m", "agent.cli", "merge", *map(str, args)],
        cwd=ROOT,
        text=True,
        timeout=120,
        **kwargs,
    )


def _yaml_copy(tmp: Path, name: str, src: Path, drop: str = "", **replace: str) -> Path:
    """A copy of a real map_server YAML pointing at the real image, with edits."""
    lines = []
    for line in src.read_text().splitlines():
        key = line.split(":", 1)[0]
        if key == drop:
            continue
        if key == "image":
            line = f"image: {src.parent / line.split(':', 1)[1].strip()}"
        if key in replace:
            line = f"{key}: {replace[key]}"
        lines.append(line)
    out = tmp / f"{name}.yaml"
    out.write_text("\n".join(lines) + "\n")
    return out


def _bad_inputs(tmp: Path, maps: Path) -> list[tuple[str, list[str | Path], str]]:
    intel = maps / "intel/intel.yaml"
    p = read_map(intel).probability()
    nan = p.copy()
    nan[400, 400] = np.nan
    np.save(tmp / "nan.npy", nan)
    np.save(tmp / "empty.npy", np.zeros((0, 888), np.float32))
    no_walls = np.where(p > 0.65, 0.1, p)
    np.save(tmp / "no_walls.npy", no_walls)
    tiny = np.full((10, 10), 0.1)
    tiny[:, 5] = 0.9
    np.save(tmp / "tiny.npy", tiny)
    (tmp / "dir.yaml").mkdir()
    (tmp / "dir.png").mkdir()
    (tmp / "nomap").mkdir()
    return [
        ("missing file", [maps / "nope.yaml", intel], "no such file"),
        ("unreadable file", [intel, tmp / "dir.yaml"], "is a directory"),
        ("a directory with no map suffix", [tmp / "nomap", intel], "is a directory, not a map"),
        ("missing key", [_yaml_copy(tmp, "k", intel, drop="resolution"), intel], "missing key"),
        ("zero resolution", [intel, _yaml_copy(tmp, "r0", intel, resolution="0")], "resolution"),
        ("negative resolution", [_yaml_copy(tmp, "rn", intel, resolution="-0.05"), intel], "-0.05"),
        # B shrunk to A's cells of a gigametre once hung the max filter of the resampling
        ("absurd resolution", [_yaml_copy(tmp, "rb", intel, resolution="1e9"), intel], "0.001-1 m"),
        # and a subnormal one overflowed B's resampled size
        ("subnormal resolution", [intel, _yaml_copy(tmp, "rs", intel, resolution="1e-320")], "1 m"),
        ("empty map", [intel, tmp / "empty.npy"], "empty map"),
        ("no occupied cells", [tmp / "no_walls.npy", intel], "no occupied cells"),
        ("over the size limit", [intel, intel, "--max-cells", "500000"], "exceeds the limit"),
        ("NaN", [intel, tmp / "nan.npy"], "NaN"),
        ("bad -o suffix", [intel, intel, "-o", tmp / "fused.png"], ".yaml, .yml or .npy"),
        # refused before the merge runs: nothing on stdout
        ("plot into a directory", [intel, intel, "--plot", tmp / "dir.png"], "is a directory"),
        ("-o under a file", [intel, intel, "-o", tmp / "nan.npy" / "f.yaml"], "is not a directory"),
        ("--despeckle of 3 maps", [intel, intel, intel, "--despeckle"], "two maps, not more"),
        ("--prior of 3 maps", [intel, intel, intel, "--prior", "0,0,0"], "two maps, not more"),
        ("--prior not a pose", [intel, intel, "--prior", "1,2"], "a pose is x,y,yaw"),
        ("--prior not finite", [intel, intel, "--prior", "1e999,0,0"], "must be finite"),
        ("--prior beyond any map", [intel, intel, "--prior=-1e307,0,0"], "1e+06 m or more away"),
        # the pose's text is quoted: a newline in it stays on the error's one line
        ("--prior with a newline", [intel, intel, "--prior", "1,2\n3"], "got '1,2\\n3'"),
        ("--plot not a PNG", [intel, intel, "--plot", tmp / "m.jpg"], "must end in .png"),
        ("bare image, no cell size", [ROOT / "examples/intel_a.pgm", intel], "--resolution M"),
        ("zero --resolution", [intel, intel, "--resolution", "0"], "--resolution 0: "),
        (
            "a nanometre cell",
            [ROOT / "examples/intel_a.pgm", ROOT / "examples/intel_b.pgm", "--resolution", "1e-9"],
            "--resolution 1e-09: a cell size of 1e-09 m is outside 0.001-1 m",
        ),
        # a map 0.5 m across has no GVD to match
        ("a map too small", [tmp / "tiny.npy", intel], "too small to merge at 0.05 m/cell"),
        # B resampled to A's millimetre cells would hold 2e9 cells: refused before it is built
        (
            "B resampled past --max-cells",
            [ROOT / "examples/intel_a.pgm", intel, "--resolution", "0.001"],
            "over --max-cells",
        ),
    ]


def test_bad_input_exits_2_with_one_line(tmp_path: Path, shared: Path) -> None:
    for name, args, why in _bad_inputs(tmp_path, shared / "maps"):
        proc = pgvd_merge(*args)
        assert proc.returncode == 2, (name, proc.stderr)
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and why in lines[0], (name, proc.stderr)
        assert lines[0].startswith("pgvd merge: error: ") and "Traceback" not in proc.stderr
        assert proc.stdout == ""


def test_bare_images_merge_with_the_cell_size_given() -> None:
    """The bundled pair as bare PGMs, as map collections ship maps: the pose in pixels is
    the one of their YAMLs."""
    examples = ROOT / "examples"
    bare = pgvd_merge(
        examples / "intel_a.pgm", examples / "intel_b.pgm", "--resolution", "0.05", "--json"
    )
    assert bare.returncode == 0, bare.stderr
    with_yaml = pgvd_merge(examples / "intel_a.yaml", examples / "intel_b.yaml", "--json")
    got, want = json.loads(bare.stdout), json.loads(with_yaml.stdout)
    assert got["accepted"] and got["matrix"] == want["matrix"]


def test_a_resolution_no_map_uses_is_said_once() -> None:
    examples = ROOT / "examples"
    proc = pgvd_merge(
        examples / "intel_a.yaml", examples / "intel_b.yaml", "--resolution", "0.1", "--json"
    )
    assert proc.returncode == 0 and json.loads(proc.stdout)["accepted"]
    assert proc.stderr == (
        "pgvd merge: note: --resolution 0.1 is not used: each map's YAML gives its own cell size\n"
    )


def test_the_map_frame_is_where_the_true_transform_puts_b_in_the_world() -> None:
    """The bundled pair, each map in a frame of its own turned by -69 deg: B's map frame in
    A's, from B's cells placed by the true pixel matrix through each map's own metric frame
    (pgvd.pixel_to_world), lies within 3 sigma of what pgvd merge reports."""
    from pgvd.grid import pixel_to_world

    examples = ROOT / "examples"
    a, b = read_map(examples / "intel_a.yaml"), read_map(examples / "intel_b.yaml")
    truth = np.asarray(json.loads((examples / "truth.json").read_text())["matrix"])
    cells = np.array([[0.0, 0.0], [500.0, 0.0], [0.0, 400.0]])
    in_b = pixel_to_world(b, cells)
    in_a = pixel_to_world(a, (truth @ np.column_stack([cells, np.ones(3)]).T)[:2].T)
    yaw = np.arctan2(*(in_a[1] - in_a[0])[::-1]) - np.arctan2(*(in_b[1] - in_b[0])[::-1])
    c, s_ = np.cos(yaw), np.sin(yaw)
    x, y = in_a[0] - np.array([[c, -s_], [s_, c]]) @ in_b[0]
    proc = pgvd_merge(examples / "intel_a.yaml", examples / "intel_b.yaml", "--json")
    frame = json.loads(proc.stdout)["map_frame"]
    err = np.array([frame["x"] - x, frame["y"] - y, np.angle(np.exp(1j * (frame["yaw"] - yaw)))])
    sd = np.sqrt(np.diag(frame["covariance"]))
    assert abs(np.degrees(frame["yaw"])) > 60  # far from the identity: a sign would show
    assert np.all(np.abs(err) < 3 * sd), (err, sd)


def test_outputs_that_would_overwrite_an_input_map_are_refused(tmp_path: Path) -> None:
    # `-o intel_a.yaml` once replaced the robot's own map by the fused one, exit 0
    for name in ("intel_a.yaml", "intel_a.pgm", "intel_b.yaml", "intel_b.pgm"):
        (tmp_path / name).write_bytes((ROOT / "examples" / name).read_bytes())
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    a, b = tmp_path / "intel_a.yaml", tmp_path / "intel_b.yaml"
    for extra, hit in (
        (["-o", a], "-o would overwrite the input map file"),
        # intel_a.yml is new, but the .pgm written beside it is A's image
        (["-o", tmp_path / "intel_a.yml"], f"-o would overwrite the input map file {a.parent}"),
        (["-o", tmp_path / "sub" / ".." / "intel_b.yaml"], "intel_b.yaml"),
    ):
        proc = pgvd_merge(a, b, *extra)
        assert proc.returncode == 2 and hit in proc.stderr, (extra, proc.stderr)
        assert proc.stdout == ""
    bare = tmp_path / "intel_a.pgm"
    proc = pgvd_merge(bare, tmp_path / "intel_b.pgm", "--resolution", "0.05", "-o", a)
    assert proc.returncode == 2 and "intel_a.pgm" in proc.stderr
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_a_missing_map_b_is_named_alone() -> None:
    """C (more maps) is optional: only B is named as missing."""
    proc = pgvd_merge(ROOT / "examples" / "intel_a.yaml")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1].endswith("the following arguments are required: B")


@pytest.mark.slow
def test_accepted_pair_json_fused_map_and_plot(tmp_path: Path, shared: Path) -> None:
    d = shared / "maps/intel_split_gt"
    fused, plot = tmp_path / "fused.yaml", tmp_path / "merge.png"
    proc = pgvd_merge(
        d / "intel_partA.yaml", d / "intel_partB.yaml", "--json", "-o", fused, "--plot", plot
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""  # no progress with --json unless -v
    doc = json.loads(proc.stdout)
    assert doc.keys() >= CONTRACT_KEYS and doc["accepted"] is True
    a, b = read_map(d / "intel_partA.yaml"), read_map(d / "intel_partB.yaml")
    truth = matrix_to_pose(relative_matrix(a, b))
    got = matrix_to_pose(np.array(doc["matrix"]))
    assert abs(np.degrees(got[0] - truth[0])) < 1.0
    assert np.hypot(got[1] - truth[1], got[2] - truth[2]) < 2.0
    assert doc["translation_px"] == [got[1], got[2]]
    cov = np.array(doc["covariance"])
    assert cov.shape == (3, 3) and np.all(np.linalg.eigvalsh(cov) >= 0)
    assert doc["timings_ms"]["total"] > 0
    assert "diagnostics" in doc["timings_ms"]  # the PGVD panels of the plot were painted
    # the fused map reads back, holds both halves, and keeps A's world frame
    g = read_map(fused)
    to_a = relative_matrix(g, a)
    np.testing.assert_allclose(to_a[:2, :2], np.eye(2), atol=1e-9)
    known = g.probability() != 0.5
    assert known.sum() > max((a.probability() != 0.5).sum(), (b.probability() != 0.5).sum())
    from PIL import Image

    with Image.open(plot) as im:
        assert im.mode == "RGB" and im.width > 2 * a.shape[1]


@pytest.mark.slow
def test_rejected_pair_exits_3_and_still_plots(tmp_path: Path, shared: Path) -> None:
    fused, plot = tmp_path / "fused.npy", tmp_path / "why.png"
    proc = pgvd_merge(
        shared / "maps/intel/intel.yaml",
        shared / "maps/uos_avz/avz.yaml",
        "--json",
        "-o",
        fused,
        "--plot",
        plot,
    )
    assert proc.returncode == 3, proc.stderr
    doc = json.loads(proc.stdout)  # strict JSON: NaN covariance entries are null
    assert doc.keys() >= CONTRACT_KEYS and doc["accepted"] is False and doc["reason"]
    assert plot.stat().st_size > 0 and not fused.exists()
    assert doc["map_frame"] is None  # a rejected pose places no frame


def test_without_plot_the_pgvd_images_are_not_painted(shared: Path) -> None:
    """Only ``--plot`` draws MergeResult.diagnostics: without it the merge skips them."""
    d = shared / "maps/intel_split_gt"
    proc = pgvd_merge(d / "intel_partA.yaml", d / "intel_partB.yaml", "--json")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["accepted"] is True and "covariance" in doc["timings_ms"]
    assert "diagnostics" not in doc["timings_ms"]
    # the two halves were rendered in one world frame: B's map frame is A's
    frame = doc["map_frame"]
    assert abs(frame["x"]) < 0.05 and abs(frame["y"]) < 0.05 and abs(frame["yaw"]) < 0.005
    # and the truth (0, 0, 0) lies inside the 99 % ellipsoid of its covariance
    e = np.array([frame["x"], frame["y"], frame["yaw"]])
    assert e @ np.linalg.solve(np.array(frame["covariance"]), e) < 11.34


@pytest.mark.slow
def test_resampled_b_matrix_maps_the_file_pixels(tmp_path: Path, shared: Path) -> None:
    """B stored at 0.1 m/cell is resampled to A's 0.05; the matrix maps B's file pixels."""
    d = shared / "maps/intel_split_gt"
    a, b = read_map(d / "intel_partA.yaml"), read_map(d / "intel_partB.yaml")
    coarse: Grid = resample(b, 0.1)
    write_map(tmp_path / "b_coarse.yaml", coarse)
    proc = pgvd_merge(d / "intel_partA.yaml", tmp_path / "b_coarse.yaml", "-v")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("merged: rotation")
    assert "resampling B from 0.1 to 0.05" in proc.stderr and "rotation:" in proc.stderr
    proc = pgvd_merge(d / "intel_partA.yaml", tmp_path / "b_coarse.yaml", "--json")
    doc = json.loads(proc.stdout)
    truth = relative_matrix(a, read_map(tmp_path / "b_coarse.yaml"))
    assert doc["b_scale"] == 2.0
    corners = np.array([[0, 0, 1], [300, 0, 1], [0, 300, 1], [300, 300, 1]], float).T
    err = np.array(doc["matrix"]) @ corners - truth @ corners
    assert np.abs(err[:2]).max() < 3.0  # cells of A, across B's extent
    # B's map frame, read from its own (coarser) file, is still A's
    frame = doc["map_frame"]
    assert abs(frame["x"]) < 0.1 and abs(frame["y"]) < 0.1 and abs(frame["yaw"]) < 0.01


def test_json_into_a_closed_pipe_is_quiet() -> None:
    """Defect: ``pgvd merge A B --json | head`` ended in a ``BrokenPipeError`` traceback when
    the reader was gone before the JSON was written."""
    read, write = os.pipe()
    os.close(read)
    try:
        proc = pgvd_merge(
            ROOT / "examples/intel_a.yaml",
            ROOT / "examples/intel_b.yaml",
            "--json",
            capture_output=False,
            stdout=write,
            stderr=subprocess.PIPE,
        )
    finally:
        os.close(write)
    assert proc.stderr == "" and proc.returncode == 1


def test_three_runs_merge_into_one_map_through_the_cli(shared: Path, tmp_path: Path) -> None:
    """``pgvd merge A B C``: the design's JSON, the fused map and the plot are written."""
    d = shared / "maps" / "fr079_albertB"
    files = [d / f"map{n}.yaml" for n in (312, 342, 371)]
    fused, plot = tmp_path / "merged.yaml", tmp_path / "merged.png"
    proc = pgvd_merge(*files, "-o", fused, "--plot", plot, "--json")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert [m["file"] for m in doc["maps"]] == [str(f) for f in files]
    assert {tuple(m) for m in doc["maps"]} == {
        ("file", "component", "matrix", "covariance", "map_frame")
    }
    # three gmapping runs of one log: their map frames lie within a few cm and a degree of
    # each other (bench/results/gmapping_truth.md), the anchor's is its own
    anchor = doc["maps"][0]["map_frame"]
    assert (anchor["x"], anchor["y"], anchor["yaw"]) == (0.0, 0.0, 0.0)
    for m in doc["maps"][1:]:
        frame = m["map_frame"]
        assert np.hypot(frame["x"], frame["y"]) < 0.1 and abs(frame["yaw"]) < np.radians(1.0)
        # its placement's covariance, carried to metres: centimetres and a tenth of a degree
        sd = np.sqrt(np.diag(frame["covariance"]))
        assert np.all(sd > 0) and np.all(sd < [0.1, 0.1, np.radians(0.5)]), sd
    assert [(ln["a"], ln["b"], ln["used"]) for ln in doc["links"]] == [
        (0, 1, True),
        (0, 2, True),
        (1, 2, True),
    ]
    assert {tuple(ln) for ln in doc["links"]} == {("a", "b", "accepted", "used", "matrix", "score")}
    merged = read_map(fused)
    assert merged.shape[0] >= read_map(files[0]).shape[0]
    assert plot.stat().st_size > 0


def test_maps_that_overlap_nowhere_exit_3_and_bad_input_2(shared: Path, tmp_path: Path) -> None:
    m = shared / "maps"
    small = [
        m / "intel/intel.yaml",
        m / "uos_avz/avz.yaml",
        m / "mit_stata_basement/stata_basement.yaml",
    ]
    fused = tmp_path / "none.yaml"
    proc = pgvd_merge(*small, "-o", fused)
    assert proc.returncode == 3, proc.stderr
    assert "no overlap" in proc.stdout and not fused.exists()
    proc = pgvd_merge(small[0], small[1], tmp_path / "missing.yaml")
    assert proc.returncode == 2
    assert proc.stderr.startswith("pgvd merge: error: ") and "Traceback" not in proc.stderr


def test_map_images_painted_free_are_merged_and_the_user_told(tmp_path: Path, shared: Path):
    """Two parts of intel's image, their unexplored area painted white, B in another frame."""
    from bench.data.pairs import painted_pair
    from bench.mapimages import part_pairs

    p = read_map(shared / "maps/intel/intel.yaml").probability()
    (pair,) = part_pairs("intel", p, 1, np.random.default_rng(21))
    pair = painted_pair(pair)
    write_map(tmp_path / "a.yaml", pair.a)
    write_map(tmp_path / "b.yaml", pair.b)
    proc = pgvd_merge(tmp_path / "a.yaml", tmp_path / "b.yaml", "--json", "-v")
    assert proc.returncode == 0, proc.stderr
    for name in "AB":
        assert f"pgvd merge: map {name}: no unknown cells" in proc.stderr
    err = np.array(json.loads(proc.stdout)["matrix"]) - pair.truth
    assert np.abs(err[:2, 2]).max() < 3.0 and np.abs(err[:2, :2]).max() < 0.01


def test_despeckle_says_what_it_read_as_unknown() -> None:
    ex = ROOT / "examples"
    proc = pgvd_merge(ex / "intel_a.yaml", ex / "intel_b.yaml", "--despeckle", "-v")
    assert proc.returncode == 0, proc.stderr
    said = [ln for ln in proc.stderr.splitlines() if "lone wall cells (speckle)" in ln]
    assert [ln.split(": ")[1] for ln in said] == ["map A", "map B"], proc.stderr
    plain = pgvd_merge(ex / "intel_a.yaml", ex / "intel_b.yaml", "-v")
    assert "speckle" not in plain.stderr


def test_verbose_prints_each_step_and_its_stage_so_far() -> None:
    ex = ROOT / "examples"
    proc = pgvd_merge(ex / "intel_a.yaml", ex / "intel_b.yaml", "-v")
    line = re.compile(r"pgvd merge: (\w+): ([\d.]+) ms \(([\d.]+) ms so far\)")
    steps = [m for m in map(line.fullmatch, proc.stderr.splitlines()) if m]
    assert len({m[1] for m in steps}) >= 6, proc.stderr
    added: dict[str, list[float]] = {}
    for m in steps:  # the running total is the sum of the stage's steps (each rounded)
        added.setdefault(m[1], []).append(float(m[2]))
        assert abs(sum(added[m[1]]) - float(m[3])) <= 0.05 * len(added[m[1]]) + 1e-9, m[0]
    assert any(len(v) > 1 for v in added.values())  # a stage run once per heading


def test_verbose_says_the_candidate_headings_and_which_were_searched() -> None:
    # a heading far off, or one whose sigma blurs its walls away, explains a failed merge
    ex = ROOT / "examples"
    proc = pgvd_merge(ex / "intel_a.yaml", ex / "intel_b.yaml", "-v", "--json")
    assert proc.returncode == 0, proc.stderr
    heading = r"(-?\d+\.\d) deg \(sigma (\d+\.\d\d)\)"
    (listed,) = [ln for ln in proc.stderr.splitlines() if "candidate headings (10): " in ln]
    candidates = re.findall(heading, listed)
    assert len(candidates) == 6 and all(0.0 < float(s) < 5.0 for _, s in candidates)
    searched = re.findall("searching heading " + heading, proc.stderr)
    assert searched and set(searched) <= set(candidates)
    rotation = json.loads(proc.stdout)["rotation_deg"]
    assert min(abs(float(deg) - rotation) for deg, _ in searched) < 1.0


def test_a_prior_near_b_is_confirmed_without_a_search_and_a_wrong_one_searched() -> None:
    """The bundled pair with ``--prior``: B's map frame in A's from a plain merge, off by
    0.36 m and 0.3 deg, is confirmed by the check alone (no search stage ran) at the pose the
    search finds; at the identity, 55 m and 69 deg off, the check fails and the search
    merges the pair all the same."""
    examples = ROOT / "examples"
    maps = (examples / "intel_a.yaml", examples / "intel_b.yaml")
    plain = json.loads(pgvd_merge(*maps, "--json").stdout)
    frame = plain["map_frame"]
    near = f"{frame['x'] + 0.3},{frame['y'] - 0.2},{frame['yaw'] + 0.005}"
    proc = pgvd_merge(*maps, "--json", "-v", f"--prior={near}")
    assert proc.returncode == 0, proc.stderr
    checked = json.loads(proc.stdout)
    assert "confirmed at the prior" in proc.stderr and "not confirmed" not in proc.stderr
    assert checked["reason"] == "confirmed at the prior"
    assert not {"pgvd", "gamma"} & set(checked["timings_ms"])  # no search
    assert abs(checked["rotation_deg"] - plain["rotation_deg"]) < 0.1
    assert np.hypot(*np.subtract(checked["translation_px"], plain["translation_px"])) < 1.0
    proc = pgvd_merge(*maps, "--json", "-v", "--prior=0,0,0")
    assert proc.returncode == 0, proc.stderr
    assert "not confirmed at the prior" in proc.stderr and "searching" in proc.stderr
    searched = json.loads(proc.stdout)
    assert searched["matrix"] == plain["matrix"] and "prior" in searched["timings_ms"]


def test_a_map_whose_unknown_space_is_drawn_black_gets_a_note(tmp_path: Path) -> None:
    """An image storing unknown as black (0) reads as mostly walls: the user is told so."""
    ex = ROOT / "examples"
    b = read_map(ex / "intel_b.yaml")
    p = b.probability()
    p[(p >= 0.3) & (p <= 0.65)] = 1.0
    write_map(tmp_path / "black.yaml", Grid.from_probability(p, b.resolution))
    proc = pgvd_merge(ex / "intel_a.yaml", tmp_path / "black.yaml", "--json")
    assert proc.returncode in (0, 3), proc.stderr
    notes = [ln for ln in proc.stderr.splitlines() if "known cells are walls" in ln]
    assert len(notes) == 1 and "of map B's known cells" in notes[0], proc.stderr
    share = int(notes[0].split("note: ")[1].split("%")[0])
    assert share > 50
    plain = pgvd_merge(ex / "intel_a.yaml", ex / "intel_b.yaml", "--json")
    assert plain.returncode == 0 and "known cells are walls" not in plain.stderr
    # more than two maps: the note names the file
    many = pgvd_merge(ex / "intel_a.yaml", ex / "intel_b.yaml", tmp_path / "black.yaml", "--json")
    notes = [ln for ln in many.stderr.splitlines() if "known cells are walls" in ln]
    assert len(notes) == 1 and f"of {tmp_path / 'black.yaml'}'s known cells" in notes[0]
