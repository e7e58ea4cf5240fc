"""Map I/O: map_server YAML + PGM/PNG and .npy, on the real maps and on crafted bad files."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from pgvd.grid import Grid
from pgvd.io import MapFormatError, read_map, write_map, write_png
from pgvd.map_shades import P_FREE, P_OCCUPIED, shade_to_probability
from pgvd.map_yaml import parse_map_yaml

YAML_TAIL = (
    "resolution: 0.05\norigin: [1.0, 2.0, 0.0]\nnegate: 0\n"
    "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
)


def _pgm(path: Path, pixels: np.ndarray, maxval: int = 255) -> None:
    h, w = pixels.shape
    dtype = ">u2" if maxval > 255 else np.uint8
    path.write_bytes(f"P5\n{w} {h}\n{maxval}\n".encode() + pixels.astype(dtype).tobytes())


def _png(path: Path, pixels: np.ndarray, mode: str) -> None:
    from PIL import Image

    img = Image.fromarray(pixels)  # Pillow infers L, LA, RGBA or I;16 from shape and dtype
    assert img.mode == mode
    img.save(path)


def _map(tmp_path: Path, pixels: np.ndarray, extra: str = "", name: str = "m.pgm") -> Path:
    if name.endswith(".pgm"):
        _pgm(tmp_path / name, pixels)
    y = tmp_path / "m.yaml"
    y.write_text(f"image: {name}\n{extra}{YAML_TAIL}")
    return y


# ----------------------------------------------------------------------------- real maps


@pytest.mark.parametrize(
    "rel",
    [
        "intel/intel.yaml",
        "intel_split_gt/intel_partA.yaml",
        "fr079_split_gt/fr079_partB.yaml",
        "willow/willow-2010-02-18-0.10.yaml",
        "ritsumeikan_cc4f/cc4.1.yaml",
        "uos_avz/avz.yaml",
    ],
)
def test_real_pgm_maps_follow_map_server_classes(shared: Path, rel: str) -> None:
    """Each cell's class equals the map_server trinary rule applied to the raw pixel."""
    g = read_map(shared / "maps" / rel)
    meta = parse_map_yaml((shared / "maps" / rel).read_text())
    data = (shared / "maps" / rel).parent.joinpath(str(meta["image"])).read_bytes()
    from io import BytesIO

    from PIL import Image

    raw = np.asarray(Image.open(BytesIO(data)).convert("L"), dtype=np.float64)
    assert g.shape == raw.shape
    assert g.resolution == meta["resolution"]
    assert g.origin == tuple(meta["origin"])
    p = (255 - raw) / 255
    expect = np.where(p > 0.65, P_OCCUPIED, np.where(p < 0.196, P_FREE, 0.5))
    np.testing.assert_allclose(g.probability(), expect, atol=1e-6)
    assert (g.logodds[p > 0.65] > 2).all() and (g.logodds[p < 0.196] < -2).all()


def test_absolute_image_path_falls_back_to_yaml_directory(shared: Path) -> None:
    yaml = shared / "maps/fr079_albertB/map312.yaml"
    assert str(parse_map_yaml(yaml.read_text())["image"]).startswith("/home/")
    g = read_map(yaml)
    assert g.shape == (800, 1184)
    assert (g.probability() > 0.65).sum() > 1000


def test_rgb_png_is_averaged_to_gray(shared: Path) -> None:
    """mit_stata_basement is an RGB PNG (unknown = 204): classes follow the channel mean."""
    from PIL import Image

    d = shared / "maps/mit_stata_basement"
    g = read_map(d / "stata_basement.yaml")
    assert g.origin == (25.9, 48.5, 3.14) and g.resolution == 0.0504
    rgb = np.asarray(Image.open(d / "stata_basement.png"), dtype=np.float64)
    assert rgb.ndim == 3 and rgb.shape[:2] == g.shape == (1300, 1730)
    p = (255 - rgb[..., :3].mean(axis=2)) / 255
    expect = np.where(p > 0.65, P_OCCUPIED, np.where(p < 0.196, P_FREE, 0.5))
    np.testing.assert_allclose(g.probability(), expect, atol=1e-6)
    assert (expect == 0.5).mean() > 0.3 and (expect == P_OCCUPIED).any()


# ----------------------------------------------------------------------------- semantics


