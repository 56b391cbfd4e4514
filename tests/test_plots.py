"""Figures (eval/plots.py): the montage finds a real Bonn run's input images, depth panels share one
scale with a colour bar, ate.png and the update curves name the run and label the estimate."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dynslam_cli.errors import DynslamError
from dynslam_cli.eval import plots


@pytest.fixture()
def figures(monkeypatch):
    """The figures the plot functions save (kept open until the test ends)."""
    saved = []

    def keep(fig, out_png):
        saved.append(fig)
        fig.canvas.draw()
        with plots.atomic_path(out_png) as tmp:
            fig.savefig(tmp)
        return Path(out_png)

    monkeypatch.setattr(plots, "_save", keep)
    yield saved
    for fig in saved:
        plots._plt().close(fig)


def _write_run(d: Path, seq: dict, frames: int, data: dict, mode: str = "dynamic") -> Path:
    import yaml

    d.mkdir(parents=True, exist_ok=True)
    (d / "run.json").write_text(json.dumps({"status": "completed", "sequence": seq, "mode": mode,
                                            "variant": mode, "frames": frames, "seed": 0}))
    (d / "config.yaml").write_text(yaml.safe_dump({"data": data}))
    return d


@pytest.fixture()
def bonn_run(tmp_path, bonn_clip):
    """A run folder on the real Bonn clip (start 10, stride 20) with masks and renders of 3 frames,
    named by the stamps the sequence reader gives the runner (run/loop.py names files by them)."""
    import cv2

    from dynslam_cli.config.loader import load_config
    from dynslam_cli.data.open import open_sequence

    seq = open_sequence(str(bonn_clip), load_config("bonn", "crowd", overrides=["data.start=10", "data.stride=20"]))
    d = _write_run(tmp_path / "run", {"dataset": "bonn", "name": "crowd_150_449_s2", "path": str(bonn_clip)},
                   len(seq), {"start": 10, "stride": 20, "frames": 0, "depth_scale": 5000.0, "max_time_diff": 0.02})
    (d / "masks").mkdir()
    (d / "renders").mkdir()
    for i in (0, 3, 6):
        rec = seq.records[i]
        mask = np.zeros((480, 640), np.uint8)
        mask[100:300, 200:320] = 255
        cv2.imwrite(str(d / "masks" / f"{seq.stamps[i]}.png"), mask)
        depth = cv2.imread(str(rec.depth), cv2.IMREAD_UNCHANGED)  # the check renders at half width
        cv2.imwrite(str(d / "renders" / f"{seq.stamps[i]}_depth.png"), depth[::2, ::2])
    return d, seq


def test_montage_of_a_real_bonn_run_shows_the_inputs(bonn_run, figures, tmp_path):
    import cv2

    d, seq = bonn_run
    assert seq.stamps[0] != Path(seq.records[0].rgb).stem  # the case the user hit: 1548….902700 vs 1548….90270
    res = plots.make_montage(d, tmp_path / "m.png")
    assert res.path.stat().st_size > 10_000
    assert [r.stamp for r in res.rows] == [seq.stamps[i] for i in (0, 3, 6)]
    assert [r.index for r in res.rows] == [0, 3, 6]
    for r, i in zip(res.rows, (0, 3, 6), strict=True):
        assert r.missing == {}
        assert r.files["input RGB"] == seq.records[i].rgb and r.files["input depth"] == seq.records[i].depth
    fig = figures[0]
    axes = fig.axes[:12]
    rgb_img = axes[0].get_images()[0].get_array()
    want = cv2.imread(str(seq.records[0].rgb))[..., ::-1]
    assert rgb_img.shape == (480, 640, 3) and np.array_equal(np.asarray(rgb_img), want) and want.std() > 10
    # one depth scale for all input and rendered depth panels, holes masked, and a colour bar in metres
    depth_ims = [ax.get_images()[0] for k, ax in enumerate(axes) if k % 4 in (1, 2)]
    assert len(depth_ims) == 6
    assert {im.get_clim() for im in depth_ims} == {(0.0, res.depth_max_m)}
    assert 2.0 <= res.depth_max_m <= 10.0
    inp = depth_ims[0].get_array()
    raw = cv2.imread(str(seq.records[0].depth), cv2.IMREAD_UNCHANGED)
    assert np.allclose(inp.filled(0), raw / 5000.0) and inp.mask.sum() == (raw == 0).sum()
    bars = [ax for ax in fig.axes if "depth (m)" in ax.get_xlabel() + ax.get_ylabel()]
    assert len(bars) == 1
    # the render (half size) is drawn over the input's extent
    assert depth_ims[1].get_extent() == [0, 640, 480, 0]
    # the title names the sequence, mode and frame range
    title = fig._suptitle.get_text()
    assert "bonn/crowd_150_449_s2" in title and "dynamic" in title
    assert f"frames 10–{10 + 20 * (len(seq) - 1)} step 20 ({len(seq)} frames)" in title
    assert "frame 3" in axes[4].get_ylabel()
    assert "dynamic)" in axes[3].get_title()


def test_montage_frame_choice_by_timestamp_and_index(bonn_run, figures, tmp_path):
    d, seq = bonn_run
    short = f"{float(seq.stamps[3]):.4f}"  # typed with fewer digits: matched numerically
    res = plots.make_montage(d, tmp_path / "a.png", frames=[short])
    assert [r.stamp for r in res.rows] == [seq.stamps[3]]
    res = plots.make_montage(d, tmp_path / "b.png", indices=[6, 0])
    assert [r.stamp for r in res.rows] == [seq.stamps[6], seq.stamps[0]]
    with pytest.raises(DynslamError, match=r"no mask for frame\(s\) 12345.5 in .*masks \(masks at"):
        plots.make_montage(d, tmp_path / "c.png", frames=["12345.5"])
    with pytest.raises(DynslamError, match=r"no mask for frame index\(es\) 1 in"):
        plots.make_montage(d, tmp_path / "c.png", indices=[1])  # frame 1 exists but saved no mask
    assert not (tmp_path / "c.png").exists()


def test_plot_cli_bad_frame_leaves_the_montage(bonn_run, figures):
    from typer.testing import CliRunner

    from dynslam_cli.cli import app

    d, seq = bonn_run
    r = CliRunner().invoke(app, ["plot", str(d)])
    assert r.exit_code == 0, r.output
    before = (d / "montage.png").read_bytes()
    r = CliRunner().invoke(app, ["plot", str(d), "--frames", "1.5"])
    assert r.exit_code == 2
    assert r.output.strip().splitlines() == [f"error: no mask for frame(s) 1.5 in {d / 'masks'} "
                                             f"(masks at {seq.stamps[0]} … {seq.stamps[6]}, 3 files)"]
    assert (d / "montage.png").read_bytes() == before
    r = CliRunner().invoke(app, ["plot", str(d), "--index", "0,x"])
    assert r.exit_code == 2
    assert r.output.strip().splitlines() == ["error: --index takes comma-separated frame indices, got '0,x'"]
    assert (d / "montage.png").read_bytes() == before
    r = CliRunner().invoke(app, ["plot", str(d), "--index", "6", "--out", str(d / "six.png")])
    assert r.exit_code == 0, r.output
    assert (d / "six.png").is_file()


def test_montage_without_the_sequence_says_why(tmp_path, figures):
    import cv2

    d = _write_run(tmp_path / "run", {"dataset": "bonn", "name": "crowd", "path": str(tmp_path / "gone")}, 5, {})
    (d / "masks").mkdir()
    cv2.imwrite(str(d / "masks" / "5.000000.png"), np.full((12, 16), 255, np.uint8))
    res = plots.make_montage(d, tmp_path / "m.png")
    row = res.rows[0]
    assert set(row.files) == {"motion mask"}
    assert row.missing["input RGB"] == f"sequence folder {tmp_path / 'gone'} not found"
    assert row.missing["rendered depth"] == "not saved: 5.000000_depth.png"
    assert "100% dynamic" in figures[0].axes[3].get_title()
    (d / "masks" / "5.000000.png").unlink()
    assert plots.make_montage(d, tmp_path / "n.png") is None


def _ate_run(tmp_path: Path):
    from dynslam_cli.eval.ate import compute_ate

    t = 100 + np.arange(40) / 30
    s = np.linspace(0, 3, 40)
    gt = np.column_stack([t, np.cos(s), np.sin(s), 0.1 * s, np.tile([0, 0, 0, 1.0], (40, 1))])
    est = gt.copy()
    est[:, 1:4] += 0.02 * np.random.default_rng(0).standard_normal((40, 3))
    np.savetxt(tmp_path / "gt.txt", gt)
    d = _write_run(tmp_path / "run", {"dataset": "tum", "name": "fr3_walking_xyz"}, 40, {"start": 5, "stride": 2})
    np.savetxt(d / "traj_est.txt", est)
    return d, compute_ate(d / "traj_est.txt", tmp_path / "gt.txt", "se3", 0.02)


def test_ate_png_names_the_run_and_labels_the_estimate(tmp_path, figures):
    d, res = _ate_run(tmp_path)
    plots.plot_ate(res, d / "ate.png")  # the run folder is found beside ate.png
    ax = figures[0].axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["ground truth", "estimate (se3-aligned, colour = error)", "estimate start"]
    title = ax.get_title()
    assert title.splitlines()[0] == "tum/fr3_walking_xyz, dynamic, frames 5–83 step 2 (40 frames), seed 0"
    assert f"ATE RMSE {res.rmse_m:.4f} m" in title and f"still camera {res.rmse_still_m:.3f} m" in title
    assert any("error (m)" in a.get_ylabel() for a in figures[0].axes[1:])
    # an explicit title keeps the run line; a folder without run.json gets the title alone
    plots.plot_ate(res, tmp_path / "elsewhere.png", title="custom")
    assert figures[1].axes[0].get_title() == "custom"
    plots.plot_ate(res, tmp_path / "x.png", title="custom", run_dir=d)
    assert figures[2].axes[0].get_title().splitlines() == [title.splitlines()[0], "custom"]


def test_update_curves_name_sequence_and_frames(tmp_path, figures):
    from dynslam_cli.eval.tables import RunRecord

    recs = []
    for seed, replay in ((0, True), (1, False)):
        d = _write_run(tmp_path / f"r{seed}", {"dataset": "bonn", "name": "crowd"}, 30, {"start": 0, "stride": 2})
        recs.append(RunRecord(d, "bonn/crowd", "dynamic", seed, "hist", "geometric", replay, False,
                              updates=[3, 10, 20]))
    paths = plots.plot_updates(recs, tmp_path / "out")
    assert paths == [tmp_path / "out" / "plots" / "classifier_updates_bonn-crowd.png"] and paths[0].is_file()
    ax = figures[0].axes[0]
    assert ax.get_title() == "bonn/crowd: classifier updates, dynamic mode\nframes 0–58 step 2 (30 frames)"
    line = ax.get_lines()[0]
    assert list(line.get_xdata()) == [0, 3, 10, 20, 29] and list(line.get_ydata()) == [0, 1, 2, 3, 3]
    assert [t.get_text() for t in ax.get_legend().get_texts()] == [
        "with replay, seed 0 (3 updates)", "without replay, seed 1 (3 updates)"]


def test_ate_png_with_a_corrupt_run_json_still_written(tmp_path, figures):
    d, res = _ate_run(tmp_path)
    (d / "run.json").write_text("{broken")
    plots.plot_ate(res, d / "ate.png")
    assert (d / "ate.png").is_file() and figures[0].axes[0].get_title().startswith("ATE RMSE")
