"""Tissue scenes: flaps draped on the 45° target, a pile of intestines, an anastomosis."""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import distance_transform_edt

from app.devices.sim.optics import SimRig
from app.devices.sim.radiometry import material_id
from app.devices.sim.scenes.base import (
    F64,
    HeightField,
    Scene,
    Sphere,
    Tool,
    frame_from_normal,
    smooth_noise,
)
from app.devices.sim.scenes.targets import dof_target_field, ruler_printer


def _grid(half_s: float, half_t: float, ds: float) -> tuple[F64, F64]:
    s = np.arange(-half_s, half_s + ds / 2, ds)
    t = np.arange(-half_t, half_t + ds / 2, ds)
    return np.meshgrid(s, t)


def _smoothstep(x: F64) -> F64:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _vessels(shape: tuple[int, int], rng: np.random.Generator, ds: float) -> F64:
    """Albedo multiplier with branching dark vessels (zero crossings of band-limited noise)."""
    n = smooth_noise(shape, 2.5 / ds, rng)
    return 1.0 - 0.35 * np.exp(-((n / 0.06) ** 2)) + 0.06 * smooth_noise(shape, 0.6 / ds, rng)


def flap_scene(rig: SimRig, kind: str, seed: int = 3) -> Scene:
    """A tissue flap (``"skin"`` 2 mm, ``"intestine"`` 1.2 mm thick) draped on the 45° target."""
    rng = np.random.default_rng(seed)
    ds = 0.1
    origin, axes = dof_target_field(rig)
    ss, tt = _grid(16.0, 16.0, ds)
    thickness = 2.0 if kind == "skin" else 1.2
    wobble = smooth_noise(ss.shape, 3.0 / ds, rng)
    r = np.sqrt((ss / 9.0) ** 2 + ((tt + 2.0) / 6.5) ** 2) + 0.08 * wobble
    inside = _smoothstep((1.0 - r) / 0.12)
    folds = (0.25 if kind == "skin" else 0.6) * smooth_noise(ss.shape, 1.5 / ds, rng)
    h = inside * (thickness + folds.clip(-0.5 * thickness, None))
    mat = np.where(h > 0.05, material_id(kind), material_id("white")).astype(np.uint8)
    tex = np.where(h > 0.05, _vessels(ss.shape, rng, ds) if kind == "intestine"
                   else 1.0 + 0.06 * smooth_noise(ss.shape, 0.8 / ds, rng), 1.0)
    hf = HeightField(origin, axes, h, float(ss[0, 0]), float(tt[0, 0]), ds, mat,
                     tex.astype(np.float32), printed=ruler_printer())
    return Scene(f"{kind}_flap", hf, description=f"{kind} flap on the 45° target")


def _tube_heights(ss: F64, tt: F64, ds: float, curve: F64, radius: float, lift: float | F64) -> F64:
    """Height of a tube of ``radius`` lying along ``curve`` ((n, 2) s/t points), resting at ``lift``
    (a height or a per-cell height map); ``-inf`` off the tube."""
    ny, nx = ss.shape
    mask = np.ones((ny, nx), bool)
    ix = np.clip(np.rint((curve[:, 0] - ss[0, 0]) / ds).astype(int), 0, nx - 1)
    iy = np.clip(np.rint((curve[:, 1] - tt[0, 0]) / ds).astype(int), 0, ny - 1)
    mask[iy, ix] = False
    d = distance_transform_edt(mask) * ds
    return np.where(d < radius, lift + radius + np.sqrt(np.clip(radius**2 - d**2, 0, None)),
                    -np.inf)


