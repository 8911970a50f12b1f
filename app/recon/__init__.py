"""Pure numerics: patterns, phase, unwrapping, the depth models' tables, points, σ, the fast path.

Imports numpy/numba/cv2 only; no I/O, no threads, no settings.
"""

from app.core.reasons import PRECEDENCE, Reason
from app.core.schedule import PatternSchedule
from app.recon.colormap import depth_colormap, reason_png, render_depth_png
from app.recon.gamma import PhaseErrorLUT
from app.recon.model import ModelTables, evaluate_height, model_tables
from app.recon.patterns import fringe_profile, generate_patterns
from app.recon.phase import WrappedPhase, default_max_code, wrapped_phase
from app.recon.points import RayTables, points_from_height, ray_tables
from app.recon.reconstructor import (
    PhaseResult,
    ReconResult,
    Reconstructor,
    SensorNoise,
    compute_phase,
)
from app.recon.unwrap import (
    DEFAULT_CONSISTENCY_RAD,
    combine_frequencies,
    unwrap_chain,
    unwrap_hierarchical,
    unwrap_phases,
)

__all__ = [
    "DEFAULT_CONSISTENCY_RAD",
    "PRECEDENCE",
    "ModelTables",
    "PatternSchedule",
    "PhaseErrorLUT",
    "PhaseResult",
    "RayTables",
    "Reason",
    "ReconResult",
    "Reconstructor",
    "SensorNoise",
    "WrappedPhase",
    "combine_frequencies",
    "compute_phase",
    "default_max_code",
    "depth_colormap",
    "evaluate_height",
    "fringe_profile",
    "generate_patterns",
    "model_tables",
    "points_from_height",
    "ray_tables",
    "reason_png",
    "render_depth_png",
    "unwrap_chain",
    "unwrap_hierarchical",
    "unwrap_phases",
    "wrapped_phase",
]
