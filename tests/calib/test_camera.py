"""Camera calibration from boards that cover only the centre: the distortion model chosen on
held-out (outer) corners, and the supported field it implies."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from app.calib.camera import (
    CANDIDATE_MODELS,
    REDUCED_MODEL,
    SPLIT,
    calibrate_camera,
    defined_radius,
    field_shortfall,
)

SIZE = (1280, 1024)
K = np.array([[1200.0, 0.0, 641.0], [0.0, 1200.0, 510.0], [0.0, 0.0, 1.0]])


def _views(dist, *, noise_px=0.03, seed=0, reach=1.0):
    """A 12×9 board (2 mm squares) 40 mm away at eight tilted poses near the centre of the field."""
    rng = np.random.default_rng(seed)
    obj = np.zeros((9 * 12, 3), np.float32)
    obj[:, :2] = np.mgrid[0:12, 0:9].T.reshape(-1, 2) * 2.0
    obj[:, :2] -= obj[:, :2].mean(axis=0)
    objs, imgs = [], []
    for k in range(8):
        rvec = np.array([0.25 * math.sin(k), 0.25 * math.cos(1.3 * k), 0.1 * k])
        tvec = np.array([reach * 2.0 * math.cos(k), reach * 1.5 * math.sin(k), 40.0 + k])
        uv, _ = cv2.projectPoints(
            obj.astype(np.float64), rvec, tvec, K, np.asarray(dist, np.float64)
        )
        uv = uv.reshape(-1, 1, 2) + rng.normal(0.0, noise_px, (len(obj), 1, 2))
        objs.append(obj.copy())
        imgs.append(uv.astype(np.float32))
    return objs, imgs


def test_central_boards_bound_the_field_and_prefer_a_model_that_extrapolates():
    objs, imgs = _views([-0.25, 0.0, 0.0, 0.0, 0.0])
    fit = calibrate_camera(objs, imgs, SIZE)
    assert set(fit.held_out_px) == {REDUCED_MODEL, *CANDIDATE_MODELS}
    radii = [
        np.hypot((i[:, 0, 0] - K[0, 2]) / K[0, 0], (i[:, 0, 1] - K[1, 2]) / K[1, 1]).max()
        for i in imgs
    ]
    assert fit.r_max == pytest.approx(max(radii), rel=0.01)
    # the chosen model is the simplest within 10 % (or 0.005 px) of the best held-out error …
    best = min(fit.held_out_px[m] for m in CANDIDATE_MODELS)
    reduced = fit.held_out_px[REDUCED_MODEL]
    if fit.model == REDUCED_MODEL:  # k1 alone only when no candidate predicts better
        assert reduced <= best
    else:
        assert fit.held_out_px[fit.model] <= max(1.10 * best, best + 0.005)
        assert reduced > best
        simpler = list(CANDIDATE_MODELS)[:list(CANDIDATE_MODELS).index(fit.model)]
        assert all(fit.held_out_px[m] > max(1.10 * best, best + 0.005) for m in simpler)
    # … and its field: at most the verified extrapolation 1/SPLIT beyond the farthest corner
    assert fit.r_max <= fit.field_radius <= fit.r_max / SPLIT + 1e-12
    cx, cy, rx, ry = fit.field_px()
    assert rx / fit.camera_matrix[0, 0] == pytest.approx(fit.field_radius)
    # the image corners (r ≈ 0.68) are not supported
    assert math.hypot((0 - cx) / rx, (0 - cy) / ry) > 1.0
    # where the field is valid the fitted lens agrees with the true one to < 0.1 px
    r = np.linspace(0.0, fit.field_radius, 50)
    k1, k2, _, _, k3 = fit.dist_coeffs
    true = r * (1 - 0.25 * r**2)
    got = r * (1 + k1 * r**2 + k2 * r**4 + k3 * r**6)
    assert np.max(np.abs(got - true)) * 1200.0 < 0.1


def test_too_many_terms_are_refused_on_held_out_corners():
    """With corners to r ≈ 0.2 only, k3 is not determined: its held-out error exceeds k1's."""
    objs, imgs = _views([-0.25, 0.0, 0.0, 0.0, 0.0], noise_px=0.05, seed=3)
    fit = calibrate_camera(objs, imgs, SIZE)
    assert fit.held_out_px["k1,k2,k3,p1,p2"] > fit.held_out_px["k1"]
    assert fit.model != "k1,k2,k3,p1,p2"


def test_noise_free_corners_choose_the_simplest_model():
    objs, imgs = _views([-0.25, 0.0, 0.0, 0.0, 0.0], noise_px=0.0)
    assert calibrate_camera(objs, imgs, SIZE).model == "k1"


def test_a_real_k2_is_kept_from_central_boards():
    """k2 = +0.065 on boards near the centre: k1 alone would bend the rays beyond them; every
    candidate fits k2, and the fitted lens matches the true one out to the farthest corner."""
    objs, imgs = _views([-0.02, 0.065, 0.0, 0.0, 0.0], noise_px=0.03, seed=5)
    fit = calibrate_camera(objs, imgs, SIZE)
    assert fit.model in CANDIDATE_MODELS and fit.dist_coeffs[1] != 0.0
    r = np.linspace(0.0, fit.r_max, 50)
    k1, k2, _, _, k3 = fit.dist_coeffs
    got = r * (1 + k1 * r**2 + k2 * r**4 + k3 * r**6)
    assert np.max(np.abs(got - r * (1 - 0.02 * r**2 + 0.065 * r**4))) * 1200.0 < 0.1


def test_the_lens_model_is_defined_until_its_rays_fold_over():
    # r (1 - 0.25 r²): slope 1 - 0.75 r² reaches 0.2 at r = √(0.8/0.75)
    rf = math.sqrt(0.8 / 0.75)
    assert defined_radius([-0.25, 0, 0, 0, 0]) == pytest.approx(rf * (1 - 0.25 * rf**2), rel=1e-2)
    assert defined_radius([0.1, 0.0, 0.0, 0.0, 0.0]) == math.inf


def test_field_shortfall_names_the_unsupported_ninths():
    short = field_shortfall((640.0, 512.0, 400.0, 400.0), SIZE)
    assert set(short) == {
        "top left",
        "top centre",
        "top right",
        "middle left",
        "middle right",
        "bottom left",
        "bottom centre",
        "bottom right",
    }
    assert short["top left"] > short["top centre"] > 0
    assert field_shortfall(None, SIZE) == {}
    assert field_shortfall((640.0, 512.0, 5000.0, 5000.0), SIZE) == {}
