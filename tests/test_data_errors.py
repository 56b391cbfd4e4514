"""Every bad input is a one-line DynslamError naming the file; the CLI exits 2 without traceback."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_data_helpers import data_cfg, make_folder
from typer.testing import CliRunner

from dynslam_cli.cli import app
from dynslam_cli.config import load_config
from dynslam_cli.data.open import open_sequence
from dynslam_cli.errors import DynslamError

CFG = {"intrinsics": [30.0, 30.0, 16.0, 12.0]}


def fails(folder: Path, *fragments: str, **data) -> str:
    with pytest.raises(DynslamError) as info:
        open_sequence(str(folder), data_cfg(**{**CFG, **data}))[0]
    msg = str(info.value)
    assert "\n" not in msg
    for frag in fragments:
        assert frag in msg, f"{frag!r} not in {msg!r}"
    return msg


def test_missing_folder(tmp_path: Path):
    fails(tmp_path / "nope", str(tmp_path / "nope"), "does not exist")


def test_missing_and_empty_rgb_txt(tmp_path: Path):
    d = make_folder(tmp_path / "s", n=2)
    (d / "rgb.txt").unlink()
    fails(d, str(d / "rgb.txt"), "not found")
    (d / "rgb.txt").write_text("# only a comment\n\n")
    fails(d, str(d / "rgb.txt"), "lists no images")
    d2 = make_folder(tmp_path / "s2", n=2)
    (d2 / "depth.txt").unlink()
    fails(d2, str(d2 / "depth.txt"), "not found")


@pytest.mark.parametrize("fname, line, bad, where", [
    ("rgb.txt", 3, "abc rgb/x.png", "rgb.txt:3"),
    ("rgb.txt", 4, "0.1", "rgb.txt:4"),
    ("depth.txt", 2, "0.0 depth/a.png extra", "depth.txt:2"),
    ("groundtruth.txt", 3, "0.0 1 2 3 0 0 1", "groundtruth.txt:3"),
    ("groundtruth.txt", 4, "0.1 1 2 3 0 0 zero 1", "groundtruth.txt:4"),
    ("groundtruth.txt", 3, "0.0 1 2 3 0 0 0 0", "groundtruth.txt:3"),
])
def test_malformed_lines(tmp_path: Path, fname, line, bad, where):
    d = make_folder(tmp_path / "s", n=3)
    lines = (d / fname).read_text().splitlines()
    lines[line - 1] = bad
    (d / fname).write_text("\n".join(lines) + "\n")
    fails(d, str(d / fname) + where[len(fname):])


def test_malformed_associations(tmp_path: Path):
    d = make_folder(tmp_path / "s", n=2)
    (d / "associations.txt").write_text("0.000000 rgb/0.000000.png 0.000000\n")
    fails(d, str(d / "associations.txt") + ":1", "malformed")


def test_listed_image_absent(tmp_path: Path):
    d = make_folder(tmp_path / "s", n=3)
    (d / "depth" / "0.100000.png").unlink()
    fails(d, str(d / "depth" / "0.100000.png"), "depth.txt", "line 3", "missing")


def test_undecodable_image(tmp_path: Path):
    d = make_folder(tmp_path / "s", n=2)
    (d / "rgb" / "0.000000.png").write_bytes(b"\x89PNG\r\n\x1a\nthis is not an image")
    fails(d, "cannot decode", str(d / "rgb" / "0.000000.png"), "frame 0")
    d2 = make_folder(tmp_path / "s2", n=2)
    (d2 / "depth" / "0.000000.png").write_bytes(b"")
    fails(d2, "cannot decode", str(d2 / "depth" / "0.000000.png"))


def test_depth_wrong_dtype_and_size(tmp_path: Path):
    import cv2

    d = make_folder(tmp_path / "s", n=2)
    cv2.imwrite(str(d / "depth" / "0.000000.png"), np.zeros((24, 32), np.uint8))
    fails(d, str(d / "depth" / "0.000000.png"), "uint16", "uint8")
    cv2.imwrite(str(d / "depth" / "0.000000.png"), np.zeros((24, 32, 3), np.uint16))
    fails(d, str(d / "depth" / "0.000000.png"), "uint16", "3 channels")
    cv2.imwrite(str(d / "depth" / "0.000000.png"), np.zeros((20, 32), np.uint16))
    fails(d, str(d / "depth" / "0.000000.png"), "32x20", "expected 32x24")


def test_timestamps_do_not_associate(tmp_path: Path):
    d = make_folder(tmp_path / "s", rgb_ts=[0.0, 0.1], depth_ts=[5.0, 5.1])
    fails(d, "no rgb/depth timestamps", str(d / "rgb.txt"), str(d / "depth.txt"), "max_time_diff=0.02 s")
    fails(d, "max_time_diff=0.5 s", max_time_diff=0.5)


@pytest.mark.parametrize("rgb_ts, depth_ts, where, how", [
    ([0.0, 0.2, 0.1], None, "rgb.txt:5", "0.100000 is earlier than 0.200000 on line 4"),
    ([0.0, 0.1, 0.1, 0.2], [0.0, 0.1, 0.15, 0.2], "rgb.txt:5", "0.100000 repeats 0.100000 on line 4"),
    ([0.0, 0.1, 0.2], [0.0, 0.2, 0.1], "depth.txt:4", "0.100000 is earlier than 0.200000 on line 3"),
])
def test_unsorted_or_repeated_list_timestamps(tmp_path: Path, rgb_ts, depth_ts, where, how):
    d = make_folder(tmp_path / "s", rgb_ts=rgb_ts, depth_ts=depth_ts)
    fails(d, str(d / where), how, "sorted by time")


def test_unsorted_associations_and_groundtruth(tmp_path: Path):
    d = make_folder(tmp_path / "s", n=3)
    lines = [f"{t} rgb/{t}.png {t} depth/{t}.png" for t in ("0.000000", "0.200000", "0.100000")]
    (d / "associations.txt").write_text("\n".join(lines) + "\n")
    fails(d, str(d / "associations.txt") + ":3", "rgb timestamp 0.100000 is earlier than 0.200000 on line 2")
    lines = [f"{t} rgb/{t}.png {u} depth/{u}.png" for t, u in
             (("0.000000", "0.000000"), ("0.100000", "0.200000"), ("0.200000", "0.100000"))]
    (d / "associations.txt").write_text("\n".join(lines) + "\n")
    fails(d, str(d / "associations.txt") + ":3", "depth timestamp 0.100000 is earlier")
    d2 = make_folder(tmp_path / "s2", n=3, gt_ts=[0.0, 0.1, 0.1])
    fails(d2, str(d2 / "groundtruth.txt") + ":5", "0.100000 repeats 0.100000 on line 4")


def test_association_running_backwards(tmp_path: Path):
    # each list is sorted, but with a wide max_time_diff the nearest pairs cross: rgb 0.0 <-> depth 0.19,
    # rgb 0.1 <-> depth 0.09
    d = make_folder(tmp_path / "s", rgb_ts=[0.0, 0.1], depth_ts=[0.09, 0.19])
    fails(d, str(d / "depth.txt") + ":2", "depth 0.090000 pairs with rgb 0.100000", "runs backwards",
          "max_time_diff=0.5", max_time_diff=0.5)
    assert len(open_sequence(str(d), data_cfg(**CFG, max_time_diff=0.05))) == 1


def test_cli_unsorted_rgb_txt(tmp_path: Path):
    d = make_folder(tmp_path / "s", rgb_ts=[0.0, 0.2, 0.1])
    before = (d / "rgb.txt").read_bytes()
    _assert_cli_error(runner.invoke(app, ["info", "--seq", str(d), "--set", "data.intrinsics=[30,30,16,12]"]),
                      str(d / "rgb.txt") + ":5", "is earlier than")
    assert (d / "rgb.txt").read_bytes() == before


def test_no_intrinsics_for_generic_folder(tmp_path: Path):
    d = make_folder(tmp_path / "s", n=2)
    fails(d, "no camera intrinsics", str(d), "data.intrinsics", intrinsics=None)
    fails(d, "4 numbers", intrinsics=[1, 2, 3])
    fails(d, "data.distortion", distortion=[0.1, 0.2, 0.3])


def test_bad_cut(tmp_path: Path):
    d = make_folder(tmp_path / "s", n=3)
    fails(d, "data.start=3", "3 frames", str(d / "rgb.txt"), start=3)
    fails(d, "data.stride", stride=0)
    fails(d, "data.frames", frames=-1)


def test_bad_synth_folder(tmp_path: Path):
    d = make_folder(tmp_path / "s", n=2, synth={"intrinsics": [20, 20, 8, 6]}, masks=True)
    (d / "dynamic" / "0.100000.png").unlink()
    fails(d, "dynamic image", str(d / "dynamic" / "0.100000.png"), intrinsics=None)
    (d / "synth.json").write_text("{not json")
    fails(d, str(d / "synth.json"), intrinsics=None)


def test_unknown_and_missing_names(tmp_path: Path):
    cfg = load_config("tum", "nope", overrides=[f"data.root={tmp_path}"])
    with pytest.raises(DynslamError, match=r"unknown sequence 'tum/nope'.*fr3_walking_xyz"):
        open_sequence("tum/nope", cfg)
    cfg = load_config("bonn", "crowd", overrides=[f"data.root={tmp_path}"])
    with pytest.raises(DynslamError) as info:
        open_sequence("bonn/crowd", cfg)
    msg = str(info.value)
    assert str(tmp_path / "rgbd_bonn_crowd") in msg and "dynslam download bonn/crowd" in msg
    with pytest.raises(DynslamError, match="unknown sequence 'bonn/ballon'.*balloon"):
        open_sequence("bonn/ballon", cfg)


# ------------------------------------------------------------------------------ CLI
runner = CliRunner()


def _assert_cli_error(result, *fragments):
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    err = result.stderr if hasattr(result, "stderr") else result.output
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for frag in fragments:
        assert frag in lines[0]


def test_cli_info_bonn_clip(bonn_clip: Path):
    res = runner.invoke(app, ["info", "--seq", str(bonn_clip)])
    assert res.exit_code == 0, res.output
    assert "150 (of 150 associated pairs)" in res.output
    assert "fx 542.823  fy 542.577  cx 315.594  cy 237.756" in res.output
    assert "640x480" in res.output and "150/150 frames with a pose" in res.output
    res = runner.invoke(app, ["info", "--seq", str(bonn_clip), "--json", "--frames", "20", "--stride", "2"])
    assert res.exit_code == 0, res.output
    info = json.loads(res.stdout if hasattr(res, "stdout") else res.output)
    assert info["frames"] == 20 and info["dataset"] == "bonn" and info["width"] == 640
    assert info["intrinsics"] == pytest.approx([542.822841, 542.576870, 315.593520, 237.756098])
    assert 0.3 < info["depth_valid_fraction"] <= 1.0 and 0.5 < info["depth_median"] < 5.0
    assert info["gt_frames"] == 20 and info["has_gt_masks"] is False and len(info["depth_sampled_frames"]) == 10


def test_cli_info_tum_frames(tum_clip: Path):
    res = runner.invoke(app, ["info", "--seq", str(tum_clip), "--start", "2", "--frames", "3"])
    assert res.exit_code == 0, res.output
    assert "3 (of 9 associated pairs)" in res.output and "fx 517.3" in res.output
    assert "2335 poses" in res.output and "undistorted on load" in res.output


def test_cli_info_synthetic_folder(tmp_path: Path):
    d = make_folder(tmp_path / "scene", n=4, synth={"intrinsics": [20.0, 21.0, 8.0, 6.0]}, masks=True)
    res = runner.invoke(app, ["info", "--seq", str(d)])
    assert res.exit_code == 0, res.output
    assert "synth/scene" in res.output and "gt masks     yes (+ instance ids)" in res.output
    assert "4/4 frames with a pose" in res.output


def test_cli_info_errors(tmp_path: Path):
    _assert_cli_error(runner.invoke(app, ["info", "--seq", "tum/nope", "--data-root", str(tmp_path)]),
                      "unknown sequence 'tum/nope'")
    _assert_cli_error(runner.invoke(app, ["info", "--seq", "tum/fr3_walking_xyz", "--data-root", str(tmp_path)]),
                      "dynslam download tum/fr3_walking_xyz", str(tmp_path))
    d = make_folder(tmp_path / "s", n=2)
    (d / "rgb" / "0.100000.png").unlink()
    _assert_cli_error(runner.invoke(app, ["info", "--seq", str(d), "--set", "data.intrinsics=[30,30,16,12]"]),
                      str(d / "rgb" / "0.100000.png"))
    d2 = make_folder(tmp_path / "s2", n=2)
    _assert_cli_error(runner.invoke(app, ["info", "--seq", str(d2)]), "no camera intrinsics")
    _assert_cli_error(runner.invoke(app, ["info", "--seq", str(tmp_path / "absent")]), "does not exist")
