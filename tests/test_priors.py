"""Depth and segmentation priors: dataset pass-through, offline fallbacks, clear errors without weights."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from endogsim.errors import DataError, ModelError
from endogsim.io.labels import endonerf_labels
from endogsim.io.scene import Scene
from endogsim.priors.depth import depth_anything_depth, estimate_depth, fallback_depth, pi3_depth
from endogsim.priors.segmentation import GreyToolConfig, grey_tool_mask, sam2_segmentation, segment_scene


def _scene(frames, depth=None, masks=None):
    t = frames.shape[0]
    K = np.array([[50.0, 0, frames.shape[2] / 2], [0, 50.0, frames.shape[1] / 2], [0, 0, 1]])
    return Scene(frames=frames.astype(np.float32), times=np.arange(t) / 30.0, K=K, depth=depth, object_masks=masks,
                 labels=endonerf_labels(masks is not None), source="synthetic")


def _tissue_with_grey_tool(h=96, w=128, seed=0):
    """Reddish, textured tissue with specular glints and a grey instrument shaft (ground-truth mask)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    tex = 0.5 + 0.2 * np.sin(xx / 5.0) * np.cos(yy / 7.0) + 0.05 * rng.standard_normal((h, w))
    img = np.stack([0.55 + 0.35 * tex, 0.25 + 0.2 * tex, 0.2 + 0.15 * tex], -1)
    # pale, low-saturation but warm tissue (fat / blanched): must not be a tool
    img[60:80, 10:40] = [0.85, 0.72, 0.70]
    for _ in range(12):  # small specular glints (white)
        y, x = rng.integers(0, h - 3), rng.integers(0, w // 2)
        img[y:y + 2, x:x + 2] = 0.98
    tool = np.zeros((h, w), np.uint8)
    cv2.line(tool, (w - 1, 10), (70, 60), 1, thickness=14)
    tool = tool.astype(bool)
    shade = 0.55 + 0.15 * (xx / w)
    img[tool] = np.stack([shade, shade, shade * 1.08], -1)[tool]
    return np.clip(img, 0, 1), tool


def test_fallback_tool_segmentation_finds_grey_tool():
    img, tool = _tissue_with_grey_tool()
    m = grey_tool_mask(img)
    inter, union = (m & tool).sum(), (m | tool).sum()
    assert inter / union > 0.8, inter / union
    assert not m[60:80, 10:40].any()  # pale warm tissue is not a tool
    assert (m & ~tool).sum() < 0.25 * tool.sum()  # only the dilated border outside the tool
    m8 = grey_tool_mask((img * 255).astype(np.uint8))
    assert (m8 == m).mean() > 0.99


def test_fallback_tool_mask_grows_into_reflective_metal_next_to_the_tool():
    """A dark reddish jaw (metal mirroring tissue) attached to the grey shaft joins the tool mask; the
    same colour far from any tool stays tissue."""
    img, tool = _tissue_with_grey_tool()
    jaw = np.zeros(tool.shape, np.uint8)
    cv2.circle(jaw, (68, 62), 5, 1, -1)
    far = np.zeros(tool.shape, np.uint8)
    cv2.circle(far, (20, 80), 5, 1, -1)
    for region in (jaw, far):
        img[region.astype(bool)] = (0.35, 0.2, 0.22)  # saturated, magenta-red, darker than the tissue
    m = grey_tool_mask(img)
    assert m[jaw.astype(bool)].mean() > 0.9
    assert not m[far.astype(bool)].any()
    without = grey_tool_mask(img, GreyToolConfig(grow_frac=0.0))
    assert without[jaw.astype(bool)].mean() < 0.5


def test_segment_scene_fallback_warns_and_labels():
    img, tool = _tissue_with_grey_tool()
    sc = _scene(np.stack([img, img]))
    with pytest.warns(UserWarning, match="colour"):
        seg = segment_scene(sc)
    assert seg.source == "fallback" and seg.masks.shape == (2, 96, 128)
    assert seg.labels[1].is_tool and seg.labels[1].name == "tool" and not seg.labels[0].is_tool
    assert set(np.unique(seg.masks)) <= {0, 1}


def test_segment_scene_uses_dataset_masks():
    img, tool = _tissue_with_grey_tool()
    masks = np.stack([tool, tool]).astype(np.int32)
    seg = segment_scene(_scene(np.stack([img, img]), masks=masks))
    assert seg.source == "dataset" and np.array_equal(seg.masks, masks)
    with pytest.raises(DataError, match="no masks"):
        segment_scene(_scene(np.stack([img])), method="dataset")
    with pytest.raises(ModelError, match="unknown segmentation method"):
        segment_scene(_scene(np.stack([img])), method="magic")


def test_sam2_without_checkpoint_gives_clear_error(tmp_path):
    img, _ = _tissue_with_grey_tool()
    with pytest.raises(ModelError, match="--seg-checkpoint"):
        sam2_segmentation(img[None], None, "configs/sam2.1/sam2.1_hiera_s.yaml")
    with pytest.raises(ModelError, match="--seg-checkpoint"):
        segment_scene(_scene(img[None]), method="sam2", checkpoint=tmp_path / "missing.pt")
    ckpt = tmp_path / "sam2.pt"
    ckpt.write_bytes(b"x")
    with pytest.raises(ModelError, match="seg-config"):
        sam2_segmentation(img[None], ckpt, None)


def test_fallback_depth_is_a_bowl_at_the_working_distance():
    K = np.array([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]])
    d = fallback_depth(K, 80, 60, num_frames=3, working_distance=0.08, bowl=0.2)
    assert d.shape == (3, 60, 80) and d.dtype == np.float32
    assert d[0, 30, 40] == pytest.approx(0.08, rel=1e-3)  # on the optical axis
    assert d[0, 0, 0] == pytest.approx(0.08 * 0.8, rel=2e-2)  # corner: bowl closer
    assert (d > 0).all() and np.allclose(d[0], d[2])
    with pytest.raises(DataError, match="working_distance"):
        fallback_depth(K, 80, 60, working_distance=-1.0)


