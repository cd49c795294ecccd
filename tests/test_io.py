"""Map files: map_server YAML + PGM/PNG, OccupancyGrid arrays, .npz; the real maps in ../shared."""

from pathlib import Path

import numpy as np
import pytest

from taichi_match import GridMap, MapFileError, MapFormatError, io

SHARED_MAPS = Path(__file__).resolve().parents[2] / "shared" / "maps"


def grid_with(prob, res=0.05, origin=(-1.0, 2.0, 0.0)):
    return GridMap(np.asarray(prob, dtype=float), res, origin)


def test_trinary_round_trip_and_row_flip(tmp_path):
    prob = np.full((4, 5), np.nan)
    prob[0, 0] = 1.0          # lowest y row: the image's last row
    prob[1, :] = 0.0
    prob[3, 4] = 1.0          # highest y row: the image's first row
    g = grid_with(prob)
    io.write_ros_map(g, tmp_path / "m.yaml")
    image = io.read_image(tmp_path / "m.pgm")
    assert image[-1, 0] == 0 and image[0, 4] == 0 and image[1, 0] == 205 and np.all(image[2] == 254)
    back = io.read_ros_map(tmp_path / "m.yaml")
    assert np.array_equal(back.prob, prob, equal_nan=True)
    assert back.resolution == 0.05 and back.corner_pose == (-1.0, 2.0, 0.0)


def test_yaml_fields_yaw_negate_and_relative_image_path(tmp_path):
    (tmp_path / "sub").mkdir()
    io.write_image(str(tmp_path / "sub" / "img.pgm"), np.array([[0, 255], [255, 128]], dtype=np.uint8))
    (tmp_path / "sub" / "m.yaml").write_text(
        "# a comment\nimage: img.pgm\nresolution: 0.5\norigin: [1.0, -2.0, 0.5]  # yaw\nnegate: 1\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n")
    g = io.read_ros_map(tmp_path / "sub" / "m.yaml")
    assert g.corner_pose == (1.0, -2.0, 0.5)
    # negate: p = v / 255. Image rows flip: prob row 0 = image row 1 = [255, 128]
    assert g.prob[0, 0] == 1.0 and np.isnan(g.prob[0, 1]) and g.prob[1, 0] == 0.0 and g.prob[1, 1] == 1.0
    c, s = np.cos(0.5), np.sin(0.5)
    assert np.allclose(g.cell_centres([0], [1]), [[1.0 + c * 0.75 - s * 0.25, -2.0 + s * 0.75 + c * 0.25]])


def test_scale_mode_follows_map_server(tmp_path):
    grey = np.array([[0, 60, 128], [200, 254, 255]], dtype=np.uint8)
    alpha = np.array([[255, 255, 0], [255, 255, 255]], dtype=np.uint8)
    io.write_image(str(tmp_path / "s.png"), np.dstack([grey, alpha]))
    (tmp_path / "s.yaml").write_text("image: s.png\nresolution: 1\norigin: [0, 0, 0]\nmode: scale\n")
    g = io.read_ros_map(tmp_path / "s.yaml").prob[::-1]            # back to image row order
    occ = (255.0 - grey) / 255.0
    expected = np.where(occ > 0.65, 1.0, np.where(occ < 0.196, 0.0,
                        np.rint(1 + 98 * (occ - 0.196) / (0.65 - 0.196)) / 100))
    expected[0, 2] = np.nan                                         # between thresholds and transparent
    assert np.allclose(g, expected, equal_nan=True)


def test_raw_mode_and_its_round_trip(tmp_path):
    prob = np.array([[0.0, 0.37, np.nan], [1.0, 0.5, 0.02]])
    io.write_ros_map(grid_with(prob), tmp_path / "r.yaml", mode="raw")
    assert np.allclose(io.read_ros_map(tmp_path / "r.yaml").prob, prob, equal_nan=True)