def pile_scene(rig: SimRig, seed: int = 5) -> Scene:
    """Loops of intestine of three pigments on a platform translating ±3 mm (period 8 s)."""
    rng = np.random.default_rng(seed)
    ds = 0.1
    origin, axes = frame_from_normal(rig.reference_point_mm, rig.reference.normal)
    ss, tt = _grid(26.0, 20.0, ds)
    h = np.zeros_like(ss)
    mat = np.full(ss.shape, material_id("white"), np.uint8)
    pigments = ["intestine", "intestine_dark", "intestine_pale"]
    u = np.linspace(-30, 30, 3000)
    for i in range(7):
        ang = rng.uniform(0, math.pi)
        off = rng.uniform(-12, 12)
        amp, wl, ph = rng.uniform(2, 6), rng.uniform(12, 25), rng.uniform(0, 2 * math.pi)
        v = off + amp * np.sin(2 * math.pi * u / wl + ph)
        curve = np.stack([u * math.cos(ang) - v * math.sin(ang),
                          u * math.sin(ang) + v * math.cos(ang)], -1)
        radius = rng.uniform(2.5, 4.0)
        lift = 0.0 if i < 3 else rng.uniform(1.5, 4.0)
        th = _tube_heights(ss, tt, ds, curve, radius, lift)
        top = th > h
        h = np.where(top, th, h)
        mat[top] = material_id(pigments[i % 3])
    tex = np.where(mat != material_id("white"), _vessels(ss.shape, rng, ds), 1.0).astype(np.float32)
    hf = HeightField(origin, axes, h, float(ss[0, 0]), float(tt[0, 0]), ds, mat, tex)
    e_s = axes[:, 0].copy()
    return Scene("intestine_pile", hf, motion=lambda t: 3.0 * math.sin(2 * math.pi * t / 8.0) * e_s,
                 description="intestine loops of three pigments on a translating platform")


def anastomosis_scene(rig: SimRig, seed: int = 7, suture: str = "suture") -> Scene:
    """Bowel end opened in a diamond by four stay sutures, running stitches 0.72 mm high,
    breathing (0.25 Hz, 1.5 mm peak-to-peak) and forceps moving through the view.

    ``suture``: the thread's material — ``"suture"`` (violet-dyed, darker than the tissue in
    green light) or ``"suture_bright"`` (undyed, brighter than the tissue): scene
    ``anastomosis_bright``.
    """
    rng = np.random.default_rng(seed)
    ds = 0.08  # 9 samples across a 0.72 mm stitch
    ref = rig.reference
    origin, axes = frame_from_normal(rig.reference_point_mm, ref.normal)
    ss, tt = _grid(22.0, 17.0, ds)
    a, b = 7.0, 5.0
    diamond = np.abs(ss) / a + np.abs(tt) / b  # 1 on the lumen edge
    wall = (6.0 + 0.8 * smooth_noise(ss.shape, 4.0 / ds, rng)
            + 0.15 * smooth_noise(ss.shape, 0.8 / ds, rng))
    cuff = 1.0 * np.exp(-(((diamond - 1.0) / 0.12) ** 2))
    depth = _smoothstep((diamond - 0.85) / 0.15)  # 0 inside the lumen, 1 on the wall
    h = 1.0 + depth * (wall - 1.0) + cuff * depth
    mat = np.where(depth > 0.5, material_id("intestine"),
                   material_id("intestine_dark")).astype(np.uint8)
    r = 0.36  # suture radius: a stitch stands 0.72 mm above the tissue
    stitches = []
    for k in range(6):  # running stitches across the upper-left edge of the diamond
        f = (k + 0.5) / 6.0
        centre = np.array([-a * (1 - f), -b * f])
        normal = np.array([-1 / a, -1 / b]) / math.hypot(1 / a, 1 / b)
        stitches.append(np.linspace(centre - 1.4 * normal, centre + 1.6 * normal, 200))
    for corner in ((a, 0), (-a, 0), (0, b), (0, -b)):  # stay sutures pulling outward
        c = np.array(corner, float)
        stitches.append(np.linspace(c, c * 3.0, 400))
    base = h.copy()
    for curve in stitches:
        tube = _tube_heights(ss, tt, ds, curve, r, base)
        on = np.isfinite(tube)
        h = np.maximum(h, tube)
        mat[on] = material_id(suture)
    tex = np.where(mat == material_id(suture), 1.0, _vessels(ss.shape, rng, ds)).astype(np.float32)
    hf = HeightField(origin, axes, h, float(ss[0, 0]), float(tt[0, 0]), ds, mat, tex)
    n = ref.normal.copy()

    def forceps(t: float) -> tuple[F64, F64]:
        ph = 2 * math.pi * t / 6.0
        tip = origin + axes @ np.array([6.0 * math.cos(ph) - 2.0, 4.0 * math.sin(ph), 13.0])
        direction = np.array([1.0, -0.35, -0.45])
        return tip, tip + 40.0 * direction / np.linalg.norm(direction)

    name = "anastomosis" if suture == "suture" else "anastomosis_bright"
    return Scene(name, hf, tool=Tool(forceps, 1.3),
                 motion=lambda t: 0.75 * math.sin(2 * math.pi * 0.25 * t) * n,
                 description="end-to-end anastomosis with stay sutures, "
                             "running stitches and forceps")