def test_modes_and_negate() -> None:
    shade = np.array([[0, 100, 205, 230, 254]], dtype=np.float32)
    tri = shade_to_probability(shade, None)
    np.testing.assert_allclose(tri, [[P_OCCUPIED, 0.5, 0.5, P_FREE, P_FREE]])
    neg = shade_to_probability(255 - shade, None, negate=True)
    np.testing.assert_allclose(neg, tri)
    sc = shade_to_probability(shade, None, mode="scale")
    # 100 -> p = 0.608, ratio (0.608 - 0.196) / (0.65 - 0.196) = 0.907
    ratio = ((255 - 100) / 255 - 0.196) / (0.65 - 0.196)
    np.testing.assert_allclose(sc[0, 1], P_FREE + (P_OCCUPIED - P_FREE) * ratio, rtol=1e-5)
    assert sc[0, 2] == pytest.approx(P_FREE + (P_OCCUPIED - P_FREE) * (50 / 255 - 0.196) / 0.454)
    alpha = np.array([[255, 0, 0, 255, 255]], dtype=np.float32)
    assert shade_to_probability(shade, alpha, mode="scale")[0, 1] == 0.5
    raw = shade_to_probability(np.array([[0, 50, 100, 255]], np.float32), None, mode="raw")
    np.testing.assert_allclose(raw, [[P_FREE, 0.5, P_OCCUPIED, 0.5]])


def test_rgba_png_and_16bit_and_ascii_pgm(tmp_path: Path) -> None:
    gray = np.array([[0, 205, 254], [254, 0, 205]], dtype=np.uint8)
    expect = np.array([[P_OCCUPIED, 0.5, P_FREE], [P_FREE, P_OCCUPIED, 0.5]])
    rgba = np.dstack([gray, gray, gray, np.full_like(gray, 255)])
    _png(tmp_path / "m.png", rgba, "RGBA")
    np.testing.assert_allclose(read_map(_map(tmp_path, gray, name="m.png")).probability(), expect)
    _pgm(tmp_path / "m16.pgm", gray.astype(np.uint16) * 257, maxval=65535)
    y = _map(tmp_path, gray, name="m16.pgm")
    np.testing.assert_allclose(read_map(y).probability(), expect, atol=1e-6)
    _png(tmp_path / "m16.png", gray.astype(np.uint16) * 257, "I;16")
    np.testing.assert_allclose(
        read_map(_map(tmp_path, gray, name="m16.png")).probability(), expect, atol=1e-6
    )
    la = np.dstack([gray, np.full_like(gray, 255)])
    _png(tmp_path / "la.png", la, "LA")
    np.testing.assert_allclose(read_map(_map(tmp_path, gray, name="la.png")).probability(), expect)
    bom = "\ufeff" + (tmp_path / "m.yaml").read_text()
    (tmp_path / "m.yaml").write_text(bom, encoding="utf-8")
    np.testing.assert_allclose(read_map(tmp_path / "m.yaml").probability(), expect)
    txt = "P2\n# comment\n3 2\n255\n" + " ".join(map(str, gray.ravel())) + "\n"
    (tmp_path / "a.pgm").write_text(txt)
    (tmp_path / "a.yaml").write_text("image: a.pgm\n" + YAML_TAIL)
    np.testing.assert_allclose(read_map(tmp_path / "a.yaml").probability(), expect, atol=1e-6)


def test_yaml_parser_subset() -> None:
    text = (
        "# header\nimage: 'my map.pgm'  # trailing\nresolution: 5e-2\n"
        "origin: [-1.5, 2, 0.0]\nnegate: 0\nmode: scale\n\n"
    )
    meta = parse_map_yaml(text)
    assert meta == {
        "image": "my map.pgm",
        "resolution": 0.05,
        "origin": [-1.5, 2.0, 0.0],
        "negate": 0,
        "mode": "scale",
    }
    for bad, why in [
        ("image: a\nimage: b\n", "duplicate key"),
        ("  image: a\n", "indented"),
        ("origin: [1, 2\n", "unterminated"),
        ("origin: [a, b]\n", "numbers"),
        ("just text\n", "key: value"),
        ("image: {a: 1}\n", "unsupported"),
    ]:
        with pytest.raises(MapFormatError, match=why):
            parse_map_yaml(bad, "x.yaml")


# ----------------------------------------------------------------------------- writing


def test_write_read_round_trips_classes_and_frame(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    p = rng.uniform(0, 1, (37, 53)).astype(np.float32)
    g = Grid.from_probability(p, 0.07, (-3.25, 4.5, 0.1))
    write_map(tmp_path / "out.yaml", g)
    back = read_map(tmp_path / "out.yaml")
    assert back.shape == g.shape and back.resolution == 0.07 and back.origin == g.origin
    q = back.probability()
    np.testing.assert_array_equal(q > 0.65, p > 0.65)
    np.testing.assert_array_equal(q < 0.196, p < 0.196)
    write_map(tmp_path / "out.npy", g)
    np.testing.assert_allclose(read_map(tmp_path / "out.npy").probability(), p, atol=1e-5)
    assert not list(tmp_path.glob("*.tmp"))


def test_write_png_is_a_valid_png(tmp_path: Path) -> None:
    from PIL import Image

    rgb = np.random.default_rng(1).integers(0, 256, (7, 11, 3), dtype=np.uint8)
    write_png(tmp_path / "x.png", rgb)
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "x.png")), rgb)
    write_png(tmp_path / "g.png", rgb[..., 0])
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "g.png")), rgb[..., 0])


