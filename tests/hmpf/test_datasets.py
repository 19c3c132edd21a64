from pathlib import Path

import numpy as np
import pytest

from hmpf.datasets import (
    frame_ground_truth,
    gps_ground_truth,
    haversine_m,
    list_images,
    natural_key,
    pairs_ground_truth,
)
from hmpf.errors import DatasetError


def test_natural_sort(tmp_path: Path):
    for n in ["img10.png", "img2.png", "img1.jpg", "notes.txt", "IMG3.JPEG"]:
        (tmp_path / n).write_bytes(b"x")
    assert [p.name for p in list_images(tmp_path)] == [
        "img1.jpg",
        "img2.png",
        "IMG3.JPEG",
        "img10.png",
    ]
    assert natural_key("a2") < natural_key("a10")


def test_empty_and_missing_folders(tmp_path: Path):
    with pytest.raises(DatasetError, match="holds no image"):
        list_images(tmp_path)
    with pytest.raises(DatasetError, match="does not exist"):
        list_images(tmp_path / "nope")


def test_frame_ground_truth():
    gt = frame_ground_truth(4, 5, 1)
    expected = np.array(
        [
            [1, 1, 0, 0, 0],
            [1, 1, 1, 0, 0],
            [0, 1, 1, 1, 0],
            [0, 0, 1, 1, 1],
        ],
        bool,
    )
    np.testing.assert_array_equal(gt, expected)


def test_pairs_csv_names_positions_and_tolerance(tmp_path: Path):
    q = ["q1.png", "q2.png", "q3.png"]
    r = [f"r{i}.png" for i in range(1, 7)]
    p = tmp_path / "gt.csv"
    p.write_text("query,reference\nq1.png,r2.png\n2,5\n3,3,1\n")
    gt = pairs_ground_truth(p, q, r)
    assert gt[0].nonzero()[0].tolist() == [1]
    assert gt[1].nonzero()[0].tolist() == [4]
    assert gt[2].nonzero()[0].tolist() == [1, 2, 3]


def test_pairs_csv_errors(tmp_path: Path):
    p = tmp_path / "gt.csv"
    p.write_text("q9.png,r1.png\n")
    with pytest.raises(DatasetError, match="gt.csv:1: query 'q9.png'"):
        pairs_ground_truth(p, ["q1.png"], ["r1.png"])
    p.write_text("1,7\n")
    with pytest.raises(DatasetError, match="out of 1..1"):
        pairs_ground_truth(p, ["q1.png"], ["r1.png"])
    p.write_text("1\n")
    with pytest.raises(DatasetError, match="expected query,reference"):
        pairs_ground_truth(p, ["q1.png"], ["r1.png"])


def test_nordland_sample_csv_layout(nordland: Path):
    names = [f.name for f in list_images(nordland / "summer")]
    gt = pairs_ground_truth(nordland / "sample_ground_truth.csv", names, names)
    # The sample lists (i, i, 15): query 1 matches references 1..16 (positions 0..15).
    assert gt[0].nonzero()[0].tolist() == list(range(16))


def test_haversine_one_degree_of_latitude():
    # R = 6378.137 km: one degree is 2*pi*R/360 metres.
    d = haversine_m(np.array(0.0), np.array(0.0), np.array(1.0), np.array(0.0))
    assert float(d) == pytest.approx(2 * np.pi * 6_378_137.0 / 360, rel=1e-9)


def test_gps_ground_truth(tmp_path: Path):
    p = tmp_path / "gps.csv"
    p.write_text(
        "role,name,lat,lon\n"
        "reference,a.jpg,-27.4770,153.0280\n"
        "reference,b.jpg,-27.4780,153.0280\n"
        "query,a.jpg,-27.47702,153.0280\n"
    )
    gt = gps_ground_truth(p, ["a.jpg"], ["a.jpg", "b.jpg"], radius_m=25)
    assert gt.tolist() == [[True, False]]  # 2.2 m vs ~109 m
    with pytest.raises(DatasetError, match="no query position for z.jpg"):
        gps_ground_truth(p, ["z.jpg"], ["a.jpg"], radius_m=25)
    p.write_text("name,lat\n")
    with pytest.raises(DatasetError, match="role,name,lat,lon"):
        gps_ground_truth(p, ["a.jpg"], ["a.jpg"], radius_m=25)
