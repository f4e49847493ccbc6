"""rce_fleet.maps.occupancy: map_server YAML + image loading (trinary / scale / raw, negate, errors)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from rce_fleet.maps.occupancy import MapError, OccupancyMap, load_map, save_map

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
MAPS = DATA / "maps"


def write(tmp_path: Path, pixels, mode_line: str = "", negate: int = 0, image_mode: str = "L",
          suffix: str = ".pgm", extra: str = "", thresholds=(0.65, 0.196)) -> Path:
    arr = np.asarray(pixels, dtype=np.uint8)
    img = tmp_path / f"m{suffix}"
    Image.fromarray(arr, mode=image_mode).save(img)
    y = tmp_path / "m.yaml"
    y.write_text(f"image: {img.name}\nresolution: 0.5\norigin: [1.0, 2.0, 0.0]\nnegate: {negate}\n"
                 f"occupied_thresh: {thresholds[0]}\nfree_thresh: {thresholds[1]}\n{mode_line}{extra}")
    return y


def test_trinary_default(tmp_path):
    y = write(tmp_path, [[254, 0, 205], [255, 100, 180]])
    m = load_map(y)
    # 254 free; 0 occupied; 205: occ = 0.196078 > 0.196 -> unknown; 100: occ 0.608 -> unknown;
    # 180: occ 0.294 -> unknown
    assert m.occupancy.dtype == np.int8
    assert m.occupancy.tolist() == [[0, 100, -1], [0, -1, -1]]
    assert m.resolution == 0.5 and m.origin == (1.0, 2.0, 0.0)
    assert (m.width, m.height) == (3, 2) and m.width_m == 1.5 and m.height_m == 1.0


def test_trinary_negate(tmp_path):
    y = write(tmp_path, [[254, 0, 128]], negate=1)
    assert load_map(y).occupancy.tolist() == [[100, 0, -1]]


def test_scale_mode_and_alpha(tmp_path):
    # occ = 1 - v/255 ; thresholds 0.65 / 0.196; between -> rint(100 * (occ-0.196)/(0.65-0.196))
    vals = [255, 0, 150, 200]
    rgba = np.zeros((1, 4, 4), dtype=np.uint8)
    rgba[0, :, 0] = rgba[0, :, 1] = rgba[0, :, 2] = vals
    rgba[0, :, 3] = [255, 255, 255, 255]
    rgba_t = rgba.copy()
    rgba_t[0, 0, 3] = 0  # transparent -> unknown in scale mode
    img = tmp_path / "m.png"
    Image.fromarray(rgba_t, mode="RGBA").save(img)
    y = tmp_path / "m.yaml"
    y.write_text("image: m.png\nresolution: 0.1\norigin: [0, 0, 0]\nnegate: 0\n"
                 "occupied_thresh: 0.65\nfree_thresh: 0.196\nmode: scale\n")
    got = load_map(y).occupancy.tolist()[0]
    expect_150 = round(100 * ((1 - 150 / 255) - 0.196) / (0.65 - 0.196))
    # 200: occ 0.2157, just above free_thresh -> a small scaled value
    expect_200 = round(100 * ((1 - 200 / 255) - 0.196) / (0.65 - 0.196))
    assert got == [-1, 100, expect_150, expect_200]
    assert 0 < expect_150 < 100


def test_scale_negate(tmp_path):
    y = write(tmp_path, [[0, 255]], mode_line="mode: scale\n", negate=1)
    assert load_map(y).occupancy.tolist() == [[0, 100]]


def test_raw_mode(tmp_path):
    y = write(tmp_path, [[0, 50, 100, 101, 255]], mode_line="mode: raw\n")
    assert load_map(y).occupancy.tolist() == [[0, 50, 100, -1, -1]]


def test_rgb_image_is_averaged(tmp_path):
    rgb = np.zeros((1, 2, 3), dtype=np.uint8)
    rgb[0, 0] = [254, 254, 254]
    rgb[0, 1] = [0, 0, 30]
    img = tmp_path / "m.png"
    Image.fromarray(rgb, mode="RGB").save(img)
    y = tmp_path / "m.yaml"
    y.write_text("image: m.png\nresolution: 0.1\norigin: [0, 0, 0]\n")  # thresholds default
    assert load_map(y).occupancy.tolist() == [[0, 100]]


def test_coordinates_row0_is_top(tmp_path):
    y = write(tmp_path, np.full((4, 6), 254))
    m = load_map(y)  # res 0.5, origin (1, 2): image spans x 1..4, y 2..4
    assert m.pixel_to_world(3, 0) == (1.25, 2.25)       # bottom-left pixel
    assert m.pixel_to_world(0, 0) == (1.25, 3.75)       # top-left pixel
    assert m.world_to_pixel(1.01, 2.01) == (3, 0)
    assert m.world_to_pixel(3.99, 3.99) == (0, 5)
    for r in range(4):
        for c in range(6):
            assert m.world_to_pixel(*m.pixel_to_world(r, c)) == (r, c)
    assert not m.in_bounds(*m.world_to_pixel(0.0, 0.0))


def test_yaw_rotation_round_trip():
    m = OccupancyMap(np.zeros((5, 7), dtype=np.int8), 0.2, (1.0, -1.0, math.pi / 2))
    # the image's lower-left corner is at the origin and its x axis points along world +y
    x, y = m.pixel_to_world(4, 0)
    assert (round(x, 9), round(y, 9)) == (0.9, -0.9)
    for r in range(5):
        for c in range(7):
            assert m.world_to_pixel(*m.pixel_to_world(r, c)) == (r, c)


def test_save_and_reload(tmp_path):
    occ = np.array([[0, 100, -1], [-1, 0, 100]], dtype=np.int8)
    p = save_map(OccupancyMap(occ, 0.05, (-1.0, -2.0, 0.0)), tmp_path / "x.yaml")
    m = load_map(p)
    assert m.occupancy.tolist() == occ.tolist() and m.origin == (-1.0, -2.0, 0.0)


@pytest.mark.parametrize("missing", ["image", "resolution", "origin"])
def test_missing_key_names_key_and_file(tmp_path, missing):
    Image.fromarray(np.full((2, 2), 254, dtype=np.uint8)).save(tmp_path / "m.pgm")
    keys = {"image": "m.pgm", "resolution": "0.05", "origin": "[0, 0, 0]"}
    del keys[missing]
    y = tmp_path / "bad.yaml"
    y.write_text("".join(f"{k}: {v}\n" for k, v in keys.items()))
    with pytest.raises(MapError) as ei:
        load_map(y)
    assert f"'{missing}'" in str(ei.value) and "bad.yaml" in str(ei.value)
    assert isinstance(ei.value, ValueError)


@pytest.mark.parametrize("key,value", [
    ("resolution", "-1"), ("resolution", "abc"), ("origin", "[0, 0]"), ("mode", "fancy"),
    ("negate", "2"), ("occupied_thresh", "1.5"), ("free_thresh", "0.9"), ("image", "nope.pgm"),
])
def test_bad_value_names_key_and_file(tmp_path, key, value):
    Image.fromarray(np.full((2, 2), 254, dtype=np.uint8)).save(tmp_path / "m.pgm")
    keys = {"image": "m.pgm", "resolution": "0.05", "origin": "[0, 0, 0]", "negate": "0",
            "occupied_thresh": "0.65", "free_thresh": "0.196", key: value}
    y = tmp_path / "bad.yaml"
    y.write_text("".join(f"{k}: {v}\n" for k, v in keys.items()))
    with pytest.raises(MapError) as ei:
        load_map(y)
    assert f"'{key}'" in str(ei.value) and "bad.yaml" in str(ei.value)


def test_invalid_yaml_and_missing_file(tmp_path):
    y = tmp_path / "broken.yaml"
    y.write_text("image: [unclosed\n")
    with pytest.raises(MapError, match="broken.yaml"):
        load_map(y)
    with pytest.raises(MapError, match="absent.yaml"):
        load_map(tmp_path / "absent.yaml")
    y.write_text("- just\n- a list\n")
    with pytest.raises(MapError, match="mapping"):
        load_map(y)


def test_turtlebot3_world_loads():
    m = load_map(MAPS / "turtlebot3_world.yaml")
    assert m.occupancy.shape == (384, 384)
    assert m.resolution == 0.05 and m.origin == (-10.0, -10.0, 0.0)
    vals, counts = np.unique(m.occupancy, return_counts=True)
    assert vals.tolist() == [-1, 0, 100]
    assert dict(zip(vals.tolist(), counts.tolist(), strict=True)) == {-1: 138722, 0: 7939, 100: 795}
    assert m.world_to_pixel(-10.0 + 1e-9, -10.0 + 1e-9) == (383, 0)


def test_warehouse_loads():
    m = load_map(MAPS / "warehouse.yaml")
    assert m.occupancy.shape == (1674, 1006)          # 50.22 m high x 30.18 m wide
    assert m.resolution == 0.03 and m.origin == (-15.1, -25.0, 0.0)
    assert abs(m.width_m - 30.18) < 1e-9 and abs(m.height_m - 50.22) < 1e-9
    # 205 grey is unknown in trinary mode; 0 occupied; 254/255 free
    assert (m.occupancy == -1).sum() == 230801
    assert (m.occupancy == 100).sum() == 30951
    assert (m.occupancy == 0).sum() == 1318485 + 103807