def test_a_bare_image_reads_as_its_map_saver_yaml_with_the_cell_size_given(
    tmp_path: Path,
) -> None:
    """The bundled intel image, alone: the classes its YAML gives, the cell size given, and
    the origin at 0; as a PNG too."""
    from PIL import Image

    examples = Path(__file__).resolve().parents[1] / "examples"
    with_yaml = read_map(examples / "intel_a.yaml")
    bare = read_map(examples / "intel_a.pgm", image_resolution=0.05)
    np.testing.assert_array_equal(bare.logodds, with_yaml.logodds)
    assert bare.resolution == 0.05 and tuple(bare.origin) == (0.0, 0.0, 0.0)
    with Image.open(examples / "intel_a.pgm") as im:
        im.save(tmp_path / "intel_a.png")
    png = read_map(tmp_path / "intel_a.png", image_resolution=0.1)
    np.testing.assert_array_equal(png.logodds, with_yaml.logodds)
    assert png.resolution == 0.1


def test_a_bare_image_without_a_cell_size_is_refused_in_one_line(tmp_path: Path) -> None:
    _pgm(tmp_path / "m.pgm", np.array([[0, 254], [205, 254]], dtype=np.uint8))
    with pytest.raises(MapFormatError, match="carries no cell size") as info:
        read_map(tmp_path / "m.pgm")
    assert "\n" not in str(info.value) and str(info.value).startswith(str(tmp_path / "m.pgm"))
    for bad in (0.0, -0.05, float("nan"), float("inf"), 1e-320, 1e-4, 2.0, 1e9):
        with pytest.raises(MapFormatError, match=r"resolution: a cell size of .* 0\.001-1 m"):
            read_map(tmp_path / "m.pgm", image_resolution=bad)


# ----------------------------------------------------------------------------- bad input


def test_bad_inputs_raise_one_line_errors(tmp_path: Path, shared: Path) -> None:
    ok = np.array([[0, 254], [205, 254]], dtype=np.uint8)
    cases: list[tuple[Path, str]] = [(tmp_path / "nope.yaml", "no such file")]
    (tmp_path / "k.yaml").write_text("image: m.pgm\nresolution: 0.05\n")
    cases.append((tmp_path / "k.yaml", "missing key"))
    for res in ("0", "-1", ".nan"):
        (tmp_path / "r.yaml").write_text(
            "image: m.pgm\n" + YAML_TAIL.replace("resolution: 0.05", f"resolution: {res}")
        )
        with pytest.raises(MapFormatError, match="resolution"):
            read_map(tmp_path / "r.yaml")
    _pgm(tmp_path / "free.pgm", np.full((4, 4), 254))
    (tmp_path / "f.yaml").write_text("image: free.pgm\n" + YAML_TAIL)
    cases.append((tmp_path / "f.yaml", "no occupied cells"))
    (tmp_path / "e.pgm").write_bytes(b"P5\n0 5\n255\n")
    (tmp_path / "e.yaml").write_text("image: e.pgm\n" + YAML_TAIL)
    cases.append((tmp_path / "e.yaml", "empty map"))
    (tmp_path / "gone.yaml").write_text("image: gone.pgm\n" + YAML_TAIL)
    cases.append((tmp_path / "gone.yaml", "gone.pgm: no such file"))
    nan = np.full((3, 3), 0.5)
    nan[0, 0], nan[1, 1] = np.nan, 0.9
    np.save(tmp_path / "nan.npy", nan)
    cases.append((tmp_path / "nan.npy", "NaN"))
    np.save(tmp_path / "range.npy", np.array([[0.2, 1.5]]))
    cases.append((tmp_path / "range.npy", r"\[0, 1\]"))
    np.save(tmp_path / "three.npy", np.zeros((2, 2, 2)))
    cases.append((tmp_path / "three.npy", "2-D"))
    (tmp_path / "x.txt").write_text("hello")
    cases.append((tmp_path / "x.txt", "unknown map format"))
    cases.append((tmp_path, "is a directory, not a map file"))
    _map(tmp_path, ok)
    for path, why in cases:
        with pytest.raises(MapFormatError, match=why) as info:
            read_map(path)
        # the YAML, or the image it names, leads the one-line message
        assert "\n" not in str(info.value) and str(info.value).startswith(str(tmp_path))
    with pytest.raises(MapFormatError, match="exceeds the limit"):
        read_map(shared / "maps/intel/intel.yaml", max_cells=500 * 500)


