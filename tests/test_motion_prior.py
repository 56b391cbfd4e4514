"""`dynslam prior fit`: from a synthetic scene folder and from photos with the YOLO model."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from dynslam_cli.cli import app
from dynslam_cli.config import Config
from dynslam_cli.errors import DynslamError
from dynslam_cli.motion.prior import background_pieces, fit_prior
from dynslam_cli.motion.toyscene import render_toy

torch = pytest.importorskip("torch")


def _write_scene(folder, n=8, w=160, h=120):
    """A scene folder in the synthetic layout: the person walks (dynamic), the box stays."""
    for sub in ("rgb", "depth", "instances", "dynamic"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    (folder / "synth.json").write_text(json.dumps({"depth_scale": 5000}))
    for i in range(n):
        rgb, depth, gt = render_toy(w, h, person_x=-0.6 + 0.15 * i, box_x=0.3 + 0.1 * (i % 3), seed=i)
        name = f"{i:06d}.png"
        cv2.imwrite(str(folder / "rgb" / name), rgb[..., ::-1])
        cv2.imwrite(str(folder / "depth" / name), (depth * 5000).astype(np.uint16))
        cv2.imwrite(str(folder / "instances" / name), gt.astype(np.uint16))
        cv2.imwrite(str(folder / "dynamic" / name), np.where(gt == 1, 255, 0).astype(np.uint8))
    return folder


def test_prior_fit_cli_from_synthetic_folder(tmp_path):
    scene = _write_scene(tmp_path / "scene")
    out = tmp_path / "prior.pt"
    r = CliRunner().invoke(app, ["prior", "fit", "--out", str(out), "--synth", str(scene), "--steps", "200",
                                 "--set", "motion.encoder=color-hist"])
    assert r.exit_code == 0, r.output
    assert "held-out 1.000" in r.output and f"wrote {out}" in r.output
    # the prior loads into the module and calls the person dynamic, the room and box static
    from dynslam_cli.motion.classifier import load_prior
    from dynslam_cli.motion.encode_hist import ColorHistEncoder

    prior = load_prior(out, "color-hist", ColorHistEncoder().dim)
    rgb, depth, gt = render_toy(160, 120, person_x=0.5, seed=42)
    z = ColorHistEncoder().encode(rgb, gt)
    assert prior.predict(z).tolist() == [True, False]
    assert prior.meta["positives"] > 0


def test_prior_fit_errors(tmp_path):
    cfg = Config()
    cfg.motion.encoder = "color-hist"
    with pytest.raises(DynslamError, match="needs --images"):
        fit_prior(tmp_path / "p.pt", cfg)
    (tmp_path / "empty").mkdir()
    with pytest.raises(DynslamError, match="not a synthetic scene folder"):
        fit_prior(tmp_path / "p.pt", cfg, synth=[str(tmp_path / "empty")])
    r = CliRunner().invoke(app, ["prior", "fit", "--out", str(tmp_path / "p.pt"), "--images", str(tmp_path / "empty"),
                                 "--yolo", str(tmp_path / "no.onnx"), "--set", "motion.encoder=color-hist"])
    assert r.exit_code == 2 and "no images" in r.output
    assert not (tmp_path / "p.pt").exists()


def test_background_pieces():
    taken = np.zeros((90, 90), bool)
    taken[:, 30:60] = True
    pieces = background_pieces(taken, 3, 0.01)
    assert len(pieces) == 6 and not any((p & taken).any() for p in pieces)


def test_prior_fit_from_photos_with_yolo(tmp_path, yolo_model, shared_dir, monkeypatch):
    monkeypatch.setenv("DYNSLAM_CACHE", str(tmp_path / "cache"))
    cfg = Config()  # effnet-lite0 encoder
    r = fit_prior(tmp_path / "people.pt", cfg, images=shared_dir / "images", yolo=str(yolo_model), steps=200)
    assert r.positives >= 5  # 4 people on bus.jpg (one cut), 2 on zidane.jpg
    assert r.samples - r.positives >= 4  # the bus and background pieces
    assert r.train_accuracy == 1.0 and r.test_samples >= 2
    assert r.test_accuracy >= 0.5  # tiny held-out set: reported, loosely checked
    assert (tmp_path / "people.pt").is_file()
