"""The unicycle EKF against a plain numerical EKF step, and on a noisy line and circle."""

import math

import numpy as np
import pytest

from vloc.workers.core.navigation import UnicycleEKF, unicycle_step
from vloc.workers.core.navigation.ekf import POSE, POSITION, ProcessNoise, motion, motion_jacobian


def _numerical_jacobian(f, x, eps=1e-6):
    cols = []
    for k in range(len(x)):
        e = np.zeros_like(x)
        e[k] = eps
        cols.append((f(x + e) - f(x - e)) / (2 * eps))
    return np.stack(cols, axis=1)


def _plain_ekf_step(x, P, dt, q, z, R):
    """Textbook EKF: finite-difference Jacobian, explicit inverse, simple covariance update."""
    F = _numerical_jacobian(lambda s: motion(s, dt), x)
    x = motion(x, dt)
    P = F @ P @ F.T + q
    H = np.zeros((3, 5))
    H[0, 0] = H[1, 1] = H[2, 2] = 1.0
    y = z - H @ x
    y[2] = (y[2] + math.pi) % (2 * math.pi) - math.pi
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    return x + K @ y, (np.eye(5) - K @ H) @ P


def test_jacobian_matches_finite_differences():
    x = np.array([1.0, -2.0, 0.7, 0.6, 0.3])
    num = _numerical_jacobian(lambda s: motion(s, 0.5), x)
    assert np.allclose(motion_jacobian(x, 0.5), num, atol=1e-8)


def test_step_matches_plain_numerical_ekf():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(5, 5))
    P0 = a @ a.T * 0.1 + np.eye(5) * 0.05
    x0 = np.array([2.0, 1.0, 3.0, 0.5, -0.2])          # heading near pi: wrapping matters
    noise = ProcessNoise(accel=0.1, ang_accel=0.3, pose=0.01, heading=0.004)
    R = np.diag([0.2, 0.3, 0.05])
    z = np.array([2.3, 1.1, -3.1])
    ekf = UnicycleEKF(x0, P0, noise)
    ekf.predict(0.8)
    ekf.update(z, POSE, R)
    q = np.diag([noise.pose, noise.pose, noise.heading, noise.accel, noise.ang_accel]) * 0.8
    x_ref, P_ref = _plain_ekf_step(x0, P0, 0.8, q, z, R)
    x_ref[2] = (x_ref[2] + math.pi) % (2 * math.pi) - math.pi
    assert np.allclose(ekf.x, x_ref, atol=1e-6)
    assert np.allclose(ekf.P, P_ref, atol=1e-6)


def _track(truth, rng, sigma_xy, sigma_th, dt):
    ekf = UnicycleEKF([*truth[0], 0.0, 0.0], np.diag([1.0, 1.0, 0.1, 1.0, 1.0]))
    est, raw = [], []
    for pose in truth[1:]:
        ekf.predict(dt)
        z = pose + np.r_[rng.normal(0, sigma_xy, 2), rng.normal(0, sigma_th)]
        ekf.update(z, POSE, np.diag([sigma_xy ** 2] * 2 + [sigma_th ** 2]))
        est.append(ekf.x.copy())
        raw.append(z)
    return np.array(est), np.array(raw)


def test_noisy_straight_line_is_smoothed_and_speed_found():
    rng = np.random.default_rng(0)
    dt, v = 0.5, 0.6
    truth = np.array([[v * dt * k, 0.0, 0.0] for k in range(200)])
    est, raw = _track(truth, rng, 0.3, math.radians(8), dt)
    tail = slice(50, None)
    err_est = np.hypot(*(est[tail, :2] - truth[1:][tail, :2]).T)
    err_raw = np.hypot(*(raw[tail, :2] - truth[1:][tail, :2]).T)
    assert err_est.mean() < 0.5 * err_raw.mean()
    assert np.mean(est[tail, 3]) == pytest.approx(v, abs=0.03)
    assert abs(np.mean(est[tail, 4])) < 0.01


def test_noisy_circle_finds_constant_turn_rate():
    rng = np.random.default_rng(1)
    dt, v, w = 0.5, 0.6, 0.15          # radius 4 m
    truth = [np.array([0.0, 0.0, 0.0])]
    for _ in range(200):
        truth.append(unicycle_step(truth[-1], v, w, dt))
    truth = np.array(truth)
    est, raw = _track(truth, rng, 0.3, math.radians(8), dt)
    tail = slice(50, None)
    assert np.mean(est[tail, 4]) == pytest.approx(w, abs=0.01)
    assert np.mean(est[tail, 3]) == pytest.approx(v, abs=0.03)
    err_est = np.hypot(*(est[tail, :2] - truth[1:][tail, :2]).T)
    err_raw = np.hypot(*(raw[tail, :2] - truth[1:][tail, :2]).T)
    assert err_est.mean() < 0.7 * err_raw.mean()


def test_position_only_fixes_reveal_heading_from_motion():
    rng = np.random.default_rng(2)
    dt = 1.0
    truth = np.array([[0.6 * k * math.cos(1.0), 0.6 * k * math.sin(1.0), 1.0] for k in range(80)])
    ekf = UnicycleEKF([0, 0, 0.0, 0.5, 0.0], np.diag([0.1, 0.1, 3.0, 0.2, 0.1]))
    heading = []
    for pose in truth[1:]:
        ekf.predict(dt)
        ekf.update(pose[:2] + rng.normal(0, 0.2, 2), POSITION, np.eye(2) * 0.04)
        heading.append(ekf.x[2])
    assert abs(heading[0] - 1.0) > 0.3                   # it did not start out knowing
    assert np.mean(heading[-30:]) == pytest.approx(1.0, abs=0.1)


def test_state_round_trips():
    ekf = UnicycleEKF([1, 2, 0.3, 0.4, 0.05], np.eye(5) * 0.2)
    ekf.predict(1.0)
    back = UnicycleEKF.from_dict(ekf.to_dict())
    assert np.array_equal(back.x, ekf.x) and np.array_equal(back.P, ekf.P)
