"""The saved-mask reader of benchmarks/bench_backend.py (``--masks run:DIR``; the benchmark itself is run by hand)."""

import cv2
import numpy as np
import pytest

import benchmark_scripts  # tests/benchmark_scripts.py

B = benchmark_scripts.load("bench_backend")


class TestRunMasker:
    def test_dilates_the_saved_mask_like_the_run(self, tmp_path):
        (tmp_path / "masks").mkdir()
        m = np.zeros((48, 64), np.uint8)
        m[20, 30] = 255
        cv2.imwrite(str(tmp_path / "masks" / "1.5.png"), m)
        mask = B.run_masker(tmp_path / "masks", 2 / 64)("1.5")  # 2 px at 64 px width
        assert mask.shape == (48, 64) and mask.dtype == bool
        assert mask.sum() == 25 and mask[18:23, 28:33].all()  # the square the run's static mask leaves out

    def test_no_dilation(self, tmp_path):
        (tmp_path / "masks").mkdir()
        m = np.zeros((8, 8), np.uint8)
        m[1, 1] = 255
        cv2.imwrite(str(tmp_path / "masks" / "0.png"), m)
        assert B.run_masker(tmp_path / "masks", 0.0)("0").sum() == 1

    def test_missing_folder_and_frame_are_clear_errors(self, tmp_path):
        with pytest.raises(SystemExit, match="no saved masks"):
            B.run_masker(tmp_path / "absent", 0.01)
        (tmp_path / "masks").mkdir()
        with pytest.raises(SystemExit, match="missing mask"):
            B.run_masker(tmp_path / "masks", 0.01)("7.0")


class TestRunDilation:
    def test_read_from_the_runs_config_else_the_default(self, tmp_path):
        assert B.run_dilation(tmp_path, 0.008) == 0.008  # no config.yaml
        (tmp_path / "config.yaml").write_text("motion:\n  mask_dilation: 0.02\n  segmenter: geometric\n")
        assert B.run_dilation(tmp_path, 0.008) == 0.02
        (tmp_path / "config.yaml").write_text("run:\n  seed: 1\n")
        assert B.run_dilation(tmp_path, 0.008) == 0.008
