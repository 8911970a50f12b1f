"""The change map's live cost per map, against baselines run in the same process.

Fixed scope (``app.recon.change.change_map``: Δ, σ_Δ and the pooled changed test) on
1384 × 1032 maps with 10 % invalid pixels, against two baselines on the same arrays:
``numpy Δ`` (``cur − ref`` alone: the least any change map costs) and ``recon`` (the fused
reconstruction of one 16-frame set of the same size: the map's own cost). Target: ≤ 3 ms per
map for the fixed scope.

The registered case (``app.analysis.change.compare`` after a 2° / 1 mm scope motion: ICP,
the refinement on every pixel pair, the change along the normal) states its cost and the
rate it allows.

``--live-s 60`` also runs the service on the twin's still tissue (its ideal Eq. (5) calibration)
for that long with a reference taken at the start and prints the changed share of every change
map (target: median ≤ 0.01 %; the test's rate is per map, so a still map should show none) and
their Δ RMS against 1.2 × √2 × the noise floor. Every figure is printed with the machine's load
average at the time (the machine is shared).

    python benchmarks/bench_change.py [--repeats 30] [--registered-repeats 3] [--live-s 60]
"""

from __future__ import annotations

import argparse
import io
import math
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from app.core.jit import numeric_environment

# before numba is imported: the numeric settings of the CLI (app/core/jit.py)
os.environ.update(numeric_environment(os.environ))

import numpy as np
from timing import median_ms

from app.analysis.change import compare
from app.recon.change import change_map

H, W = 1032, 1384


def _load() -> str:
    """The 1, 5 and 15 min load averages."""
    return " / ".join(f"{x:.1f}" for x in os.getloadavg())


