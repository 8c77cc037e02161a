"""The one-line messages a user reads say what happened, once, and where (issue 47)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from app.cli import main
from vo_core.direct.divergence import DivergenceConfig, Verdict, judge
from vo_core.direct.odometry import DirectTracking
from vo_core.datasets.tum_rgbd import read_image_list
from vo_core.errors import InputError


def tracking_after(intervals_missed: float | None) -> DirectTracking:
    """A converged alignment whose image moved 20x the last frames' median, after a gap or none."""
    return DirectTracking(reference=None, result=SimpleNamespace(success=True, rmse_after=9.0), rmse_before=10.0,
                          rmse_end=9.0, saturated_end=0.1, achieved_rmse=np.array([9.0]), last_rmse=8.0, good_enough=True, hypotheses_tried=1,
                          from_prior=False, ms=1.0, intervals_missed=intervals_missed, image_motion_px=200.0,
                          typical_motion_px=10.0)


def test_a_jump_after_a_gap_the_timestamps_show_is_not_called_one_they_do_not_show():
    judgement = judge(tracking_after(intervals_missed=21.0), DivergenceConfig())
    assert judgement.verdict is Verdict.SUSPECT and judgement.jump
    assert "frames were missed" in judgement.reason
    assert "the timestamps do not show" not in judgement.reason


def test_a_jump_without_a_gap_is_one_the_timestamps_do_not_show():
    judgement = judge(tracking_after(intervals_missed=None), DivergenceConfig())
    assert judgement.verdict is Verdict.SUSPECT and judgement.jump
    assert "a jump the timestamps do not show" in judgement.reason
    assert "frames were missed" not in judgement.reason


def test_timestamps_out_of_order_name_their_line_in_rgb_txt(tmp_path):
    lines = ["# color images", "# file: 'rgbd_dataset.bag'", "# timestamp filename"]
    lines += [f"{100 + i / 30:.6f} rgb/{i}.png" for i in range(60)]
    lines[54] = f"{90.0:.6f} rgb/51.png"  # line 55 of the file, the 52nd entry
    (tmp_path / "rgb.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as raised:
        read_image_list(tmp_path / "rgb.txt")
    assert str(raised.value) == f"{tmp_path / 'rgb.txt'}:55: timestamp 90.000000000 is out of order"


def test_a_malformed_drop_is_said_with_one_prefix(capsys):
    assert main(["run", "--drop", "10"]) == 2
    assert capsys.readouterr().err.strip() == ("fdmo: error: --drop 10: expected FRAME:COUNT, two integers "
                                               "(see fdmo run --help)")


def test_a_malformed_config_names_the_line(tmp_path, capsys):
    config = tmp_path / "config.yaml"
    config.write_text("seed: 1\ndirect:\n  point_density: [1500\nmethod: fdmo\n")
    assert main(["run", "--config", str(config)]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith(f"fdmo: error: {config}:4: malformed YAML (") and "\n" not in error
