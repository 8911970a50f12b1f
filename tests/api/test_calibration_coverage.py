"""Coverage guidance over REST on the twin: each suggested pose is realised by the twin's board,
captured, and the session's coverage map grows where the advice pointed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from tests.helpers.live_app import capture_after_change, live_settings, wait_for

_ROWS = {"upper": 0, "lower": 2}
_COLS = {"left": 0, "right": 2}


def _block(region: str) -> tuple[int, int]:
    """The ninth (row, col) a region name means."""
    parts = region.split("-") if region != "centre" else []
    i = next((_ROWS[p] for p in parts if p in _ROWS), 1)
    j = next((_COLS[p] for p in parts if p in _COLS), 1)
    return i, j


@pytest.mark.slow
def test_the_advice_drives_the_twin_and_the_coverage_grows(
    tmp_path: Path, sim_calibration_file: Path
) -> None:
    settings = live_settings(tmp_path, sim_calibration_file, sim_scene="plane", sim_seed=13)
    app = create_app(settings)
    with TestClient(app) as client:
        wait_for(client, lambda s: s["results_published"] >= 1, 300, "first result")
        board = {"type": "checkerboard", "inner_corners": [9, 6], "square_mm": 2.0}
        r = client.post("/api/calibration/session", json=board)
        assert r.status_code == 200, r.text
        cov = r.json()["coverage"]
        assert cov["poses"] == 0 and cov["covered_share"] == 0.0 and not cov["reached"]
        assert "reference plane" in cov["suggestion"]["text"]
        shares = []
        for k in range(6):
            s = client.post("/api/calibration/session/suggested-pose").json()
            advice = s["suggestion"]
            assert s["moved"] is True and advice["text"] in s["hint"]
            before = np.array(s["coverage"]["covered"])
            pose = capture_after_change(client)
            assert pose["found"] is True, pose
            cov = pose["coverage"]
            assert cov["poses"] == k + 1
            after = np.array(cov["covered"])
            reached = s["coverage"]["reached"]  # then the advice names no missing cells
            # until the target is reached each advised pose adds cells (earlier poses' heights
            # move a little as the camera is refitted, so a cell on a bin edge may change sides)
            assert reached or after.sum() > before.sum()
            if k > 0 and not reached:
                # the advised ninth at the advised height bin gained board points (once the
                # target is reached the advice names no missing cells: "solve now")
                edges = np.array(cov["height_edges_mm"])
                b = int(np.searchsorted(edges, advice["height_mm"]) - 1)
                i, j = _block(advice["region"])
                rows, cols = after.shape[1] // 3, after.shape[2] // 3
                sl = (b, slice(i * rows, (i + 1) * rows), slice(j * cols, (j + 1) * cols))
                assert after[sl].sum() > before[sl].sum(), (k, advice, after[b])
            sigma = np.array(cov["sigma_model_um"], dtype=float)
            assert np.isfinite(sigma).all() == (k >= 2)  # the model's jackknife needs 3 poses
            shares.append((cov["covered_share"], cov["calibrated_share"]))
            print(f"\npose {k}: {cov['status']}; next: {cov['suggestion']['text']}")
        assert shares[-1][0] > shares[0][0] and shares[-1][1] >= shares[-1][0]
        assert cov["reached"] or shares[-1][1] > shares[1][1]
        # the session describes the same coverage after the fact (a reloaded page reads it)
        again = client.get("/api/calibration/session").json()["coverage"]
        assert again["covered"] == cov["covered"] and again["status"] == cov["status"]
        # the advice's poses make a calibration: solved with both models' held-out errors
        r = client.post("/api/calibration/session/solve", json={})
        assert r.status_code == 200, r.text
        assert r.json()["held_out"]["geometric"]["rms_mm"] < 0.1
        # deleting a pose recomputes the map
        r = client.delete("/api/calibration/session/poses/5")
        assert r.status_code == 200
        assert client.get("/api/calibration/session").json()["coverage"]["poses"] == 5