def _maps(rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    truth = rng.uniform(0, 20, (H, W)).astype(np.float32)
    s_ref = rng.uniform(0.03, 0.08, (H, W)).astype(np.float32)
    s_cur = rng.uniform(0.03, 0.08, (H, W)).astype(np.float32)
    ref = truth + s_ref * rng.standard_normal((H, W)).astype(np.float32)
    cur = truth + s_cur * rng.standard_normal((H, W)).astype(np.float32)
    for arr in (ref, cur):
        arr[rng.random((H, W)) < 0.1] = np.nan
    return cur, s_cur, ref, s_ref


def _recon_baseline() -> tuple[float, float]:
    from app.devices.sim.analytic_rig import Rig, bump_surface
    from app.recon import Reconstructor

    rig = Rig(width=W, height=H, focal_px=1700.0)
    frames = rig.render(bump_surface(rig), noise=1.0, rng=np.random.default_rng(1))
    eng = Reconstructor(rig.calibration())
    return median_ms(lambda: eng.run(frames), 10)


def _view(k: np.ndarray, transform: np.ndarray, seed: int) -> np.ndarray:
    """(H, W, 3) points of a wavy surface ~40 mm away seen by a camera moved by ``transform``."""
    rng = np.random.default_rng(seed)
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.stack([(uu - k[0, 2]) / k[0, 0], (vv - k[1, 2]) / k[1, 1], np.ones_like(uu)], -1)
    inv = np.linalg.inv(transform)
    t = np.full((H, W), 40.0)
    dz = (rays @ inv[:3, :3].T)[..., 2]
    for _ in range(60):
        q = (rays * t[..., None]) @ inv[:3, :3].T + inv[:3, 3]
        zs = 40 + 2.0 * np.sin(q[..., 0] / 3.0) * np.cos(q[..., 1] / 4.0) + 0.05 * q[..., 0]
        t += (zs - q[..., 2]) / dz
    t += 0.04 * rng.standard_normal(t.shape)
    return (rays * t[..., None]).astype(np.float32)


def live(seconds: float) -> None:
    """The still scene live: the share of changed pixels of every change map for ``seconds``."""
    import tempfile
    import time

    from fastapi.testclient import TestClient

    from app.calib import save_calibration
    from app.config import Settings
    from app.core.schedule import PatternSchedule
    from app.devices.sim import default_rig
    from app.devices.sim.ideal import ideal_calibration
    from app.main import create_app

    with tempfile.TemporaryDirectory() as tmp:
        cal = Path(tmp) / "twin.json"
        save_calibration(ideal_calibration(default_rig(), PatternSchedule()), cal)
        settings = Settings(data_dir=Path(tmp) / "data", calibration_file=cal, viewer=False,
                            sim_seed=1, exposure_ms=30.0, sim_scene="tissue_still")
        with TestClient(create_app(settings)) as client:
            while client.get("/api/status").json()["results_published"] < 1:
                time.sleep(0.2)
            ref = client.post("/api/reference").json()
            sigma_ref = np.load(io.BytesIO(
                client.get("/api/depth/latest?field=sigma").content))
            floor = float(np.sqrt(np.nanmean(sigma_ref ** 2)))
            seen, shares, rms, costs = ref["source"]["seq"], [], [], []
            t_end = time.monotonic() + seconds
            while time.monotonic() < t_end:
                r = client.get("/api/change/summary")
                if r.status_code == 200 and r.json()["seq"] > seen:
                    summary = r.json()
                    seen = summary["seq"]
                    delta = np.load(io.BytesIO(
                        client.get("/api/change/latest?field=delta").content))
                    shares.append(summary["changed_share"])
                    rms.append(float(np.sqrt(np.nanmean(delta ** 2))))
                    costs.append(summary["elapsed_ms"])
                time.sleep(0.05)
    sh = np.array(shares)
    print(f"load average {_load()}")
    print(f"live still scene, {seconds:.0f} s: {len(sh)} change maps; changed share median "
          f"{100 * np.median(sh):.4f}% (target <= 0.01%), mean {100 * sh.mean():.4f}%, max "
          f"{100 * sh.max():.4f}%; delta RMS median {np.median(rms):.4f} mm vs "
          f"1.2 x sqrt2 x noise floor {1.2 * math.sqrt(2) * floor:.4f} mm; change cost in "
          f"the service median {np.median(costs):.1f} ms; maps with any changed pixel "
          f"{int((sh > 0).sum())} of {len(sh)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--registered-repeats", type=int, default=3)
    ap.add_argument("--live-s", type=float, default=0.0)
    args = ap.parse_args()
    if args.live_s > 0:
        live(args.live_s)
    cur, s_cur, ref, s_ref = _maps(np.random.default_rng(0))
    delta_wall, delta_cpu = median_ms(lambda: np.subtract(cur, ref), args.repeats)
    fixed_wall, fixed_cpu = median_ms(lambda: change_map(cur, s_cur, ref, s_ref), args.repeats)
    recon_wall, recon_cpu = _recon_baseline()
    print(f"load average {_load()}")
    print(f"fixed scope, {W}x{H}: change map {fixed_wall:.2f} ms wall / {fixed_cpu:.2f} ms CPU"
          f" (target <= 3 ms)")
    print(f"  baseline numpy delta  {delta_wall:.2f} ms wall / {delta_cpu:.2f} ms CPU: "
          f"ratio {fixed_wall / delta_wall:.1f}x wall, {fixed_cpu / max(delta_cpu, 1e-3):.1f}x "
          f"CPU")
    print(f"  baseline recon (1 set) {recon_wall:.2f} ms wall / {recon_cpu:.2f} ms CPU: "
          f"ratio {fixed_wall / recon_wall:.2f}x wall, {fixed_cpu / recon_cpu:.2f}x CPU")
    k = np.array([[1700.0, 0, (W - 1) / 2], [0, 1700.0, (H - 1) / 2], [0, 0, 1]])
    motion = np.eye(4)
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    import cv2

    motion[:3, :3] = cv2.Rodrigues(math.radians(2.0) * axis)[0]
    centre = np.array([0.0, 0.0, 40.0])
    motion[:3, 3] = centre - motion[:3, :3] @ centre + np.array([0.6, -0.5, 0.6])
    ref_pts = _view(k, np.eye(4), 1)
    pts = _view(k, motion, 2)
    sig = np.full((H, W), 0.04, np.float32)
    runs: list[float] = []

    def registered() -> None:
        res = compare(pts[..., 2].copy(), sig, pts, ref_pts[..., 2].copy(), sig, ref_pts,
                      camera_matrix=k, dist_coeffs=np.zeros(5))
        assert res.mode == "registered", res.mode
        assert res.registration is not None
        runs.append(res.registration.residual_mm)

    reg_wall, reg_cpu = median_ms(registered, args.registered_repeats)
    print(f"registered (2 deg, 1 mm), {W}x{H}: {reg_wall:.0f} ms wall / {reg_cpu:.0f} ms CPU "
          f"per map = {1000.0 / reg_wall:.2f} maps/s; ratio {reg_wall / fixed_wall:.0f}x the "
          f"fixed scope; residual {runs[-1]:.3f} mm; load average {_load()}")


if __name__ == "__main__":
    main()
