"""The per-scene renderer: geometry and shading precomputed once, per frame only
fringes, motion and noise (see kernels.py). Also the ground truth of any instant."""

from __future__ import annotations

import math
import threading
from dataclasses import replace

import numpy as np
import numpy.typing as npt
from scipy.ndimage import gaussian_filter

from app.core.limits import DEFAULT_LED, full_scale
from app.core.schedule import PatternSchedule
from app.devices.sim import kernels, tool_kernels
from app.devices.sim.optics import SimRig, mat3
from app.devices.sim.radiometry import (
    MATERIALS,
    REFLECTANCE,
    SPECULAR,
    SSS_MM,
    SensorModel,
    defocus_sigma_px,
    gaussian_quantile_table,
    projector_response_lut,
)
from app.devices.sim.raycast import raycast_capsule
from app.devices.sim.scenes.base import F64, Scene
from app.devices.sim.shading_kernels import shade_combine, shade_geometry, shade_terms
from app.devices.sim.trace import integrate_print, trace

F32 = npt.NDArray[np.float32]
_TABLE = gaussian_quantile_table()
BLOCK = 8  # tile size (px) of the per-tile motion flow


def blur_varying(img: F64, sigma_px: F64,
                 levels: tuple[float, ...] = (0.0, 0.75, 1.5, 3.0, 6.0)) -> F64:
    """Spatially varying Gaussian blur by interpolating between a few pre-blurred copies."""
    sig = np.clip(np.nan_to_num(sigma_px, nan=0.0), levels[0], levels[-1])
    # blur only to the levels some pixel needs (a board in focus never reaches 3 or 6 px)
    stack: dict[int, F64] = {}

    def blurred(i: int) -> F64:
        if i not in stack:
            s = levels[i]
            stack[i] = img if s == 0 else gaussian_filter(img, s, mode="nearest")
        return stack[i]

    out = np.array(blurred(0), copy=True)
    for lo in range(len(levels) - 1):
        sel = (sig > levels[lo]) & (sig <= levels[lo + 1])
        if not sel.any():
            continue
        a = (sig[sel] - levels[lo]) / (levels[lo + 1] - levels[lo])
        out[sel] = (1 - a) * blurred(lo)[sel] + a * blurred(lo + 1)[sel]
    return out


