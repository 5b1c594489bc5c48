"""``endogsim demo``: the preview render runs from the CLI and writes a playable video and PNG frames."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
from typer.testing import CliRunner

from endogsim.cli.main import app


def test_demo_writes_video_and_frames(tmp_path):
    res = CliRunner().invoke(app, ["demo", "--preview", "--out", str(tmp_path), "--preview-frames", "3"])
    assert res.exit_code == 0, res.output
    pngs = sorted((tmp_path / "frames").glob("*.png"))
    assert len(pngs) == 3
    img = iio.imread(pngs[1])
    assert img.shape == (256, 320, 3)
    # Tissue fills the view: reddish on average, and the tool adds grey pixels.
    mean = img.reshape(-1, 3).mean(0)
    assert mean[0] > 1.3 * mean[1] and mean[0] > 60
    video = iio.imread(tmp_path / "render.mp4")
    assert video.shape[0] == 3 and np.abs(video[1].astype(float) - img).mean() < 20  # lossy codec


def test_demo_rejects_bad_options(tmp_path):
    res = CliRunner().invoke(app, ["demo", "--preview", "--out", str(tmp_path), "--preview-frames", "1"])
    assert res.exit_code != 0 and "--preview-frames" in res.output