def test_png_decoder_against_matplotlibs_encoder(tmp_path):
    plt_image = pytest.importorskip("matplotlib.image")
    rng = np.random.default_rng(0)
    rgba = (rng.random((23, 31, 4)) * 255).astype(np.uint8)
    rgba[..., 3] = 255
    smooth = np.add.outer(np.arange(23), np.arange(31)).astype(np.uint8)   # filters other than 0
    rgba[:12, :, :3] = smooth[:12, :, None]
    plt_image.imsave(tmp_path / "m.png", rgba)
    assert np.array_equal(io.read_image(tmp_path / "m.png")[..., :4], rgba)


def test_pgm_variants(tmp_path):
    (tmp_path / "a.pgm").write_bytes(b"P2\n# comment\n3 2\n15\n0 15 7\n1 2 3\n")
    assert io.read_image(tmp_path / "a.pgm").tolist() == [[0, 255, 119], [17, 34, 51]]
    data = np.array([[0, 65535], [32768, 1]], dtype=">u2")
    (tmp_path / "b.pgm").write_bytes(b"P5\n2 2\n65535\n" + data.tobytes())
    assert io.read_image(tmp_path / "b.pgm").tolist() == [[0, 255], [128, 0]]


def test_yaml_in_any_style_map_server_reads(tmp_path):
    """Block sequences, flow mappings, a float without a dot (yaml-cpp reads 1e-1 as a number)."""
    io.write_image(str(tmp_path / "m.pgm"), np.array([[0, 254]], dtype=np.uint8))
    texts = ["image: m.pgm\nresolution: 1e-1\norigin:\n  - 1.5\n  - -2\n  - 0.25\nnegate: 0\n",
             "{image: m.pgm, resolution: 0.1, origin: [1.5, -2, 0.25], mode: trinary}\n",
             "---\nimage: 'm.pgm'   # quoted\nresolution: 0.1\norigin: [1.5, -2.0, 0.25]\n...\n"]
    for text in texts:
        (tmp_path / "m.yaml").write_text(text)
        g = io.read_ros_map(tmp_path / "m.yaml")
        assert g.resolution == 0.1 and g.corner_pose == (1.5, -2.0, 0.25)
        assert g.prob.tolist() == [[1.0, 0.0]]


def test_png_variants_pillow_writes(tmp_path):
    """16-bit grey, a palette with a transparent entry, 1-bit: read as map_server's SDL_image would."""
    from PIL import Image

    Image.fromarray(np.array([[0, 65535, 32896]], dtype=np.uint16)).save(tmp_path / "g16.png")
    assert io.read_image(tmp_path / "g16.png").tolist() == [[0, 255, 128]]
    palette = Image.fromarray(np.array([[0, 1, 2]], dtype=np.uint8), "P")
    palette.putpalette([0, 0, 0, 255, 255, 255, 205, 205, 205])
    palette.save(tmp_path / "p.png", transparency=2)
    assert io.read_image(tmp_path / "p.png").tolist() == [[[0, 0, 0, 255], [255, 255, 255, 255], [205, 205, 205, 0]]]
    Image.fromarray(np.array([[True, False]])).save(tmp_path / "b.png")
    assert io.read_image(tmp_path / "b.png").tolist() == [[255, 0]]


# nested aliases: nine levels of nine, 9**10 items once expanded (a YAML bomb)
BOMB = "l0: &l0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n" + "".join(
    f"l{k}: &l{k} [" + ", ".join([f"*l{k - 1}"] * 9) + "]\n" for k in range(1, 10))


