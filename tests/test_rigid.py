import numpy as np
import pytest

from treereg_core.geometry.rigid import (
    apply_transform,
    invert,
    kabsch,
    kabsch_yaw,
    make_transform,
    mean_displacement,
    rotation_error_deg,
    rotation_z,
)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_kabsch_recovers_a_known_transform():
    rng = np.random.default_rng(1)
    src = rng.uniform(-5, 5, size=(50, 3))
    T = make_transform(_random_rotation(rng), rng.normal(size=3) * 10)
    est = kabsch(src, apply_transform(T, src))
    assert np.allclose(est, T, atol=1e-9)


def test_kabsch_never_returns_a_reflection():
    rng = np.random.default_rng(2)
    src = rng.uniform(-1, 1, size=(20, 3))
    mirrored = src * np.array([1.0, 1.0, -1.0])  # the best orthogonal map is a reflection
    est = kabsch(src, mirrored)
    assert np.linalg.det(est[:3, :3]) == pytest.approx(1.0)


def test_kabsch_yaw_recovers_yaw_and_translation_only():
    rng = np.random.default_rng(3)
    src = rng.uniform(-5, 5, size=(30, 3))
    T = make_transform(rotation_z(73.0), np.array([4.0, -2.0, 0.5]))
    est = kabsch_yaw(src, apply_transform(T, src) + rng.normal(scale=0.001, size=src.shape))
    assert rotation_error_deg(est, T) < 0.05
    assert np.allclose(est[:3, 3], T[:3, 3], atol=0.01)
    assert np.allclose(est[2, :3], [0, 0, 1])  # z axis untouched: a levelled scanner


def test_errors_against_truth():
    pts = np.random.default_rng(4).uniform(-1, 1, size=(100, 3))
    T = make_transform(rotation_z(30.0), np.array([1.0, 2.0, 3.0]))
    assert rotation_error_deg(T, T) == pytest.approx(0.0, abs=1e-6)
    shifted = T.copy()
    shifted[:3, 3] += [0.0, 0.0, 0.05]
    assert mean_displacement(shifted, T, pts) == pytest.approx(0.05)
    assert rotation_error_deg(make_transform(rotation_z(32.0), T[:3, 3]), T) == pytest.approx(2.0)
    assert np.allclose(invert(T) @ T, np.eye(4))
