"""`pose_errors`, the measure `nehad prepare` is held to (issue 30), on cameras whose errors are
known by construction: the true orbit moved by a similarity (the gauge structure from motion
leaves free) and each camera then turned and shifted by a chosen amount."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from nehad.data.synth_capture import orbit_poses, pose_errors


def _turn(axis, degrees: float) -> np.ndarray:
    """Rotation by `degrees` about `axis` (Rodrigues)."""
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    a = math.radians(degrees)
    return np.eye(3) + math.sin(a) * kx + (1.0 - math.cos(a)) * kx @ kx


def _write(tmp_path, truth_poses, est_poses, fps=30.0):
    truth = {"kind": "orbit", "fps": fps, "extent": 4.0,
             "cameras": [{"camera_to_world": p.tolist()} for p in truth_poses]}
    (tmp_path / "truth.json").write_text(json.dumps(truth))
    frames = [{"source_time": i / fps, "transform_matrix": p.tolist()}
              for i, p in enumerate(est_poses)]
    (tmp_path / "transforms_train.json").write_text(json.dumps({"frames": frames[1:]}))
    (tmp_path / "transforms_test.json").write_text(json.dumps({"frames": frames[:1]}))


def test_errors_are_the_ones_put_in_whatever_the_gauge(tmp_path):
    """A 60-degree orbit of 12 cameras: every orientation turned by 0.4 degree, about the
    same axis in pairs of opposite signs (so the turns average out), one centre moved by 1% of
    the extent, then the whole set scaled by 0.37, turned and shifted. pose_errors gives back
    0.4 degree on every camera and 1% at most, to 1e-6."""
    truth = orbit_poses(12, 60.0)
    gauge = _turn([0.3, -1.0, 0.5], 47.0)
    rng = np.random.default_rng(3)
    est, axis = [], None
    for i, c2w in enumerate(truth):
        pose = c2w.copy()
        if i % 2 == 0:
            axis = rng.normal(size=3)
        pose[:3, :3] = _turn(axis, 0.4 if i % 2 == 0 else -0.4) @ pose[:3, :3]
        if i == 5:
            pose[:3, 3] += 0.04 * np.array([0.0, 0.0, 1.0])  # 1% of the extent 4
        moved = np.eye(4)
        moved[:3, :3] = gauge @ pose[:3, :3]
        moved[:3, 3] = 0.37 * gauge @ pose[:3, 3] + [2.0, -1.0, 0.5]
        est.append(moved)
    _write(tmp_path, truth, est)
    err = pose_errors(tmp_path, tmp_path / "truth.json")
    assert err["cameras"] == 12
    assert err["rotation_max_deg"] == pytest.approx(0.4, abs=1e-6)
    assert err["rotation_median_deg"] == pytest.approx(0.4, abs=1e-6)
    # the centre fit spreads the one moved centre over the others: at most its 1%, not zero
    assert 0.005 < err["position_max"] <= 0.01 + 1e-9


def test_exact_cameras_score_zero(tmp_path):
    truth = orbit_poses(8, 120.0)
    gauge = _turn([1.0, 2.0, 3.0], -130.0)
    est = []
    for c2w in truth:
        moved = np.eye(4)
        moved[:3, :3] = gauge @ c2w[:3, :3]
        moved[:3, 3] = 2.5 * gauge @ c2w[:3, 3] - [1.0, 0.0, 3.0]
        est.append(moved)
    _write(tmp_path, truth, est)
    err = pose_errors(tmp_path, tmp_path / "truth.json")
    assert err["rotation_max_deg"] < 1e-5 and err["position_max"] < 1e-9
