"""Tests of the point-track prior (endogsim.priors.tracks) and the motion cue of the tool segmentation.

The sequences are synthetic: a smooth random texture translated by a known sub-pixel shift per frame
(cv2.warpAffine, bilinear), so the true position of every point is known in every frame.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from endogsim.errors import DataError
from endogsim.priors.segmentation import GreyToolConfig, grey_tool_mask, motion_residual
from endogsim.priors.tracks import MOTION_BOUNDARY_RADIUS_PX, flow_lookup, near_forbidden, track_points

H, W = 96, 128
SHIFT = np.array([1.5, -0.7])  # pixels per frame


def _texture(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.random((H * 2, W * 2, 3)).astype(np.float32), (0, 0), 2.5)
    base = (base - base.min()) / (base.max() - base.min())
    return 0.2 + 0.6 * base


def _translated(num_frames: int, shift=SHIFT) -> np.ndarray:
    tex = _texture()
    frames = []
    for t in range(num_frames):
        M = np.array([[1.0, 0, -W / 2 + shift[0] * t], [0, 1.0, -H / 2 + shift[1] * t]], dtype=np.float32)
        frames.append(cv2.warpAffine(tex, M, (W, H), flags=cv2.INTER_LINEAR))
    return np.clip(np.stack(frames), 0, 1)


def test_flow_lookup_is_bilinear_at_pixel_centres():
    field = np.arange(12, dtype=np.float32).reshape(3, 4, 1)
    pts = np.array([[0.5, 0.5], [1.5, 0.5], [1.0, 1.0], [3.5, 2.5]], dtype=np.float32)
    assert np.allclose(flow_lookup(field, pts)[:, 0], [0.0, 1.0, 2.5, 11.0], atol=1e-5)


def test_tracks_follow_a_known_translation_forward_and_backward():
    frames = _translated(8)
    used = [0, 2, 3, 4, 5, 6, 7]  # frame 1 is a "test" frame: never read, never valid
    gy, gx = np.mgrid[20:H - 20:8, 24:W - 24:8]
    seeds0 = np.stack([gx.ravel() + 0.5, gy.ravel() + 0.5], 1).astype(np.float32)
    seeds4 = seeds0[:10] + 4 * SHIFT
    seeds = np.concatenate([seeds0, seeds4]).astype(np.float32)
    seed_frames = np.array([0] * len(seeds0) + [4] * len(seeds4))
    tr = track_points(frames, np.ones((8, H, W), bool), seeds, seed_frames, used)
    pos, valid = tr.positions.numpy(), tr.valid.numpy()
    assert not valid[:, 1].any()
    assert valid[:, used].mean() > 0.95
    truth = seeds[:, None, :] + (np.arange(8)[None, :, None] - seed_frames[:, None, None]) * SHIFT
    err = np.linalg.norm(pos - truth, axis=-1)[valid]
    assert np.median(err) < 0.15 and np.percentile(err, 95) < 0.5, (np.median(err), np.percentile(err, 95))
    # points seeded in frame 4 are tracked back to frame 0 too
    assert valid[len(seeds0):, 0].all()


def test_tracks_are_lost_under_an_occluder_and_outside_the_allowed_pixels():
    frames = _translated(6)
    other = _texture(5)[:30, :40]
    for t in range(6):  # an instrument-like patch sliding left, against the tissue, over the tracked points
        x0 = 80 - 10 * t
        frames[t, 40:70, x0:x0 + 40] = other
    allowed = np.ones((6, H, W), bool)
    allowed[:, :, :16] = False  # e.g. the field-of-view border
    gy, gx = np.mgrid[46:64:4, 44:60:4]
    pts = np.stack([gx.ravel() + 0.5, gy.ravel() + 0.5], 1).astype(np.float32)
    tr = track_points(frames, allowed, pts, np.zeros(len(pts), int), list(range(6)))
    valid = tr.valid.numpy()
    assert valid[:, 2].mean() > 0.9  # tracked while visible
    assert valid[:, 5].mean() < 0.1  # lost once covered, and stays lost
    # tracked backward from frame 5, a point moves left by 1.5 px a frame and enters the band at frame 1
    back = track_points(frames, allowed, np.array([[16.5 + 4.5, 20.5]], dtype=np.float32), np.array([5]),
                        list(range(6)))
    assert back.valid[0, 2:].all() and not back.valid[0, :2].any()


def test_tracks_beside_a_sliding_instrument_stay_with_the_still_tissue():
    """Optical flow smooths an instrument's motion into the tissue beside it, forward and backward alike, so the
    forward-backward test keeps those steps; the motion-boundary test drops them. Still tissue, a grey bar sliding
    right 6 px a frame between rows of tracked points: before it, 15% of the kept steps drifted over 0.5 px (up to
    3.4 px, 0.46 px RMS)."""
    tex, other = _texture()[:H, :W], _texture(5)[:H, :W]
    T = 6
    frames = np.repeat(tex[None], T, 0)
    allowed = np.ones((T, H, W), bool)
    for t in range(T):
        x0 = 10 + 6 * t
        frames[t, 40:56, x0:x0 + 50] = 0.6 + 0.3 * other[40:56, x0:x0 + 50]
        allowed[t, 40:56, x0:x0 + 50] = False
    rows = np.r_[30:40:2, 57:67:2]
    gy, gx = np.meshgrid(rows, np.arange(10, 120, 2), indexing="ij")
    pts = np.stack([gx.ravel() + 0.5, gy.ravel() + 0.5], 1).astype(np.float32)
    tr = track_points(frames, allowed, pts, np.zeros(len(pts), int), list(range(T)))
    valid = tr.valid.numpy()
    err = np.linalg.norm(tr.positions.numpy() - pts[:, None], axis=-1)[valid]
    assert valid[:, 1:].mean() > 0.5  # most of the tissue stays tracked
    rms, far = np.sqrt((err ** 2).mean()), (err > 0.5).mean()
    assert rms < 0.25 and far < 0.05, (rms, far)


def test_stretching_tissue_away_from_instruments_stays_tracked():
    """The motion-boundary test applies only near pixels a track may not land on: in the open, tissue that
    stretches (a flow gradient as large as a boundary's where the motion is small) keeps its tracks, as a lost
    track is never taken up again. Here the texture grows 6% a frame about the image centre; with the test
    everywhere the points within 12 px of the centre were lost at the first step."""
    tex = _texture()
    frames = []
    for t in range(8):
        s = 1.06 ** t
        M = np.array([[s, 0, W / 2 - s * W], [0, s, H / 2 - s * H]], dtype=np.float32)  # texture centre -> image centre
        frames.append(cv2.warpAffine(tex, M, (W, H), flags=cv2.INTER_LINEAR))
    frames = np.clip(np.stack(frames), 0, 1)
    allowed = np.ones(frames.shape[:3], bool)
    gy, gx = np.meshgrid(np.arange(-10, 11, 4), np.arange(-10, 11, 4), indexing="ij")
    centre = np.array([W / 2 + 0.5, H / 2 + 0.5])  # pixel W/2's centre (pixel i spans [i, i + 1))
    pts = (centre + np.stack([gx.ravel(), gy.ravel()], 1)).astype(np.float32)
    tr = track_points(frames, allowed, pts, np.zeros(len(pts), int), list(range(8)))
    assert tr.valid.numpy().all()
    truth = (pts - centre)[:, None] * (1.06 ** np.arange(8))[None, :, None] + centre
    assert np.abs(tr.positions.numpy() - truth).max() < 1.0  # chained DIS drifts 0.7 px over 7 frames of growth


def test_near_forbidden_is_the_distance_to_a_pixel_a_track_may_not_land_on():
    allowed = np.ones((40, 60), bool)
    assert not near_forbidden(allowed).any()
    allowed[:, :5] = False  # a border band
    near = near_forbidden(allowed)
    x = np.arange(60)
    assert near[:, x < 5 + MOTION_BOUNDARY_RADIUS_PX - 1].all() and not near[:, x > 5 + MOTION_BOUNDARY_RADIUS_PX].any()


def test_track_points_checks_its_frames():
    frames = _translated(3)
    with pytest.raises(DataError, match="increasing"):
        track_points(frames, np.ones((3, H, W), bool), np.zeros((1, 2), np.float32), np.array([0]), [0, 2, 1])
    with pytest.raises(DataError, match="seed frame"):
        track_points(frames, np.ones((3, H, W), bool), np.zeros((1, 2), np.float32), np.array([1]), [0, 2])


def test_motion_residual_flags_an_object_moving_against_the_tissue():
    frames = _translated(5)
    stripes = (np.arange(24) // 3) % 2 == 0  # jaw teeth: tissue-coloured, high contrast
    patch = np.where(stripes[None, :, None], [0.5, 0.25, 0.25], [0.3, 0.15, 0.2]).astype(np.float32).repeat(20, 0)
    for t in range(5):
        x0 = 90 - 6 * t  # moves left, against the texture
        frames[t, 40:60, x0:x0 + 24] = patch
    res = motion_residual(frames, 2, np.zeros((H, W), bool))
    inside = res[42:58, 80:100].mean()
    outside = np.concatenate([res[5:30, 10:120].ravel(), res[70:90, 10:120].ravel()]).mean()
    assert inside > 0.1 > 3 * outside, (inside, outside)


def test_grey_tool_mask_grows_into_moving_pixels_only_with_the_motion_cue():
    frame = np.zeros((H, W, 3), np.float32)
    frame[...] = [0.75, 0.35, 0.3]  # saturated tissue
    frame[40:56, 10:60] = 0.6  # grey shaft (strong evidence)
    frame[44:52, 60:90] = [0.55, 0.3, 0.32]  # the jaw: tissue-coloured, but it moves with the shaft
    motion = np.zeros((H, W), np.float32)
    motion[44:52, 60:90] = 0.3
    cfg = GreyToolConfig(dilate_frac=0.0)
    without = grey_tool_mask(frame, cfg)
    with_motion = grey_tool_mask(frame, cfg, motion)
    assert without[48, 30] and not without[48, 80]
    assert with_motion[48, 80] and not with_motion[20, 80]  # the jaw joins, static tissue does not