def test_estimate_depth_dataset_and_fallback():
    f = np.zeros((2, 6, 8, 3))
    dep = np.full((2, 6, 8), 0.05, np.float32)
    p = estimate_depth(_scene(f, depth=dep))
    assert p.source == "dataset" and p.metric and np.array_equal(p.depth, dep)
    with pytest.warns(UserWarning, match="fallback"):
        p = estimate_depth(_scene(f))
    assert p.source == "fallback" and not p.metric and p.depth.shape == (2, 6, 8)
    with pytest.raises(DataError, match="no depth"):
        estimate_depth(_scene(f), method="dataset")
    with pytest.raises(ModelError, match="unknown depth method"):
        estimate_depth(_scene(f), method="lidar")


def test_depth_models_without_weights_give_clear_errors(tmp_path):
    f = np.zeros((1, 6, 8, 3))
    with pytest.raises(ModelError, match="--depth-weights"):
        pi3_depth(f, None)
    with pytest.raises(ModelError, match="--depth-weights"):
        depth_anything_depth(f, tmp_path / "missing.pth")
    with pytest.raises(ModelError, match="--depth-weights"):
        estimate_depth(_scene(f), method="pi3")
    # weights present but the package is not installed: the error names the package
    w = tmp_path / "w.pth"
    w.write_bytes(b"x")
    try:
        import pi3  # noqa: F401
    except ImportError:
        with pytest.raises(ModelError, match="pi3"):
            pi3_depth(f, w)
    try:
        import depth_anything_v2  # noqa: F401
    except ImportError:
        with pytest.raises(ModelError, match="depth_anything_v2"):
            depth_anything_depth(f, w)
