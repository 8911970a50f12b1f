"""The change map on the digital twin with known deformations (the issue's targets).

Every set is rendered by the twin (1384 × 1032, sensor noise, lens distortion) and
reconstructed with its ideal Eq. (5) calibration (exact without lens distortion: with the
twin's it errs by 0.19 mm median, which a fixed scope's Δ cancels) or, where said, with the
twin's own geometry (``true_geometric_calibration``: exact); the truth is the twin's surface.
Run with ``-s`` to see the figures.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from app.analysis.change import ChangeResult, compare, surface_normals
from app.calib.calibration import load_calibration
from app.core.calibration import Calibration
from app.core.schedule import PatternSchedule
from app.devices.sim import SimulatedWorld, default_rig
from app.devices.sim.ideal import ideal_calibration, true_geometric_calibration
from app.devices.sim.offline import render_capture_set
from app.devices.sim.scenes import Scene
from app.devices.sim.scenes.tissue import (
    breathing_scene,
    field_point,
    pressing_tool,
    scope_moved,
    still_tissue_scene,
    with_bumps,
)
from app.recon import Reconstructor

pytestmark = pytest.mark.slow

BUMP = [(0.0, 0.0, 0.3, 3.0)]  # 0.3 mm high, 3 mm across, on an intestine loop
ROT_DEG, AXIS, SHIFT_MM = 2.0, (0.3, 1.0, 0.2), (0.6, -0.5, 0.6)  # |SHIFT| = 1.0 mm


class Map:
    """A reconstructed map: ``sigma`` its sensor-noise σ, ``sigma_model`` its calibration σ."""

    def __init__(self, depth: Any, sigma: Any, points: Any, truth: Any,
                 sigma_model: Any = None) -> None:
        self.depth, self.sigma, self.points, self.truth = depth, sigma, points, truth
        self.sigma_model = sigma_model


Frames = dict[Any, tuple[Any, Any]]  # (key, seed, t0) -> (frames, truth)


@pytest.fixture(scope="module")
def frames() -> Frames:
    """The twin's sets, rendered once for every calibration (freed with the module: ~45 MB
    a set, which a module-level dict kept for the rest of the test session)."""
    return {}


def _renderer(cal: Calibration, rig: Any, rendered: Frames) -> Callable[..., Map]:
    engine = Reconstructor(cal)
    cache: dict[Any, Map] = {}
    # the last scene's world: its next seed reuses the traced geometry (seconds a set, and
    # ~0.3 GB, so one slot); reseeded, it renders what a new world of that seed renders
    last_world: dict[str, SimulatedWorld] = {}

    def render(key: str, scene: Scene, seed: int, t0_s: float = 0.0) -> Map:
        if (key, seed, t0_s) not in rendered:
            world = last_world.get(key)
            if world is None:
                last_world.clear()
                world = last_world[key] = SimulatedWorld(scene, seed=seed)
            world.reseed(seed)
            cs, truth, _ = render_capture_set(scene, world=world, t0_s=t0_s)
            rendered[key, seed, t0_s] = (cs.frames, truth)
        if (key, seed, t0_s) not in cache:
            frames, truth = rendered[key, seed, t0_s]
            res = engine.run(frames)
            cache[key, seed, t0_s] = Map(res.depth, res.sigma_noise, res.points, truth,
                                         res.sigma_model)
        return cache[key, seed, t0_s]

    render.calibration = cal  # type: ignore[attr-defined]
    render.rig = rig  # type: ignore[attr-defined]
    return render


@pytest.fixture(scope="module")
def twin(frames: Frames) -> Callable[..., Map]:
    rig = default_rig()
    return _renderer(ideal_calibration(rig, PatternSchedule()), rig, frames)


# one test each: their engines and maps go when it ends, not with the module
@pytest.fixture()
def fitted_twin(sim_calibration_file: Path, frames: Frames) -> Callable[..., Map]:
    """The same sets reconstructed with the calibration the simulator's service makes and
    uses (board poses rendered by the twin, fitted, with its σ_model): what a user has."""
    return _renderer(load_calibration(sim_calibration_file), default_rig(), frames)


@pytest.fixture()
def exact_twin(frames: Frames) -> Callable[..., Map]:
    """The same sets reconstructed with the twin's own geometry as the calibration."""
    rig = default_rig()
    return _renderer(true_geometric_calibration(rig, PatternSchedule()), rig, frames)


def _truth_along_normal(cal: Calibration, ref: Map, cur_truth: Any) -> Any:
    """The true change as a registered map measures it: the distance from the reference
    surface to the changed one along the reference's (measured) normal, from the twin's true
    heights of both on each pixel's ray (mm)."""
    h, w = ref.truth.shape
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    px = np.stack([uu.ravel(), vv.ravel()], -1)[:, None, :]
    xy = cv2.undistortPoints(px, cal.camera_matrix, cal.dist_coeffs).reshape(h, w, 2)
    rays = np.dstack([xy, np.ones((h, w))])
    per_mm = 1.0 / (rays @ cal.plane_normal)  # ray length per mm of height
    ref_pts = rays * ((ref.truth - cal.plane_offset_mm) * per_mm)[..., None]
    cur_pts = rays * ((cur_truth - cal.plane_offset_mm) * per_mm)[..., None]
    normals = surface_normals(ref.points).astype(np.float64)
    return np.einsum("ijk,ijk->ij", cur_pts - ref_pts, normals)


