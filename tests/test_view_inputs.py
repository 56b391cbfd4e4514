"""dynslam_cli.view.inputs: what `dynslam view` reads from a run folder."""

import numpy as np
import pytest

from dynslam_cli.errors import DynslamError
from dynslam_cli.view import inputs


class TestStampedFiles:
    def test_numeric_names_only_sorted(self, tmp_path):
        for name in ("2.5.png", "10.0.png", "notes.png", "1.0_depth.png"):
            (tmp_path / name).write_bytes(b"")
        stamps, paths = inputs.stamped_files(tmp_path, ".png")
        assert sorted(stamps) == [2.5, 10.0] and {p.name for p in paths} == {"2.5.png", "10.0.png"}
        assert inputs.stamped_files(tmp_path / "none", ".png") == ([], [])


class TestUpdates:
    def test_frames_by_timestamp_then_index(self, tmp_path):
        t_est = np.array([0.0, 0.1, 0.2, 0.3])
        ups = [{"timestamp": "0.2"}, {"frame": 3}, {"timestamp": 9.0}, {"frame": 7}]
        assert inputs.update_frames(ups, t_est) == [2, 3, None, None]

    def test_corrupt_line_is_one_error(self, tmp_path):
        p = tmp_path / "classifier_updates.jsonl"
        p.write_text('{"frame": 1}\n\n[1, 2]\n')
        with pytest.raises(DynslamError, match="line 3: expected a JSON object"):
            inputs.read_updates(p)


class TestReadImage:
    def test_resized_to_the_camera_and_uint16_checked(self, tmp_path):
        import cv2

        cv2.imwrite(str(tmp_path / "m.png"), np.full((12, 16), 255, np.uint8))
        assert inputs.read_image(tmp_path / "m.png", "mask", (32, 24)).shape == (24, 32)
        with pytest.raises(DynslamError, match="must be single-channel uint16"):
            inputs.read_image(tmp_path / "m.png", "render", (16, 12), uint16=True)
