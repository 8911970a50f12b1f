"""The joint refinement's exact Jacobian (app.calib.refine) against finite differences.

The refinement feeds MINPACK's Levenberg-Marquardt exact derivatives of its residuals (corners
through ``cv2.projectPoints``, the phase by the chain rule through board plane, projector and the
camera's undistortion). Here they are compared, at random states with every distortion term
free, with central differences of the residuals themselves.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.optimize._numdiff import approx_derivative

from app.calib.refine import JointProblem, undistort_rays, undistort_rays_jacobian

WIDTH, HEIGHT = 1384, 1032


def _camera(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    cam = np.array([[1100.0 + 50 * rng.standard_normal(), 0.0, 692.0 + 5 * rng.standard_normal()],
                    [0.0, 1105.0 + 50 * rng.standard_normal(), 516.0 + 5 * rng.standard_normal()],
                    [0.0, 0.0, 1.0]])
    dist = np.array([-0.25, 0.08, 1e-3, -6e-4, -0.01]) * (1.0 + 0.2 * rng.standard_normal(5))
    return cam, dist


def _problem(rng: np.random.Generator, free: tuple[int, ...]) -> tuple[JointProblem, np.ndarray]:
    """A joint problem of 3 views with random poses, pixels and phases, and a random state."""
    cam, dist = _camera(rng)
    grid = np.stack(np.meshgrid(np.arange(6.0), np.arange(5.0)), -1).reshape(-1, 2) * 1.5
    obj_k = np.column_stack([grid - grid.mean(axis=0), np.zeros(len(grid))])
    obj, img, pix, xps, wts, poses = [], [], [], [], [], []
    for _ in range(3):
        rvec = 0.3 * rng.standard_normal(3)
        tvec = np.array([rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(35, 50)])
        uv, _ = cv2.projectPoints(obj_k, rvec, tvec, cam, dist)
        obj.append(obj_k)
        img.append(uv.reshape(-1, 2) + 0.05 * rng.standard_normal((len(obj_k), 2)))
        pix.append(np.column_stack([rng.uniform(100, WIDTH - 100, 400),
                                    rng.uniform(100, HEIGHT - 100, 400)]))
        xps.append(rng.uniform(200, 800, 400))
        wts.append(rng.uniform(0.5, 1.5, 400))
        poses.append(np.concatenate([rvec, tvec]))
    prob = JointProblem(obj, img, pix, xps, wts, list(dist), free, s_corner=0.07,
                        s_phase=list(rng.uniform(0.05, 0.2, 3)))
    projector = np.array([*(0.2 * rng.standard_normal(3)), rng.uniform(10, 30),
                          rng.uniform(-5, 5), rng.uniform(1200, 1800), rng.uniform(400, 600),
                          0.05 * rng.standard_normal()])
    camera = np.array([cam[0, 0], cam[1, 1], cam[0, 2], cam[1, 2], *dist[list(free)]])
    return prob, np.concatenate([projector, camera, *poses])


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("free", [(0, 1), (0, 1, 2, 3, 4)])
def test_joint_jacobian_matches_central_differences(seed: int, free: tuple[int, ...]) -> None:
    prob, x = _problem(np.random.default_rng(seed), free)
    exact = prob.jacobian(x)
    numeric = approx_derivative(prob.residuals, x, method="3-point")
    assert exact.shape == numeric.shape == (prob.residuals(x).size, x.size)
    scale = np.abs(numeric).max(axis=0)
    assert np.all(scale > 0)  # every parameter moves some residual
    err = np.abs(exact - numeric).max(axis=0)
    # central differences are good to ~1e-9 of a column's scale here; a wrong term is O(1)
    assert np.all(err <= 1e-6 * scale), (err / scale).max()


def test_undistortion_jacobian_matches_central_differences() -> None:
    rng = np.random.default_rng(5)
    cam, dist = _camera(rng)
    uv = np.column_stack([rng.uniform(0, WIDTH, 200), rng.uniform(0, HEIGHT, 200)])
    free = (0, 1, 2, 3, 4)
    theta = np.array([cam[0, 0], cam[1, 1], cam[0, 2], cam[1, 2], *dist])

    def rays_xy(th: np.ndarray) -> np.ndarray:
        k = np.array([[th[0], 0.0, th[2]], [0.0, th[1], th[3]], [0.0, 0.0, 1.0]])
        return undistort_rays(uv, k, th[4:], iterations=200)[:, :2].ravel()

    exact = undistort_rays_jacobian(undistort_rays(uv, cam, dist, iterations=200), cam, dist, free)
    numeric = approx_derivative(rays_xy, theta, method="3-point").reshape(len(uv), 2, -1)
    scale = np.abs(numeric).max(axis=(0, 1))
    assert np.all(np.abs(exact - numeric).max(axis=(0, 1)) <= 1e-6 * scale)


@pytest.mark.parametrize("seed", [3, 4])
def test_projector_only_jacobian_matches_central_differences(seed: int) -> None:
    """The start's projector-only fit: one view's phase residuals in the projector's 8
    parameters, the camera and pose held (its rays given)."""
    prob, x = _problem(np.random.default_rng(seed), (0, 1))
    ray = prob.rays(x)[1]

    def phase(xp: np.ndarray) -> np.ndarray:
        return prob.phase_res(np.concatenate([xp, x[8:]]), 1, ray) * 0.5

    exact = prob.phase_jacobian(x, 1, ray, 0.5)
    numeric = approx_derivative(phase, x[:8], method="3-point")
    assert exact.shape == numeric.shape == (len(ray), 8)
    scale = np.abs(numeric).max(axis=0)
    assert np.all(np.abs(exact - numeric).max(axis=0) <= 1e-6 * scale)