#: breathing: heave of the tissue along the reference normal (mm, amplitude) and its rate (Hz)
BREATHING_AMPLITUDE_MM = 2.0  # 4 mm peak to peak
BREATHING_HZ = 0.25


def breathing_scene(rig: SimRig, seed: int = 5) -> Scene:
    """The intestine loops of :func:`pile_scene` heaving with breathing: 4 mm peak to peak along
    the reference normal at 0.25 Hz (peak speed 3.1 mm/s), no tool."""
    base = pile_scene(rig, seed)
    n = rig.reference.normal.copy()
    amp, hz = BREATHING_AMPLITUDE_MM, BREATHING_HZ
    return Scene("breathing", base.surface,
                 motion=lambda t: amp * math.sin(2 * math.pi * hz * t) * n,
                 description="intestine loops heaving 4 mm peak to peak at 0.25 Hz (breathing)")


def tool_scene(rig: SimRig, seed: int = 5) -> Scene:
    """Still intestine loops with forceps sweeping across them: the tip runs ±10 mm along the
    surface's s axis, 8 mm above it, at 0.1 Hz (peak speed 6.3 mm/s)."""
    base = pile_scene(rig, seed)
    hf = base.surface
    origin, axes = hf.origin, hf.axes

    def forceps(t: float) -> tuple[F64, F64]:
        tip = origin + axes @ np.array([10.0 * math.sin(2 * math.pi * 0.1 * t), 3.0, 14.0])
        direction = np.array([0.3, -1.0, -0.5])  # the shaft rises toward the scope (camera z falls)
        return tip, tip + 40.0 * direction / np.linalg.norm(direction)

    return Scene("tool", hf, tool=Tool(forceps, 1.3),
                 description="still intestine loops, forceps sweeping ±10 mm across them at 0.1 Hz")


def still_tissue_scene(rig: SimRig, seed: int = 5) -> Scene:
    """The intestine loops of :func:`pile_scene`, still: the reference scene of a change map."""
    base = pile_scene(rig, seed)
    return Scene("tissue_still", base.surface,
                 description="still intestine loops (the change map's reference scene)")


def with_bumps(scene: Scene, bumps: list[tuple[float, float, float, float]],
               name: str | None = None) -> Scene:
    """``scene`` with local bumps (height > 0) or dents (< 0) on its height field.

    Args:
        scene: the scene to deform (not changed).
        bumps: ``(s_mm, t_mm, height_mm, diameter_mm)`` each: a raised-cosine bump
            ``height·(1 + cos(π r / R)) / 2`` (R = diameter / 2) along the field's normal
            centred at (s, t) of the field.
        name: the new scene's name (default ``<name>_deformed``).
    """
    hf = scene.surface
    ny, nx = hf.heights.shape
    ss = hf.s0 + hf.ds * np.arange(nx)[None, :]
    tt = hf.t0 + hf.ds * np.arange(ny)[:, None]
    h = hf.heights.copy()
    for s_mm, t_mm, height_mm, diameter_mm in bumps:
        if not diameter_mm > 0:
            raise ValueError(f"bumps: diameter must be > 0 mm, got {diameter_mm}")
        r = np.hypot(ss - s_mm, tt - t_mm) / (0.5 * diameter_mm)
        h += np.where(r < 1.0, 0.5 * height_mm * (1.0 + np.cos(math.pi * np.minimum(r, 1.0))),
                      0.0)
    surface = HeightField(hf.origin, hf.axes, h, hf.s0, hf.t0, hf.ds, hf.material, hf.texture,
                          hf.printed)
    return Scene(name or f"{scene.name}_deformed", surface, list(scene.spheres), scene.tool,
                 scene.motion, scene.description + "; " + ", ".join(
                     f"{'bump' if b[2] > 0 else 'dent'} {abs(b[2]):.2f} mm Ø {b[3]:.1f} mm"
                     for b in bumps))