@pytest.mark.parametrize("text, match", [
    ("resolution: 0.05\norigin: [0, 0, 0]\n", "'image' is missing"),
    ("image: m.pgm\norigin: [0, 0, 0]\n", "'resolution' is missing"),
    ("image: m.pgm\nresolution: fast\norigin: [0, 0, 0]\n", "'resolution' must be a number"),
    ("image: m.pgm\nresolution: -1\norigin: [0, 0, 0]\n", "out of range"),
    ("image: m.pgm\nresolution: 0.1\norigin: [0, zero, 0]\n", "'origin' must be"),
    ("image: m.pgm\nresolution: 0.1\norigin: [0, 0, 0\n", "not valid YAML"),
    ("image: m.pgm\nresolution: 0.1\norigin: [0, 0, 0]\nmode: fancy\n", "'mode' must be"),
    ("image: m.pgm\nresolution: 0.1\norigin: [0, 0, 0]\nfree_thresh: 0.9\n", "free_thresh"),
    ("image: m.pgm\nresolution: 0.1\norigin: [0, 0, 0]\nnegate: 2\n", "'negate'"),
    ("just a line\n", "expected 'key: value'"),
    ("image: m.pgm\nresolution: 1e300\norigin: [0, 0, 0]\n", "out of range"),
    ("image: m.pgm\nresolution: 1e-300\norigin: [0, 0, 0]\n", "out of range"),
    (BOMB + "image: m.pgm\nresolution: 0.1\norigin: *l9\n", "'origin' must be"),
    ("image: m.pgm\nresolution: 0.1\norigin: [0, 0, 0]\nresolution: 0.05\n", "'resolution' appears twice"),
    ("image: m.pgm\nresolution: 0.1\norigin: {x: 0, x: 1}\n", "'x' appears twice"),
])
def test_malformed_yaml_gives_clear_errors(tmp_path, text, match):
    io.write_image(str(tmp_path / "m.pgm"), np.zeros((2, 2), np.uint8))
    (tmp_path / "m.yaml").write_text(text)
    with pytest.raises(MapFormatError, match=match) as error:
        io.read_ros_map(tmp_path / "m.yaml")
    assert len(str(error.value)) < 2000                  # a hostile value is shown in part


def test_yaml_merge_keys_may_repeat_what_they_merge(tmp_path):
    """A key written after a merge (``<<``) overrides the merged one, as YAML says: not a duplicate."""
    io.write_image(str(tmp_path / "m.pgm"), np.zeros((2, 2), np.uint8))
    (tmp_path / "m.yaml").write_text("base: &b {resolution: 0.2, origin: [1, 2, 0]}\n<<: *b\nimage: m.pgm\n"
                                     "resolution: 0.05\n")
    grid = io.read_ros_map(tmp_path / "m.yaml")
    assert grid.resolution == 0.05 and grid.origin == (1.0, 2.0)


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(MapFileError):
        io.read_ros_map(tmp_path / "none.yaml")
    (tmp_path / "m.yaml").write_text("image: gone.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n")
    with pytest.raises(MapFileError, match="gone.pgm"):
        io.read_ros_map(tmp_path / "m.yaml")
    (tmp_path / "t.pgm").write_bytes(b"P5\n10 10\n255\n" + bytes(20))
    with pytest.raises(MapFormatError, match="truncated"):
        io.read_image(tmp_path / "t.pgm")
    io.write_image(str(tmp_path / "c.png"), np.zeros((8, 8), np.uint8))
    data = bytearray((tmp_path / "c.png").read_bytes())
    data[45:60] = b"x" * 15
    (tmp_path / "c.png").write_bytes(bytes(data))
    with pytest.raises(MapFormatError):
        io.read_image(tmp_path / "c.png")
    (tmp_path / "x.pgm").write_bytes(b"GIF89a")
    with pytest.raises(MapFormatError, match="not an image"):
        io.read_image(tmp_path / "x.pgm")
    assert issubclass(MapFileError, OSError) and issubclass(MapFormatError, ValueError)