class Renderer:
    """Renders frames of ``scene`` as seen by ``rig`` under the fringe ``schedule``.

    Args:
        projector_gamma: DMD response exponent (1 = linear, as the LightCrafter in pattern mode).
    """

    def __init__(self, scene: Scene, rig: SimRig, *, schedule: PatternSchedule | None = None,
                 sensor: SensorModel | None = None, projector_gamma: float = 1.0,
                 geometry: dict[str, npt.NDArray[np.generic]] | None = None) -> None:
        """``geometry``: the arrays :meth:`geometry` returned for the same scene, rig and
        schedule (e.g. from the disk cache), instead of tracing the scene again (seconds)."""
        self.scene, self.rig = scene, rig
        self.schedule = schedule or PatternSchedule()
        self.sensor = sensor or SensorModel()
        self.lut = projector_response_lut(projector_gamma)
        theta = np.linspace(0, 2 * math.pi, 4096, endpoint=False)
        self.qbar = float(self.lut[np.rint(255 * (0.5 + 0.5 * np.cos(theta))).astype(int)].mean())
        w, h = rig.camera.image_size
        self.shape = (h, w)
        geo = geometry if geometry is not None else self._trace_geometry()
        # all float64 but the material codes (asarray: no copy of arrays of that dtype)
        self.rays: F64 = np.asarray(geo["rays"], np.float64)  # (H·W, 3)
        self.points: F64 = np.asarray(geo["points"], np.float64)  # (H, W, 3) mm
        self._normals: F64 = np.asarray(geo["normals"], np.float64)  # (H·W, 3)
        self._material: npt.NDArray[np.uint8] = np.asarray(geo["material"], np.uint8)  # (H·W,)
        self.sigma_cam: F64 = np.asarray(geo["sigma_cam"], np.float64)  # (H, W) px
        self.albedo: F64 = np.asarray(geo["albedo"], np.float64)  # (H·W,)
        # (H, W) continuous projector coordinate along the fringe axis (the column for vertical
        # fringes)
        self.xp: F64 = np.asarray(geo["xp"], np.float64)
        self.grad_xp: F64 = np.asarray(geo["grad_xp"], np.float64)  # (H·W,)
        self.grad_median = float(geo["grad_median"])
        self._led_cache: dict[str, tuple[F32, F32, F32, F32]] = {}
        self._trig: tuple[F32, F32] | None = None
        self._cache_lock = threading.RLock()
        self._means: F32 | None = None
        self._means_key: tuple[object, ...] | None = None
        self._truth_static: tuple[F32, F32] | None = None
        self._scratch = threading.local()  # per-thread mean buffer (worlds may share a renderer)
        self._nd: F32 | None = None
        self._planes: tuple[F64, F64] | None = None
        self._tiles: tuple[F64, F64, F64] | None = None
        # Projector output over one fringe period: cosine → 8-bit DMD level → response.
        frac = (np.arange(4096) + 0.5) / 4096
        self.qtab = self.lut[np.rint(255 * (0.5 + 0.5 * np.cos(2 * math.pi * frac))).astype(int)]

    def _trace_geometry(self) -> dict[str, npt.NDArray[np.generic]]:
        """The static scene's geometry as seen by the rig: what :meth:`geometry` returns."""
        rig, (h, w) = self.rig, self.shape
        rays = rig.camera.pixel_rays().reshape(-1, 3)
        hits = trace(replace(self.scene, motion=None, tool=None), rays, 0.0)
        points = hits.points.reshape(h, w, 3)
        printed = integrate_print(self.scene.surface, hits.st, hits.material, (h, w))
        alb = hits.albedo.reshape(h, w) * printed
        z = points[..., 2]
        sigma_cam = defocus_sigma_px(np.nan_to_num(z, nan=rig.focus_mm), rig.focus_mm,
                                     rig.blur_per_inv_mm)
        xp = rig.projector.fringe_coordinate(points, self.schedule.orientation)
        grad = np.hypot(np.gradient(xp, axis=1), np.gradient(xp, axis=0))
        grad_median = float(np.nanmedian(grad))
        return {"rays": rays, "points": points, "normals": hits.normals, "material": hits.material,
                "sigma_cam": sigma_cam, "albedo": blur_varying(alb, sigma_cam).ravel(), "xp": xp,
                "grad_xp": np.where(np.isfinite(grad), grad, grad_median).ravel(),
                "grad_median": np.asarray(grad_median)}

    def geometry(self) -> dict[str, npt.NDArray[np.generic]]:
        """The traced geometry (rays, points, normals, material, albedo, blur, projector
        coordinate and its gradient), to build another Renderer of the same scene without
        tracing: the arrays are shared, never written after construction."""
        return {"rays": self.rays, "points": self.points, "normals": self._normals,
                "material": self._material, "sigma_cam": self.sigma_cam, "albedo": self.albedo,
                "xp": self.xp, "grad_xp": self.grad_xp, "grad_median": np.asarray(self.grad_median)}

    # -- shading ---------------------------------------------------------------------------
    def shade(self, points: F64, normals: F64, material: npt.NDArray[np.uint8], albedo: F64,
              sigma_cam: F64, grad_xp: F64, led: str) -> tuple[F64, F64]:
        """(base, fringe) for points (N, 3): base = reflected fraction of the projector light
        (diffuse + specular, inverse square, mm⁻²); fringe (F, N) = the part that keeps the
        fringe modulation of frequency k after defocus and subsurface blur."""
        proj = self.rig.projector
        k = np.asarray(self.schedule.frequencies, np.float64)
        n_pts = points.shape[0]
        d_p, cos_i, cos_h = np.empty(n_pts), np.empty(n_pts), np.empty(n_pts)
        lit = np.empty(n_pts, np.bool_)
        # distance, incidence and half-vector cosines and the projector's lit test, one pass
        pts, nrm, centre, rot, kp = (np.ascontiguousarray(a, np.float64)
                                     for a in (points, normals, proj.centre, proj.R, proj.K))
        shade_geometry(pts, nrm, centre, rot, kp, float(self.schedule.width),
                       float(proj.size[1]), d_p, cos_i, cos_h, lit)
        names = [MATERIALS[m] for m in range(len(MATERIALS))]
        refl = np.array([REFLECTANCE[n][led] for n in names])[material] * albedo
        ks = np.array([SPECULAR.get(n, (0.0, 1.0))[0] for n in names])[material]
        shin = np.array([SPECULAR.get(n, (0.0, 1.0))[1] for n in names])[material]
        sss = np.array([SSS_MM.get(n, {}).get(led, 0.0) for n in names])[material]
        spec = 0.05 * ks * cos_h**shin  # pow in numpy: its SIMD pow is the reference's
        f_px = float(self.rig.camera.K[0, 0])
        g_d, g_s = np.empty(n_pts), np.empty(n_pts)
        # exponents of the fringe attenuation (σ² → exponent), then exp in place (numpy's)
        exp_d, exp_s = np.empty((k.size, n_pts)), np.empty((k.size, n_pts))
        shade_terms(refl, cos_i, d_p, spec, lit, np.ascontiguousarray(sigma_cam, np.float64),
                    np.ascontiguousarray(grad_xp, np.float64), sss,
                    np.ascontiguousarray(pts[:, 2]), f_px,
                    0.5 * self.rig.projector_blur_per_inv_mm, 1.0 / self.rig.projector_focus_mm,
                    2 * math.pi * k, float(self.schedule.axis_length), g_d, g_s, exp_d, exp_s)
        np.exp(exp_d, out=exp_d)
        np.exp(exp_s, out=exp_s)
        base = np.empty(n_pts)
        shade_combine(g_d, g_s, exp_d, exp_s, base, exp_d)  # the fringe parts over exp_d
        return base, exp_d

    def _led_arrays(self, led: str) -> tuple[F32, F32]:
        with self._cache_lock:
            return self._led_arrays_locked(led)

    def _led_arrays_locked(self, led: str) -> tuple[F32, F32]:
        if led not in self._led_cache:
            pts = self.points.reshape(-1, 3)
            safe = np.where(np.isfinite(pts), pts, np.array([0.0, 0.0, 1e6]))
            base, fringe = self.shade(safe, np.nan_to_num(self._normals), self._material,
                                      self.albedo, self.sigma_cam.ravel(), self.grad_xp, led)
            entry = (base.astype(np.float32), fringe.astype(np.float32), None, None)
            self._led_cache[led] = entry  # type: ignore[assignment]
        b, f, _, _ = self._led_cache[led]
        return b, f

    def _phase_tables(self) -> tuple[F32, F32]:
        with self._cache_lock:
            return self._phase_tables_locked()

    def _phase_tables_locked(self) -> tuple[F32, F32]:
        if self._trig is None:
            k = np.asarray(self.schedule.frequencies, np.float64)[:, None]
            phi = 2 * math.pi * k * np.nan_to_num(self.xp.ravel())[None] / self.schedule.axis_length
            self._trig = (np.cos(phi).astype(np.float32), np.sin(phi).astype(np.float32))
        return self._trig

    # -- frames ----------------------------------------------------------------------------
    def scales(self, *, exposure_ms: float, gain: float, led: str, current: float, bits: int
               ) -> tuple[float, float, float, float, int]:
        """(DN per unit base, ambient DN, DN per electron, read variance DN², max DN)."""
        s = self.sensor
        g = s.dn_per_electron(bits, gain)
        return (g * s.light_scale(exposure_ms=exposure_ms, current=current, led=led),
                g * s.ambient_e_per_ms * exposure_ms, g, (g * s.read_noise_e) ** 2,
                full_scale(bits))

    def mean_frame(self, pattern_index: int, t_s: float, *, exposure_ms: float, gain: float = 1.0,
                   led: str = DEFAULT_LED, current: float = 0.5, bits: int = 8) -> F32:
        """Noise-free expected frame (H, W) float32 DN, before clipping
        (projector dark if index < 0)."""
        scale, amb, _, _, _ = self.scales(exposure_ms=exposure_ms, gain=gain, led=led,
                                          current=current, bits=bits)
        mean = np.empty(self.shape, np.float32)
        self._mean_into(mean, pattern_index, t_s, scale, amb, led)
        return mean

    def _mean_into(self, mean: F32, pattern_index: int, t_s: float, scale: float, amb: float,
                   led: str) -> None:
        if pattern_index < 0:
            mean.fill(amb)
            return
        fi, n = divmod(pattern_index % self.schedule.n_frames, self.schedule.steps)
        shift = 2 * math.pi * n / self.schedule.steps
        base, fringe = self._led_arrays(led)
        if self.scene.is_static:
            ck, sk = self._phase_tables()
            kernels.mean_static(mean.reshape(-1), base, fringe[fi], ck[fi], sk[fi], math.cos(shift),
                                math.sin(shift), self.lut, self.qbar, scale, amb)
            return
        self._moving(mean, False, fi, shift, t_s, scale, amb, led, 0.0, 0.0, 0,
                     np.zeros(1, np.uint64))

    def _moving(self, out: np.ndarray, noisy: bool, fi: int, shift: float, t_s: float, scale: float,
                amb: float, led: str, g: float, read2: float, maxv: int,
                state: npt.NDArray[np.uint64]) -> None:
        """Mean (``noisy`` False, float32 ``out``) or noisy frame of the moving scene
        and its tool, one pass."""
        h, w = self.shape
        base, fringe = self._led_arrays(led)
        alpha, _, gam, _ = self.rig.projector.fringe_coefficients(self.schedule.orientation)
        k = self.schedule.frequencies[fi]
        delta = self.scene.offset(t_s)
        scene = (self._nd_table(), base.reshape(h, w), fringe[fi].reshape(h, w),
                 self._block_flow(delta), BLOCK, float(alpha @ delta), float(gam @ delta),
                 k / self.schedule.axis_length, shift / (2 * math.pi),
                 float(self.schedule.axis_length), self.qtab, self.qbar, scale, amb, g, read2, maxv,
                 _TABLE, state)
        band, zbuf, kk, qv = self._scratch_rows()
        if self.scene.tool is None:
            kernels.moving_frame(out, noisy, band, zbuf, kk, qv, *scene)
            return
        # With a tool: raster order (the noise sequence of add_noise over the mean frame).
        v0, spans, tool = self._tool_frame(fi, shift, t_s, led, float(delta[2]))
        rays, zs = self._tool_planes()
        tool_kernels.tool_frame(out, noisy, band[0], zbuf, kk, qv, *scene, rays, zs, v0, spans,
                                tool, self.lut)

    def _scratch_rows(self) -> tuple[F32, F32, npt.NDArray[np.int32], F32]:
        """This thread's scratch for the frame kernels (allocated once): a (BLOCK, W) float32 band
        of mean rows, (W,) float32 deviates, (W,) int32 projector-table indices,
        (W,) float32 table values."""
        rows = getattr(self._scratch, "rows", None)
        if rows is None:
            w = self.shape[1]
            rows = self._scratch.rows = (np.empty((BLOCK, w), np.float32), np.empty(w, np.float32),
                                         np.empty(w, np.int32), np.empty(w, np.float32))
        return rows

    def _tool_planes(self) -> tuple[F64, F64]:
        """Unit pixel rays as (3, H, W) float64 planes and the rest-pose depth (H, W) float64 mm
        (NaN off-object), for tool_kernels.tool_frame: contiguous rows let its loops
        vectorise (built once)."""
        with self._cache_lock:
            if self._planes is None:
                h, w = self.shape
                self._planes = (np.ascontiguousarray(self.rays.T.reshape(3, h, w)),
                                np.ascontiguousarray(self.points[..., 2]))
            return self._planes

    def _nd_table(self) -> F32:
        with self._cache_lock:
            return self._nd_table_locked()

    def _nd_table_locked(self) -> F32:
        if self._nd is None:
            alpha, a_c, gam, g_c = self.rig.projector.fringe_coefficients(self.schedule.orientation)
            # (2, H, W): numerator and denominator planes, contiguous rows for the vectorised
            # kernels
            self._nd = np.stack([mat3(self.points, alpha) - a_c,
                                 mat3(self.points, gam) - g_c]).astype(np.float32)
        return self._nd

    def _tile_centres(self) -> tuple[F64, F64, F64]:
        """Rest-pose centre points (tiles_y, tiles_x, 3) mm of the BLOCK×BLOCK tiles (NaN where the
        image ends or no surface) and their normalised image coordinates x/z, y/z."""
        with self._cache_lock:
            if self._tiles is None:
                h, w = self.shape
                c = self.points[BLOCK // 2 :: BLOCK, BLOCK // 2 :: BLOCK]
                pad = np.full((-(-h // BLOCK), -(-w // BLOCK), 3), np.nan)
                pad[: c.shape[0], : c.shape[1]] = c
                with np.errstate(invalid="ignore"):
                    self._tiles = (pad, pad[..., 0] / pad[..., 2], pad[..., 1] / pad[..., 2])
            return self._tiles

    def _block_flow(self, delta: F64) -> npt.NDArray[np.int64]:
        """Integer pinhole image flow of each BLOCK×BLOCK tile for a translation ``delta`` (mm)."""
        pad, x0, y0 = self._tile_centres()
        fx, fy = self.rig.camera.K[0, 0], self.rig.camera.K[1, 1]
        with np.errstate(invalid="ignore"):
            z1 = pad[..., 2] + delta[2]
            fu = fx * ((pad[..., 0] + delta[0]) / z1 - x0)
            fv = fy * ((pad[..., 1] + delta[1]) / z1 - y0)
        flow: F64 = np.stack([fu, fv], -1)
        if np.isnan(flow).any():  # tiles with no surface at their centre take the mean flow
            fill = (np.nanmean(flow.reshape(-1, 2), axis=0) if np.isfinite(flow).any()
                    else np.zeros(2))
            flow = np.where(np.isnan(flow), fill, flow)
        return np.rint(flow).astype(np.int64)

    def _tool_frame(self, fi: int, shift: float, t_s: float, led: str, dz: float
                    ) -> tuple[int, npt.NDArray[np.int64], tool_kernels.ToolFrame]:
        """The tool at ``t_s`` for tool_kernels.tool_frame: (v0, spans, tool) with spans (n, 2) the
        first/last column to ray-test in rows v0 .. v0 + n − 1 (its image; n = 0
        when it is out of view)."""
        tool = self.scene.tool
        assert tool is not None
        p0, p1 = (np.asarray(p, np.float64) for p in tool.path(t_s))
        cam, proj = self.rig.camera, self.rig.projector
        ends = np.stack([p0, p1])
        ends = ends[ends[:, 2] > 1.0]
        v0, spans = (self._tool_spans(cam.project(ends),
                                      cam.K[0, 0] * tool.radius_mm / ends[:, 2].min() + 4)
                     if len(ends) else (0, np.zeros((0, 2), np.int64)))
        axis = p1 - p0
        length = float(np.linalg.norm(axis))
        alpha, a_c, gam, g_c = proj.fringe_coefficients(self.schedule.orientation)
        k = self.schedule.frequencies[fi]
        ks, shin = SPECULAR.get(tool.material, (0.0, 1.0))
        assert shin == int(shin) and 0 <= shin < 1024, (
            "tool_kernels._tool_dn_run takes a whole specular exponent")
        # Fringe attenuation on the tool from camera defocus at its mean depth.
        z_mid = float(np.clip(ends[:, 2].mean(), 5.0, 80.0)) if len(ends) else self.rig.focus_mm
        sig = float(defocus_sigma_px(z_mid, self.rig.focus_mm, self.rig.blur_per_inv_mm))
        axis_px = self.schedule.axis_length
        atten = math.exp(-((2 * math.pi * k * self.grad_median / axis_px) ** 2) * sig**2 / 2)
        # The projector coordinate across the fringes is not traced (the tool stays inside the DMD);
        # only its centre line is tested.
        across = 1 if self.schedule.orientation == "vertical" else 0
        rows_lit = -0.5 <= proj.K[across, 2] <= float(proj.size[across])
        return v0, spans, tool_kernels.ToolFrame(
            p0, axis / length, length, float(tool.radius_mm),
            float(REFLECTANCE[tool.material][led]), float(ks), float(shin),
            np.asarray(proj.centre, np.float64), alpha, a_c, gam, g_c, float(axis_px),
            bool(rows_lit), 2 * math.pi * k / axis_px, shift, atten, dz)

    def _tool_spans(self, uv: F64, rad_px: float) -> tuple[int, npt.NDArray[np.int64]]:
        """Row spans (v0, (n, 2) first/last column) of the stadium of radius ``rad_px`` swept by a
        disc along the image segment ``uv`` ((1 or 2, 2) px), clipped to the
        image (n = 0 if outside)."""
        h, w = self.shape
        none = (0, np.zeros((0, 2), np.int64))
        samples = uv[0] + np.linspace(0, 1, 96)[:, None] * (uv[-1] - uv[0])
        v0 = int(max(samples[:, 1].min() - rad_px, 0))
        v1 = int(min(samples[:, 1].max() + rad_px, h - 1))
        if v1 < v0 or samples[:, 0].max() + rad_px < 0 or samples[:, 0].min() - rad_px > w - 1:
            return none
        # per row: numba (the numpy (rows, samples) version cost 0.6 ms per frame)
        return v0, tool_kernels.tool_spans(samples[:, 0].copy(), samples[:, 1].copy(), v0, v1,
                                           float(rad_px), w)

    def _static_means(self, exposure_ms: float, gain: float, led: str, current: float,
                      bits: int) -> F32:
        """Noise-free frames of every pattern for these settings (static scenes; one cached set)."""
        key = (exposure_ms, gain, led, current, bits)
        with self._cache_lock:
            if self._means_key != key:
                scale, amb, _, _, _ = self.scales(exposure_ms=exposure_ms, gain=gain, led=led,
                                                  current=current, bits=bits)
                # a fresh array: a world sharing this renderer may still be reading the old one
                means = np.empty((self.schedule.n_frames, *self.shape), np.float32)
                for i in range(self.schedule.n_frames):
                    self._mean_into(means[i], i, 0.0, scale, amb, led)
                self._means, self._means_key = means, key
            assert self._means is not None
            return self._means

    def render(self, pattern_index: int, t_s: float, state: npt.NDArray[np.uint64], *,
               exposure_ms: float, gain: float = 1.0, led: str = DEFAULT_LED, current: float = 0.5,
               bits: int = 8
               ) -> npt.NDArray[np.uint8] | npt.NDArray[np.uint16]:
        """One noisy frame (H, W), uint8 for 8 bits or uint16 0..4095 for 12 bits.

        ``state``: (1,) uint64 generator state (non-zero), advanced in place.
        """
        scale, amb, g, read2, maxv = self.scales(exposure_ms=exposure_ms, gain=gain, led=led,
                                                 current=current, bits=bits)
        out = np.empty(self.shape, np.uint8 if bits <= 8 else np.uint16)
        flat = out.reshape(-1)
        if self.scene.is_static and pattern_index >= 0:
            means = self._static_means(exposure_ms, gain, led, current, bits)
            kernels.add_noise(flat, means[pattern_index % self.schedule.n_frames].reshape(-1), g,
                              read2, maxv, _TABLE, state)
            return out
        if pattern_index >= 0:  # rigid motion (and the tool): one fused pass
            fi, n = divmod(pattern_index % self.schedule.n_frames, self.schedule.steps)
            self._moving(out, True, fi, 2 * math.pi * n / self.schedule.steps, t_s, scale, amb, led,
                         g, read2, maxv, state)
            return out
        buf = getattr(self._scratch, "mean", None)
        if buf is None:
            buf = self._scratch.mean = np.empty(self.shape, np.float32)
        self._mean_into(buf, pattern_index, t_s, scale, amb, led)
        kernels.add_noise(flat, buf.reshape(-1), g, read2, maxv, _TABLE, state)
        return out

    # -- truth -----------------------------------------------------------------------------
    def truth(self, t_s: float = 0.0) -> tuple[F32, F32]:
        """True depth (H, W) float32 mm above the reference plane (NaN off-object) and true
        points (H, W, 3) float32 mm in the camera frame, for the instant ``t_s``.

        This is the surface the frames rendered at ``t_s`` show. A rigidly moving scene is
        rendered from its rest pose through a per-tile (``BLOCK`` px) integer image flow
        (:func:`kernels.moving_frame`): pixel p gets the projector coordinate of the rest-pose
        point of pixel p − flow moved by δ(t), a point near (not on) p's ray. The truth is the
        point on p's ray with that projector coordinate — what the frames encode; the tool is
        ray-traced at ``t_s`` over it. :meth:`traced_truth` is the exact ray-traced scene (it
        differs from the rendered one by the tile flow's error times the triangulation gain).
        """
        if self.scene.is_static:
            if self._truth_static is None:
                self._truth_static = self._truth_from(self.points)
            return self._truth_static
        h, w = self.shape
        delta = self.scene.offset(t_s)
        flow = np.repeat(np.repeat(self._block_flow(delta), BLOCK, axis=0), BLOCK, axis=1)[:h, :w]
        sv = np.clip(np.arange(h)[:, None] - flow[..., 1], 0, h - 1)
        su = np.clip(np.arange(w)[None, :] - flow[..., 0], 0, w - 1)
        moved = self.points[sv, su] + delta
        # The pixel shows that point's projector coordinate; the point on the pixel's own ray
        # with that coordinate is what the frames encode (the flow is integer per tile).
        alpha, a_c, gam, g_c = self.rig.projector.fringe_coefficients(self.schedule.orientation)
        dirs = self.rays.reshape(h, w, 3)
        with np.errstate(invalid="ignore", divide="ignore"):
            xp = (mat3(moved, alpha) - a_c) / (mat3(moved, gam) - g_c)
            t_ray = (a_c - xp * g_c) / (mat3(dirs, alpha) - xp * mat3(dirs, gam))
        points = t_ray[..., None] * dirs
        if self.scene.tool is not None:
            p0, p1 = (np.asarray(p, np.float64) for p in self.scene.tool.path(t_s))
            tt, _ = raycast_capsule(np.zeros(3), self.rays, p0, p1, self.scene.tool.radius_mm)
            tt = tt.reshape(h, w)
            with np.errstate(invalid="ignore"):
                t_surface = points[..., 2] / dirs[..., 2]
                # in front of the surface, or over nothing
                closer = np.isfinite(tt) & ~(t_surface <= tt)
            points[closer] = tt[closer, None] * dirs[closer]
        return self._truth_from(points)

    def traced_truth(self, t_s: float = 0.0) -> tuple[F32, F32]:
        """As :meth:`truth`, but the scene ray-traced exactly at ``t_s`` (not the rendered warp)."""
        if self.scene.is_static:
            return self.truth(t_s)
        hits = trace(self.scene, self.rays, t_s)
        return self._truth_from(hits.points.reshape(*self.shape, 3))

    def _truth_from(self, points: F64) -> tuple[F32, F32]:
        depth = self.rig.reference.height(points)
        return depth.astype(np.float32), points.astype(np.float32)
