"""The simulator's shared renderers can be given back (tests/helpers/release.py does, above a
memory budget): worlds holding one keep it, the next world builds its own again."""

from __future__ import annotations

from app.devices.sim import SimulatedWorld
from app.devices.sim.world import release_shared_renderers


def test_released_renderers_are_kept_by_their_worlds_and_built_again_for_new_ones() -> None:
    # its own world, not the session's: the shared cache may have evicted that one's renderer
    plane_world = SimulatedWorld("plane", seed=3, distortion=False)
    held = plane_world.renderer
    assert SimulatedWorld("plane", seed=3, distortion=False).renderer is held  # shared
    assert release_shared_renderers() >= 1
    assert release_shared_renderers() == 0  # nothing left to give back
    assert plane_world.renderer is held  # a world keeps the one it has
    again = SimulatedWorld("plane", seed=3, distortion=False).renderer
    assert again is not held and again.shape == held.shape
    assert SimulatedWorld("plane", seed=4, distortion=False).renderer is again  # shared again