def test_occupancy_grid_and_npz_round_trips(tmp_path):
    prob = np.array([[0.0, 0.25, np.nan], [1.0, 0.5, 0.07]])
    g = grid_with(prob, origin=(0.5, -0.5, 0.3))
    data, info = io.to_occupancy_grid(g)
    assert data.dtype == np.int8 and data.tolist() == [[0, 25, -1], [100, 50, 7]]
    assert info == {"resolution": 0.05, "width": 3, "height": 2, "origin": (0.5, -0.5, 0.3)}
    back = io.from_occupancy_grid(data.ravel(), 0.05, info["origin"], width=3, height=2)
    assert np.allclose(back.prob, prob, equal_nan=True) and back.corner_pose == g.corner_pose
    with pytest.raises(MapFormatError):
        io.from_occupancy_grid([0, 101], 0.1, width=2, height=1)
    io.save_npz(g, tmp_path / "g.npz")
    loaded = io.load_map(tmp_path / "g.npz")
    assert np.array_equal(loaded.prob, prob, equal_nan=True) and loaded.corner_pose == g.corner_pose
    with pytest.raises(MapFormatError):
        io.load_map(tmp_path / "g.txt")
    io.save_npy(g, tmp_path / "g.npy")
    from_npy = io.load_map(tmp_path / "g.npy", resolution=0.05, origin=(0.5, -0.5, 0.3))
    assert np.allclose(from_npy.prob, prob, equal_nan=True)
    with pytest.raises(MapFormatError, match="resolution"):
        io.load_map(tmp_path / "g.npy")


# The shares of free / occupied / unknown cells SOURCES.md gives for each map with its own YAML
SOURCES_SHARES = {
    "avz5floor_closed": (18.0, 1.1, 80.9), "avz5floor_open": (31.7, 2.4, 65.9), "gdc_3": (33.1, 3.0, 63.9),
    "gdc_3ne": (42.9, 3.2, 53.9), "intel_bwi": (57.4, 8.9, 33.7), "intel_gondsm": (28.3, 1.7, 70.0),
    "willow_2010": (31.7, 0.2, 68.1), "willow_full": (43.6, 2.7, 53.8),
}


@pytest.mark.skipif(not SHARED_MAPS.is_dir(), reason="../shared/maps is not present")
@pytest.mark.parametrize("name", sorted(SOURCES_SHARES))
def test_every_shared_map_loads_with_the_documented_shares(name):
    yaml = next((SHARED_MAPS / name).glob("*.yaml"))
    g = io.read_ros_map(yaml)
    p = g.prob
    shares = (100 * np.mean(p == 0.0), 100 * np.mean(p == 1.0), 100 * np.mean(np.isnan(p)))
    assert np.allclose(shares, SOURCES_SHARES[name], atol=0.06)


@pytest.mark.parametrize("image", ["m.pgm", "m.png"])
def test_mutated_map_files_raise_only_documented_errors(tmp_path, image):
    """A seeded fuzz pass: flip, cut or insert bytes of a valid map's image and YAML."""
    from taichi_match import InvalidMapError

    rng = np.random.default_rng(99)
    prob = np.full((9, 11), np.nan)
    prob[2:7, 1:10] = 0.0
    prob[2, 1:10] = 1.0
    io.write_ros_map(grid_with(prob), tmp_path / "m.yaml", image=image)
    originals = {name: (tmp_path / name).read_bytes() for name in ("m.yaml", image)}
    for trial in range(150):
        name = ("m.yaml", image)[trial % 2]
        data = bytearray(originals[name])
        kind = rng.integers(3)
        pos = int(rng.integers(len(data)))
        if kind == 0:
            data[pos] = int(rng.integers(256))
        elif kind == 1:
            del data[pos:pos + int(rng.integers(1, 40))]
        else:
            data[pos:pos] = bytes(rng.integers(0, 256, int(rng.integers(1, 8)), dtype=np.uint8))
        (tmp_path / name).write_bytes(bytes(data))
        try:
            g = io.read_ros_map(tmp_path / "m.yaml")
            assert isinstance(g, GridMap)
        except (MapFileError, MapFormatError, InvalidMapError):
            pass
        (tmp_path / name).write_bytes(originals[name])