def _compare(twin: Any, cur: Map, ref: Map) -> ChangeResult:
    cal = twin.calibration
    return compare(cur.depth, cur.sigma, cur.points, ref.depth, ref.sigma, ref.points,
                   camera_matrix=cal.camera_matrix, dist_coeffs=cal.dist_coeffs,
                   sigma_model=cur.sigma_model, ref_sigma_model=ref.sigma_model)


def _still_figures(res: ChangeResult, ref: Map) -> tuple[float, float, float]:
    cm = res.cmap
    ok = np.isfinite(cm.delta)
    rms = float(np.sqrt(np.mean(cm.delta[ok] ** 2)))
    floor = float(np.sqrt(np.nanmean(ref.sigma ** 2)))  # one map's RMS σ: the noise floor
    return cm.changed_share, rms, floor


def _bump_figures(res: ChangeResult, truth_change: Any,
                  truth_measured: Any = None) -> tuple[float, float]:
    """(share of the area whose true height change exceeds 0.15 mm flagged, share of the
    crest's pixels whose Δ is within 2 σ_Δ of the truth of what the map measures:
    ``truth_measured``, the change along the normal for a registered map, default the height
    change)."""
    cm = res.cmap
    measured = truth_change if truth_measured is None else truth_measured
    region = np.isfinite(truth_change) & (truth_change > 0.15)
    crest = np.isfinite(measured) & (truth_change >= 0.95 * np.nanmax(truth_change))
    within = np.abs(cm.delta - measured)[crest] <= 2 * cm.sigma[crest]
    return float(cm.changed[region].mean()), float(within.mean())


def test_a_still_scene_shows_no_change(twin):
    base = still_tissue_scene(twin.rig)
    ref, cur = twin("still", base, 1), twin("still", base, 2)
    res = _compare(twin, cur, ref)
    share, rms, floor = _still_figures(res, ref)
    print(f"\nstill: changed {100 * share:.4f}% (target <= 0.01%), delta RMS {rms:.4f} mm <= "
          f"{1.2 * math.sqrt(2) * floor:.4f} mm (1.2 x sqrt2 x noise floor {floor:.4f} mm)")
    assert res.mode == "fixed"
    assert rms <= 1.2 * math.sqrt(2) * floor
    # the rate is 1e-4 per map: a still map shows a changed pixel once in 10 000 maps
    assert share <= 1e-4


def test_a_small_bump_is_flagged_and_measured(twin):
    base = still_tissue_scene(twin.rig)
    ref = twin("still", base, 1)
    cur = twin("bump", with_bumps(base, BUMP), 3)
    res = _compare(twin, cur, ref)
    truth = cur.truth - ref.truth
    flagged, crest = _bump_figures(res, truth)
    print(f"\nbump 0.3 mm / 3 mm: {100 * flagged:.1f}% of the > 0.15 mm area flagged (target "
          f">= 90%), crest within 2 sigma in {100 * crest:.1f}% of its pixels; truth peak "
          f"{np.nanmax(truth):.3f} mm")
    assert res.mode == "fixed" and flagged >= 0.9 and crest >= 0.9


def _scope_motion(twin: Any) -> tuple[ChangeResult, ChangeResult, Map, Map]:
    """(the registered still scene, the registered bump, the reference, the bumped truth map)"""
    base = still_tissue_scene(twin.rig)
    pivot = field_point(base, 0.0, 0.0)
    ref = twin("still", base, 1)
    moved = twin("moved", scope_moved(base, ROT_DEG, AXIS, SHIFT_MM, pivot), 3)
    moved_bump = twin("moved_bump", scope_moved(with_bumps(base, BUMP), ROT_DEG, AXIS,
                                                SHIFT_MM, pivot), 3)
    bumped = twin("bump", with_bumps(base, BUMP), 3)
    return _compare(twin, moved, ref), _compare(twin, moved_bump, ref), ref, bumped


