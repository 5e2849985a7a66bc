"""Damaged scan files are refused in one line (issue 34): a KITTI .bin whose size is not a whole
number of 16-byte points (numpy alone read 16 N + 3 bytes as N points), a .label file likewise,
and a scan of a few distinct points (5000 copies of one point were labelled "road 100 %"), in
every scan format, through `semcal segment-cloud` as a user meets it."""

from __future__ import annotations

import numpy as np
import pytest

from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.io import files, kitti, pcd, ply


def _scan(n: int = 5000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-20, 20, (n, 3)), rng.uniform(0, 1, n)]).astype("<f4")


def _write_pcd(path, xyz: np.ndarray) -> None:
    lines = ["VERSION 0.7", "FIELDS x y z", "SIZE 4 4 4", "TYPE F F F", "COUNT 1 1 1",
             f"WIDTH {len(xyz)}", "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {len(xyz)}",
             "DATA ascii"]
    path.write_text("\n".join(lines + [" ".join(f"{v:g}" for v in p) for p in xyz]) + "\n")


def _damaged(tmp_path):
    """name -> (file, the refusal)"""
    out = {}
    good = _scan()
    path = tmp_path / "plus3.bin"
    path.write_bytes(good.tobytes() + b"\x01\x02\x03")
    out["bin-16N+3-bytes"] = (path, f"size {16 * 5000 + 3} bytes is not a multiple of 16")
    one = np.repeat(good[:1], 5000, axis=0)
    path = tmp_path / "one_point.bin"
    one.tofile(path)
    out["bin-one-point"] = (path, "only 1 distinct point among 5000 (fewer than 10): not a scan")
    path = tmp_path / "one_point.ply"
    ply.write_ply(path, LabelledCloud(one[:, :3].astype(float), np.full(5000, 40, np.uint16)))
    out["ply-one-point"] = (path, "only 1 distinct point among 5000")
    path = tmp_path / "three_points.pcd"
    _write_pcd(path, np.tile(good[:3, :3], (1000, 1)))
    out["pcd-three-points"] = (path, "only 3 distinct points among 3000")
    return out


def test_readers_refuse_damaged_scans(tmp_path):
    readers = {".bin": kitti.read_scan, ".ply": ply.read_ply, ".pcd": pcd.read_pcd}
    for name, (path, expected) in _damaged(tmp_path).items():
        with pytest.raises(ValueError) as info:
            readers[path.suffix](path)
        message = str(info.value)
        assert expected in message and str(path) in message and "\n" not in message, \
            (name, message)
    labels = tmp_path / "plus1.label"
    labels.write_bytes(np.full(5000, 40, "<u4").tobytes() + b"\x00")
    with pytest.raises(ValueError, match="size 20001 bytes is not a multiple of 4"):
        kitti.read_labels(labels)


def test_good_scans_pass_and_distinct_points_are_counted(tmp_path):
    good = _scan()
    good.tofile(tmp_path / "good.bin")
    np.testing.assert_array_equal(kitti.read_velodyne(tmp_path / "good.bin"), good)
    # ten distinct points repeated are a scan (the smallest one), nine are not
    assert files.distinct_points_problem(np.tile(good[:10, :3], (500, 1))) == ""
    assert "only 9 distinct" in files.distinct_points_problem(np.tile(good[:9, :3], (500, 1)))
    # NaN rows are not points; an all-NaN or empty cloud is left to the caller's own words
    with_nan = np.vstack([np.full((100, 3), np.nan), np.tile(good[:2, :3], (50, 1))])
    assert "only 2 distinct points among 100" in files.distinct_points_problem(with_nan)
    assert files.distinct_points_problem(np.full((10, 3), np.nan)) == ""
    assert files.distinct_points_problem(np.zeros((0, 3))) == ""


@pytest.mark.parametrize("name", ["bin-16N+3-bytes", "bin-one-point", "ply-one-point",
                                  "pcd-three-points"])
def test_segment_cloud_refuses_them_in_one_line(tmp_path, capsys, name):
    from semcal_ros.cli import main

    path, expected = _damaged(tmp_path)[name]
    code = main(["segment-cloud", "--method", "geometric", str(path), "--out",
                 str(tmp_path / "out.ply")])
    err = capsys.readouterr().err
    assert code == 1 and err.count("\n") == 1 and expected in err, err
    assert not (tmp_path / "out.ply").exists()
