"""Flow estimators (priors/flow.py) and flow metrics (evaluate/flow_metrics.py)."""

import numpy as np
import pytest

from endogsim.errors import ModelError
from endogsim.evaluate.flow_metrics import epe, flow_to_color, warp_backward
from endogsim.priors.flow import DISFlow, FineDISFlow, FlowConfig, flow_estimator


def _texture(h=128, w=160, seed=0):
    import cv2

    rng = np.random.default_rng(seed)
    img = rng.uniform(0, 1, (h // 4, w // 4, 3)).astype(np.float32)
    return np.clip(cv2.resize(img, (w, h), interpolation=cv2.INTER_CUBIC), 0, 1)


def test_dis_recovers_translation():
    import cv2

    a = _texture()
    d = np.array([2.5, -1.5])
    M = np.float32([[1, 0, d[0]], [0, 1, d[1]]])
    b = cv2.warpAffine(a, M, (a.shape[1], a.shape[0]), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    flow = DISFlow("medium").estimate(a, b)
    assert flow.shape == (128, 160, 2) and flow.dtype == np.float32
    inner = np.zeros(flow.shape[:2], bool)
    inner[10:-10, 10:-10] = True
    gt = np.broadcast_to(d.astype(np.float32), flow.shape)
    assert epe(flow, gt, inner) < 0.3
    assert epe(np.zeros_like(gt), gt, inner) == pytest.approx(np.hypot(*d), rel=1e-6)


def test_raft_without_weights_is_a_clear_error(tmp_path):
    with pytest.raises(ModelError, match="weights"):
        flow_estimator(FlowConfig("raft"))
    missing = tmp_path / "raft_large.pth"
    with pytest.raises(ModelError, match="raft_large.pth"):
        flow_estimator(FlowConfig("raft", weights=str(missing)))


def test_factory_rejects_unknown_names():
    with pytest.raises(ModelError, match="unknown optical-flow estimator 'farneback-9000'; use one of dis, dis_fine, raft"):
        FlowConfig("farneback-9000")
    with pytest.raises(ModelError, match="preset"):
        DISFlow("slowest")
    assert isinstance(flow_estimator(FlowConfig("dis")), DISFlow)
    assert isinstance(flow_estimator(FlowConfig("dis_fine")), FineDISFlow)


def test_epe_uses_valid_pixels_only():
    gt = np.zeros((4, 5, 2), np.float32)
    est = gt.copy()
    est[0, 0] = (3, 4)  # error 5 at one pixel
    valid = np.ones((4, 5), bool)
    assert epe(est, gt, valid) == pytest.approx(5 / 20)
    valid[0, 0] = False
    assert epe(est, gt, valid) == 0.0
    assert np.isnan(epe(est, gt, np.zeros_like(valid)))


def test_flow_to_color_and_warp():
    f = np.zeros((8, 8, 2), np.float32)
    f[:, 4:, 0] = 1.0
    c = flow_to_color(f)
    assert c.shape == (8, 8, 3) and c.min() >= 0 and c.max() <= 1
    assert np.allclose(c[:, :4], 1.0)  # zero flow is white
    assert not np.allclose(c[:, 4:], 1.0)
    # warp_backward(I_t+1, flow) = I_t for an exact integer shift.
    a = _texture(32, 40)
    b = np.roll(a, 2, axis=1)
    flow = np.zeros((32, 40, 2), np.float32)
    flow[..., 0] = 2
    assert np.abs(warp_backward(b, flow)[:, :-3] - a[:, :-3]).max() < 1e-5