def _check_scope_motion(twin: Any, label: str) -> float:
    """The registered case's figures and the targets met whatever the calibration; returns
    the still scene's changed share."""
    still, res, ref, bumped = _scope_motion(twin)
    assert still.mode == "registered" and still.registration is not None
    reg = still.registration
    share, rms, floor = _still_figures(still, ref)
    print(f"\n{label}: scope moved {ROT_DEG} deg / 1 mm: registration {reg.rotation_deg:.3f} "
          f"deg, residual {reg.residual_mm:.4f} mm, {reg.elapsed_ms:.0f} ms; changed "
          f"{100 * share:.4f}% (target <= 0.01%), delta RMS {rms:.4f} mm (limit "
          f"{1.2 * math.sqrt(2) * floor:.4f} mm)")
    assert reg.ok and abs(reg.rotation_deg - ROT_DEG) < 0.2
    assert rms <= 1.2 * math.sqrt(2) * floor
    assert res.mode == "registered"
    truth = bumped.truth - ref.truth
    flagged, crest = _bump_figures(res, truth,
                                   _truth_along_normal(twin.calibration, ref, bumped.truth))
    print(f"{label}: scope moved + bump: {100 * flagged:.1f}% flagged (target >= 90%), crest "
          f"within 2 sigma of the true change along the normal in {100 * crest:.1f}%")
    assert flagged >= 0.9 and crest >= 0.9
    return share


def test_a_scope_motion_is_registered_and_a_bump_found_after_it(twin):
    share = _check_scope_motion(twin, "Eq. (5) calibration")
    if share > 1e-4:
        pytest.xfail(f"registered still scene: {100 * share:.3f}% changed, target 0.01%: the "
                     "Eq. (5) calibration errs by 0.19 mm median here (the twin's lens "
                     "distortion), an error it does not know (no σ_model) and that a moved "
                     "scope no longer cancels; with the twin's exact geometry it is met")


def test_with_the_twins_exact_geometry_a_scope_motion_meets_every_target(exact_twin):
    """The same sets with an exact calibration: what is left after the registration is the
    noise, and the registered map meets the fixed scope's targets."""
    share = _check_scope_motion(exact_twin, "exact geometry")
    assert share <= 1e-4


def test_with_the_services_fitted_calibration_a_scope_motion_meets_every_target(fitted_twin):
    """The calibration the twin's service fits from rendered board poses (geometric, with its
    σ_model) knows the twin's lens: the registered map meets the fixed scope's targets."""
    share = _check_scope_motion(fitted_twin, "fitted calibration")
    assert share <= 1e-4


def test_a_tool_pressing_the_surface_shows_the_dent_and_the_tool(twin):
    base = still_tissue_scene(twin.rig)
    ref = twin("still", base, 1)
    cur = twin("pressed", pressing_tool(base, 4.0, 2.0, 0.5, 5.0), 3)
    res = _compare(twin, cur, ref)
    truth = cur.truth - ref.truth
    cm = res.cmap
    dent = np.isfinite(truth) & (truth < -0.15) & (truth > -1.0)
    tool = np.isfinite(truth) & (truth > 1.0)
    seen = cm.changed | np.isnan(cm.delta)  # the tool itself may be invalid (shadow, glints)
    print(f"\ntool pressing 0.5 mm: dent {100 * cm.changed[dent].mean():.1f}% flagged, deepest "
          f"delta {np.nanmin(cm.delta[dent]):.3f} mm; tool {100 * seen[tool].mean():.1f}% "
          f"flagged or not compared")
    assert res.mode == "fixed"
    assert cm.changed[dent].mean() >= 0.9 and np.nanmin(cm.delta[dent]) < -0.4
    assert seen[tool].mean() >= 0.99


def test_breathing_reads_as_a_motion_of_the_whole_scene(twin):
    scene = breathing_scene(twin.rig)
    ref = twin("breathing", scene, 4, 0.0)
    cur = twin("breathing", scene, 5, 1.0)  # a quarter period later: heaved ~2 mm
    res = _compare(twin, cur, ref)
    # the heave between the two maps (each map stands for its finest group's instant, not the
    # set's middle where the truth is taken: the maps' own difference is the comparison)
    heave = float(np.nanmedian(cur.depth - ref.depth))
    truth_heave = float(np.nanmedian(cur.truth - ref.truth))
    assert res.registration is not None
    reg = res.registration
    # how far the registration moves the scene's centre (the rotation part is the set's own
    # motion blur: the tissue heaves ~1.5 mm during the 16 frames of one set)
    centre = np.nanmean(ref.points.reshape(-1, 3), axis=0)
    back = np.linalg.inv(reg.transform)
    shift = float(np.linalg.norm(back[:3, :3] @ centre + back[:3, 3] - centre))
    print(f"\nbreathing: heave {heave:.2f} mm between the maps ({truth_heave:.2f} mm between "
          f"the sets' middles); mode {res.mode}, fixed-scope changed "
          f"{100 * res.fixed_changed_share:.1f}%, registration moves the scene centre "
          f"{shift:.2f} mm ({reg.rotation_deg:.2f} deg), residual {reg.residual_mm:.4f} mm; "
          f"changed after it {100 * res.cmap.changed_share:.2f}%")
    assert res.fixed_changed_share > 0.5  # pixel by pixel it all "changed"...
    assert res.mode == "registered" and reg.ok  # ...and it is read as one rigid motion
    assert abs(shift - abs(heave)) < 0.3
    assert res.cmap.changed_share < 0.1