def test_size_limit_is_checked_before_decoding(tmp_path: Path) -> None:
    """A header claiming 10^5 x 10^5 cells is refused without reading (or needing) the pixels."""
    (tmp_path / "big.pgm").write_bytes(b"P5\n100000 100000\n255\n\x00\x00")
    (tmp_path / "big.yaml").write_text("image: big.pgm\n" + YAML_TAIL)
    with pytest.raises(MapFormatError, match="100000x100000 cells exceeds"):
        read_map(tmp_path / "big.yaml")
    ihdr = struct.pack(">IIBBBBB", 90000, 90000, 8, 0, 0, 0, 0)
    png = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr
    (tmp_path / "big.png").write_bytes(png + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr)))
    (tmp_path / "big.yaml").write_text("image: big.png\n" + YAML_TAIL)
    with pytest.raises(MapFormatError, match="90000x90000 cells exceeds"):
        read_map(tmp_path / "big.yaml")
    with open(tmp_path / "big.npy", "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": "<f4", "fortran_order": False, "shape": (9000, 9000)}
        )
    with pytest.raises(MapFormatError, match="9000x9000 cells exceeds"):
        read_map(tmp_path / "big.npy")


# ----------------------------------------------------------------------------- fuzz

_yaml_lines = st.lists(
    st.one_of(
        st.text(max_size=40),
        st.sampled_from(["image: m.pgm", "resolution: 0.05", "origin: [0, 0, 0]", "negate: 1"]),
        st.builds(
            lambda k, v: f"{k}: {v}",
            st.from_regex(r"[a-z_]{1,8}", fullmatch=True),
            st.text(max_size=20),
        ),
    ),
    max_size=10,
)


@settings(max_examples=300)
@given(_yaml_lines)
def test_fuzz_yaml_parser_only_raises_map_format_error(lines: list[str]) -> None:
    try:
        meta = parse_map_yaml("\n".join(lines), "f.yaml")
    except MapFormatError as exc:
        assert "\n" not in str(exc)
    else:
        assert isinstance(meta, dict)


_headers = st.sampled_from(
    [
        b"",
        b"P5\n",
        b"P5\n3 2\n255\n",
        b"P2\n3 2\n255\n",
        b"P5 3 2 65535 ",
        b"\x89PNG\r\n\x1a\n",
        b"\x93NUMPY\x01\x00",
        b"image: m.pgm\n",
    ]
)


@settings(max_examples=300, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(header=_headers, body=st.binary(max_size=200), ext=st.sampled_from(["pgm", "png", "npy"]))
# found by CI: a .npy header "(" left numpy's header tokenizer mid-statement (TokenError)
@example(header=b"\x93NUMPY\x01\x00", body=b"\x03\x00\x00\x00(", ext="npy")
def test_fuzz_read_map_on_random_bytes(
    tmp_path: Path, header: bytes, body: bytes, ext: str
) -> None:
    """Random bytes behind a valid YAML, as a bare image, or as the .npy/.yaml itself: only
    MapFormatError."""
    data = header + body
    paths = [tmp_path / "g.yaml"]
    if ext == "npy":
        target = tmp_path / "f.npy"
        target.write_bytes(data)
    else:
        (tmp_path / f"f.{ext}").write_bytes(data)
        target = tmp_path / "f.yaml"
        target.write_text(f"image: f.{ext}\n" + YAML_TAIL)
        paths.append(tmp_path / f"f.{ext}")
    for path in (target, *paths):
        if path.name == "g.yaml":
            path.write_bytes(data)
        try:
            g = read_map(path, max_cells=10_000, image_resolution=0.05)
        except MapFormatError as exc:
            assert "\n" not in str(exc)
        else:
            assert np.isfinite(g.logodds).all()


def test_map_writes_are_durable_file_and_rename(tmp_path: Path, monkeypatch) -> None:
    """Both the file and its directory are fsynced: after a power cut the rename itself
    survives, not only the bytes of a temporary file nobody points to."""
    import os
    import stat

    synced: list[str] = []
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        synced.append("dir" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file")
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    write_map(tmp_path / "m.npy", Grid.from_probability(np.full((4, 5), 0.9), 0.1))
    assert synced == ["file", "dir"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npy"]  # no temporary left