def field_point(scene: Scene, s_mm: float, t_mm: float) -> F64:
    """(3,) camera-frame point of the height field at (s, t) on its surface, mm."""
    hf = scene.surface
    i = int(round((t_mm - hf.t0) / hf.ds))
    j = int(round((s_mm - hf.s0) / hf.ds))
    out: F64 = hf.origin + hf.axes @ np.array([s_mm, t_mm, hf.heights[i, j]])
    return out


def scope_moved(scene: Scene, rotation_deg: float, axis: tuple[float, float, float],
                translation_mm: tuple[float, float, float], pivot_mm: F64 | None = None,
                name: str | None = None) -> Scene:
    """``scene`` seen after the scope moved: every part moved rigidly in the camera frame.

    ``X' = R (X − p) + p + t`` with R ``rotation_deg`` about ``axis`` through ``pivot_mm``
    (default the surface's origin) and t ``translation_mm``; a scene motion and a tool path
    move the same way.
    """
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_rotvec(math.radians(rotation_deg) * np.asarray(axis, np.float64)
                               / np.linalg.norm(axis)).as_matrix()
    hf = scene.surface
    pivot = hf.origin if pivot_mm is None else np.asarray(pivot_mm, np.float64)
    shift = np.asarray(translation_mm, np.float64)

    def move(p: F64) -> F64:
        out: F64 = rot @ (np.asarray(p, np.float64) - pivot) + pivot + shift
        return out

    surface = HeightField(move(hf.origin), rot @ hf.axes, hf.heights, hf.s0, hf.t0, hf.ds,
                          hf.material, hf.texture, hf.printed)
    spheres = [Sphere(move(sp.centre), sp.radius_mm, sp.material) for sp in scene.spheres]
    tool = None
    if scene.tool is not None:
        path = scene.tool.path

        def moved_path(t: float) -> tuple[F64, F64]:
            a, b = path(t)
            return move(a), move(b)

        tool = Tool(moved_path, scene.tool.radius_mm, scene.tool.material)
    motion = None
    if scene.motion is not None:
        m = scene.motion

        def motion_rotated(t: float) -> F64:
            out: F64 = rot @ np.asarray(m(t), np.float64)
            return out

        motion = motion_rotated
    return Scene(name or f"{scene.name}_moved", surface, spheres, tool, motion,
                 scene.description + f"; scope moved {rotation_deg:g}° and "
                 f"{np.linalg.norm(shift):g} mm")


def pressing_tool(scene: Scene, s_mm: float, t_mm: float, press_mm: float,
                  dent_diameter_mm: float, name: str | None = None) -> Scene:
    """``scene`` with a still forceps tip pressing its surface at (s, t): a dent ``press_mm``
    deep and ``dent_diameter_mm`` across, the tool's capsule (r 1.3 mm) resting in it."""
    dented = with_bumps(scene, [(s_mm, t_mm, -press_mm, dent_diameter_mm)])
    hf = dented.surface
    radius = 1.3
    tip_local = np.array([s_mm, t_mm, -press_mm + radius])
    tip = hf.origin + hf.axes @ tip_local
    direction = hf.axes @ np.array([0.3, -0.4, 1.0])  # the shaft rises toward the scope
    end = tip + 40.0 * direction / np.linalg.norm(direction)
    return Scene(name or f"{scene.name}_pressed", hf, list(dented.spheres),
                 Tool(lambda t: (tip, end), radius), dented.motion,
                 dented.description + f"; forceps pressing {press_mm:g} mm")
