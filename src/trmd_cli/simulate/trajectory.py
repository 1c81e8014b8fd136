"""Sharp image sequences from one still image: a smooth random camera path, plus optional
independently moving foreground layers (occlusion).

The camera path is a homography ``G(t)`` in output-pixel coordinates (translation, rotation and
scale about the image centre, and a small perspective term), composed with a fixed view ``A0``
that places the output window inside the source image. Every sample of the sequence is
``frame(t)(x) = src(A0 · G(t) · x)`` — bilinear interpolation in the *source*, so no border or
resampling artefact accumulates, and the view stays inside the source image (reflection is only
a fallback for extreme paths).

Time is measured in exposures (``u = t / T``). Each path parameter is a cubic Hermite curve with
knots every half exposure whose knot velocities vary smoothly (AR(1)) around a random mean
velocity, so the motion over one exposure is about the drawn magnitude and may bend.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError

__all__ = ["MotionRanges", "SmoothPath", "CameraPath", "Layer", "StillScene", "make_scene",
           "to_gray"]

#: knot spacing of the smooth paths, in exposures
_KNOT = 0.5
#: correlation of knot velocities from one knot to the next
_AR = 0.7


@dataclass(frozen=True)
class MotionRanges:
    """How much the camera (and foreground) may move during one exposure.

    Each magnitude is drawn uniformly in ``[0, max]`` per sample (direction/sign uniform);
    with ``log_magnitude`` the translations are drawn log-uniformly in ``[max/20, max]``
    instead, so small and large blur are equally represented per octave.

    Attributes:
        translation_px: max image translation over one exposure, output pixels.
        rotation_deg: max in-plane rotation over one exposure, degrees.
        scale: max relative zoom over one exposure (0.05 = 5 %).
        perspective: max perspective tilt over one exposure, as the relative scale difference
            between opposite image borders (0.05 = 5 %).
        curvature: how much the velocity may change within an exposure relative to its mean
            (0 = straight, uniform motion).
        foreground_prob: probability that a sample has foreground layers.
        max_layers: most foreground layers when it has any (drawn uniformly in 1..max).
        layer_translation_px: max translation of a foreground layer over one exposure.
        layer_size: (min, max) size of a layer as a fraction of the shorter image side.
        margin: extra source area around the view, as a fraction of the output size, so the
            path stays inside the source image.
        log_magnitude: draw translations log-uniformly (see above).
    """

    translation_px: float = 30.0
    rotation_deg: float = 2.0
    scale: float = 0.04
    perspective: float = 0.02
    curvature: float = 0.3
    foreground_prob: float = 0.0
    max_layers: int = 2
    layer_translation_px: float = 40.0
    layer_size: tuple[float, float] = (0.2, 0.5)
    margin: float = 0.25
    log_magnitude: bool = False

    def __post_init__(self) -> None:
        for name in ("translation_px", "rotation_deg", "scale", "perspective", "curvature",
                     "layer_translation_px", "margin"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"motion {name} must be ≥ 0, got {v}")
        if not 0 <= self.foreground_prob <= 1:
            raise InputError(f"foreground_prob must be in [0, 1], got {self.foreground_prob}")
        if self.max_layers < 0:
            raise InputError(f"max_layers must be ≥ 0, got {self.max_layers}")

    @classmethod
    def static(cls) -> MotionRanges:
        """No motion at all (camera and foreground still)."""
        return cls(translation_px=0.0, rotation_deg=0.0, scale=0.0, perspective=0.0,
                   curvature=0.0, foreground_prob=0.0)


class SmoothPath:
    """A smooth random curve ``q(u)`` (D parameters) over ``u ∈ [0, duration]`` exposures.

    Mean velocity ``mean_velocity`` (D,) per exposure; knot velocities are that plus AR(1)
    deviations of size ``curvature × deviation_scale`` (D,) (default: ``|mean_velocity|``);
    positions integrate the velocities so that ``q(centre) = 0``.
    """

    def __init__(self, mean_velocity: np.ndarray, duration: float, curvature: float,
                 rng: np.random.Generator, centre: float | None = None,
                 deviation_scale: np.ndarray | None = None):
        v = np.asarray(mean_velocity, np.float64)
        self.dim = v.shape[0]
        k = max(2, int(math.ceil(duration / _KNOT)) + 1)
        self.knots = np.arange(k) * _KNOT
        dev = np.empty((k, self.dim))
        dev[0] = rng.standard_normal(self.dim)
        for i in range(1, k):
            dev[i] = _AR * dev[i - 1] + math.sqrt(1 - _AR * _AR) * rng.standard_normal(self.dim)
        scale = np.abs(v) if deviation_scale is None else np.asarray(deviation_scale)
        self.vel = v[None, :] + curvature * scale[None, :] * dev
        pos = np.zeros((k, self.dim))
        pos[1:] = np.cumsum(0.5 * _KNOT * (self.vel[1:] + self.vel[:-1]), 0)
        self.pos = pos
        c = 0.5 * duration if centre is None else centre
        self.pos = pos - self(np.array([c]))[0]

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """Positions (len(u), D) by cubic Hermite interpolation."""
        u = np.asarray(u, np.float64)
        i = np.clip(np.floor(u / _KNOT).astype(np.int64), 0, len(self.knots) - 2)
        s = (u - self.knots[i]) / _KNOT
        s2, s3 = s * s, s * s * s
        h00 = 2 * s3 - 3 * s2 + 1
        h10 = s3 - 2 * s2 + s
        h01 = -2 * s3 + 3 * s2
        h11 = s3 - s2
        return (h00[:, None] * self.pos[i] + h10[:, None] * _KNOT * self.vel[i]
                + h01[:, None] * self.pos[i + 1] + h11[:, None] * _KNOT * self.vel[i + 1])


#: with log-uniform magnitudes, the smallest is the largest divided by this
_LOG_SPAN = 20.0


def _random_velocity(rng: np.random.Generator, magnitude_max: float, dim: int,
                     log: bool = False) -> np.ndarray:
    if log and magnitude_max > 0:
        mag = magnitude_max * math.exp(-rng.uniform(0.0, math.log(_LOG_SPAN)))
    else:
        mag = rng.uniform(0.0, magnitude_max)
    if dim == 1:
        return np.array([mag if rng.random() < 0.5 else -mag])
    d = rng.standard_normal(dim)
    return mag * d / max(float(np.linalg.norm(d)), 1e-12)


class CameraPath:
    """Camera homography ``G(u)`` (3×3, output pixels → output pixels) about the centre.

    Parameters per time: translation (2, px), rotation (rad), log-scale, perspective (2).
    """

    def __init__(self, width: int, height: int, motion: MotionRanges, duration: float,
                 rng: np.random.Generator, centre: float | None = None):
        self.cx, self.cy = (width - 1) / 2, (height - 1) / 2
        self.half = 0.5 * max(width, height)
        groups = [
            _random_velocity(rng, motion.translation_px, 2, motion.log_magnitude),
            _random_velocity(rng, math.radians(motion.rotation_deg), 1),
            _random_velocity(rng, math.log1p(motion.scale), 1),
            # perspective coefficient p so that p · half = relative tilt
            _random_velocity(rng, motion.perspective / self.half, 2),
        ]
        vel = np.concatenate(groups)
        # a 2-D motion bends by an amount relative to its speed, in both components
        dev = np.concatenate([np.full(len(g), np.linalg.norm(g)) for g in groups])
        self.path = SmoothPath(vel, duration, motion.curvature, rng, centre, dev)

    def homographies(self, u: np.ndarray) -> np.ndarray:
        """(len(u), 3, 3) matrices mapping output pixels at time u to output pixels at the
        path's centre time (i.e. where in the reference view each pixel looks)."""
        q = self.path(u)
        tx, ty, th, ls, px, py = q.T
        s = np.exp(ls)
        cos, sin = np.cos(th) * s, np.sin(th) * s
        n = len(q)
        g = np.zeros((n, 3, 3))
        g[:, 0, 0], g[:, 0, 1] = cos, -sin
        g[:, 1, 0], g[:, 1, 1] = sin, cos
        g[:, 2, 0], g[:, 2, 1], g[:, 2, 2] = px, py, 1.0
        # translation last, so the centre moves by (tx, ty)
        g[:, 0, 2] = tx
        g[:, 1, 2] = ty
        c = np.array([[1, 0, self.cx], [0, 1, self.cy], [0, 0, 1.0]])
        ci = np.array([[1, 0, -self.cx], [0, 1, -self.cy], [0, 0, 1.0]])
        return c[None] @ g @ ci[None]


@dataclass(frozen=True, eq=False)
class Layer:
    """A foreground patch: texture (h, w) float32, soft mask (h, w) float32 [0, 1], and its own
    path of translation (2, px) and rotation (rad) in output coordinates around ``origin``."""

    texture: np.ndarray
    mask: np.ndarray
    origin: tuple[float, float]
    path: SmoothPath

    def affines(self, u: np.ndarray) -> np.ndarray:
        """(len(u), 2, 3) affine maps patch pixels → output pixels."""
        q = self.path(u)
        h, w = self.mask.shape
        cx, cy = (w - 1) / 2, (h - 1) / 2
        cos, sin = np.cos(q[:, 2]), np.sin(q[:, 2])
        a = np.zeros((len(q), 2, 3))
        a[:, 0, 0], a[:, 0, 1] = cos, -sin
        a[:, 1, 0], a[:, 1, 1] = sin, cos
        a[:, 0, 2] = self.origin[0] + q[:, 0] - cos * cx + sin * cy
        a[:, 1, 2] = self.origin[1] + q[:, 1] - sin * cx - cos * cy
        return a


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3) [0, 1] → (H, W) float32 (Rec. 601 luma of an RGB image)."""
    img = np.asarray(image)
    if img.dtype == np.uint8:
        img = img.astype(np.float32) / 255.0
    elif img.dtype == np.uint16:
        img = img.astype(np.float32) / 65535.0
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = img[..., 0] * 0.299 + img[..., 1] * 0.587 + img[..., 2] * 0.114
    if img.ndim != 2:
        raise InputError(f"image has shape {np.shape(image)}, expected (H, W) or (H, W, 3)")
    return np.ascontiguousarray(np.clip(img, 0.0, 1.0), dtype=np.float32)


class StillScene:
    """Renders frames of a still image seen along a camera path (+ layers) at given times.

    Args:
        source: (Hs, Ws) float32 linear intensity.
        view: (3, 3) map from output pixels (reference view) to source pixels.
        size: output (W, H).
        camera: the camera path; layers: foreground layers.
        exposure_us: length of one exposure in µs (the path's time unit).
        t0_us: time of u = 0.
    """

    def __init__(self, source: np.ndarray, view: np.ndarray, size: tuple[int, int],
                 camera: CameraPath, layers: list[Layer], exposure_us: float, t0_us: float = 0.0):
        self.source = source
        self.view = view
        self.size = size
        self.camera = camera
        self.layers = layers
        self.exposure_us = float(exposure_us)
        self.t0_us = float(t0_us)

    def _u(self, times_us: np.ndarray) -> np.ndarray:
        return (np.asarray(times_us, np.float64) - self.t0_us) / self.exposure_us

    def render(self, times_us: np.ndarray) -> np.ndarray:
        """Frames (S, H, W) float32 at ``times_us`` (S,)."""
        import cv2

        u = self._u(times_us)
        w, h = self.size
        mats = self.view[None] @ self.camera.homographies(u)
        out = np.empty((len(u), h, w), np.float32)
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        for i, m in enumerate(mats):
            out[i] = cv2.warpPerspective(self.source, m, (w, h), flags=flags,
                                         borderMode=cv2.BORDER_REFLECT101)
        for layer in self.layers:
            aff = layer.affines(u)
            for i, a in enumerate(aff):
                tex = cv2.warpAffine(layer.texture, a, (w, h), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_CONSTANT)
                alpha = cv2.warpAffine(layer.mask, a, (w, h), flags=cv2.INTER_LINEAR,
                                       borderMode=cv2.BORDER_CONSTANT)
                out[i] += alpha * (tex - out[i])
        return out

    def exposure_motion(self, start_us: float, end_us: float, fractions) -> np.ndarray:
        """The camera's true motion over the exposure ``[start_us, end_us]`` (µs): (J, 3, 3)
        homographies mapping a pixel of its middle frame (the frame :meth:`render` draws at
        mid-exposure) to where that point of the scene is at each of ``fractions`` (J,) of the
        exposure, output pixels, normalised to ``H[2, 2] = 1``.

        :meth:`render` samples ``src(A0 · G(u) · x)``: a scene point seen at ``y`` in the
        middle frame is at ``x = G(u)⁻¹ · G(u_mid) · y`` at time u (the view ``A0`` cancels).
        Foreground layers move on their own and are not part of it."""
        f = np.asarray(fractions, np.float64)
        times = start_us + f * (end_us - start_us)
        g = self.camera.homographies(self._u(np.append(times, 0.5 * (start_us + end_us))))
        h = np.linalg.solve(g[:-1], np.broadcast_to(g[-1], g[:-1].shape))
        return h / h[:, 2:3, 2:3]

    def max_speed_px(self, u_start: float, u_end: float, samples_per_exposure: int = 32) -> float:
        """Largest image-space speed (output px per exposure) of the camera's corners and centre
        and of every layer's corners, over ``[u_start, u_end]`` exposures."""
        n = max(2, int(math.ceil((u_end - u_start) * samples_per_exposure)) + 1)
        u = np.linspace(u_start, u_end, n)
        du = (u_end - u_start) / (n - 1)
        if du <= 0:
            return 0.0
        w, h = self.size
        pts = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1],
                        [(w - 1) / 2, (h - 1) / 2, 1]], np.float64).T
        # where each output pixel looks in the reference view; its motion is the image motion
        g = self.camera.homographies(u) @ pts[None]
        xy = g[:, :2] / g[:, 2:3]
        speed = float(np.linalg.norm(np.diff(xy, axis=0), axis=1).max()) / du
        for layer in self.layers:
            lh, lw = layer.mask.shape
            lp = np.array([[0, 0, 1], [lw - 1, 0, 1], [0, lh - 1, 1], [lw - 1, lh - 1, 1]],
                          np.float64).T
            xy = layer.affines(u) @ lp[None]
            speed = max(speed, float(np.linalg.norm(np.diff(xy, axis=0), axis=1).max()) / du)
        return speed


def _fit_view(src_w: int, src_h: int, out_w: int, out_h: int, margin: float,
              rng: np.random.Generator | None, zoom: tuple[float, float] | None
              ) -> tuple[float, float, float]:
    """Where the output window goes in the source: (k, ox, oy) with ``k`` source pixels per
    output pixel and (ox, oy) the source position of the window's top-left corner. The window
    plus ``margin`` on every side fits inside the source; it is placed at random (centred when
    ``rng`` is None). ``zoom`` is the range of ``k`` to draw from (capped by what fits; None =
    as large as fits, i.e. the whole image)."""
    need_w, need_h = out_w * (1 + 2 * margin), out_h * (1 + 2 * margin)
    fit = min(src_w / need_w, src_h / need_h)
    if zoom is None:
        k = fit
    else:
        z = zoom[0] if rng is None else rng.uniform(*zoom)
        k = min(fit, z)
    span_w, span_h = need_w * k, need_h * k
    if rng is None:
        x0, y0 = (src_w - span_w) / 2, (src_h - span_h) / 2
    else:
        x0 = rng.uniform(0, max(src_w - span_w, 0.0))
        y0 = rng.uniform(0, max(src_h - span_h, 0.0))
    return k, x0 + out_w * margin * k, y0 + out_h * margin * k


def _view_matrix(k: float, ox: float, oy: float) -> np.ndarray:
    """Output pixel centres → source pixel centres: output pixel i covers source
    ``[ox + i·k, ox + (i+1)·k)``."""
    return np.array([[k, 0, ox + 0.5 * k - 0.5], [0, k, oy + 0.5 * k - 0.5], [0, 0, 1.0]])


def _make_layer(source: np.ndarray, size: tuple[int, int], motion: MotionRanges, duration: float,
                rng: np.random.Generator, centre: float | None) -> Layer:
    import cv2

    w, h = size
    short = min(w, h)
    lw = int(max(8, round(short * rng.uniform(*motion.layer_size))))
    lh = int(max(8, round(lw * rng.uniform(0.6, 1.6))))
    sh, sw = source.shape
    # texture: another part of the image, resized to the patch, flipped so it rarely matches
    tw, th = min(sw, lw * 2), min(sh, lh * 2)
    x0, y0 = int(rng.integers(0, sw - tw + 1)), int(rng.integers(0, sh - th + 1))
    tex = cv2.resize(source[y0:y0 + th, x0:x0 + tw], (lw, lh), interpolation=cv2.INTER_AREA)
    if rng.random() < 0.5:
        tex = tex[::-1]
    tex = np.clip(tex * rng.uniform(0.6, 1.4) + rng.uniform(-0.15, 0.15), 0, 1)
    yy, xx = np.mgrid[0:lh, 0:lw].astype(np.float32)
    nx, ny = (xx - (lw - 1) / 2) / (lw / 2), (yy - (lh - 1) / 2) / (lh / 2)
    if rng.random() < 0.5:  # ellipse
        r = np.sqrt(nx * nx + ny * ny)
    else:  # rounded rectangle
        r = np.maximum(np.abs(nx), np.abs(ny))
    soft = 2.0 / min(lw, lh)  # about one pixel of anti-aliasing
    mask = np.clip((1 - r) / soft, 0, 1).astype(np.float32)
    origin = (float(rng.uniform(0.15, 0.85) * w), float(rng.uniform(0.15, 0.85) * h))
    groups = [_random_velocity(rng, motion.layer_translation_px, 2, motion.log_magnitude),
              _random_velocity(rng, math.radians(10.0), 1)]
    dev = np.concatenate([np.full(len(g), np.linalg.norm(g)) for g in groups])
    path = SmoothPath(np.concatenate(groups), duration, motion.curvature, rng, centre, dev)
    return Layer(np.ascontiguousarray(tex, np.float32), mask, origin, path)


def make_scene(image: np.ndarray, size: tuple[int, int], motion: MotionRanges,
               exposure_us: float, duration: float, rng: np.random.Generator, *,
               random_view: bool = True, zoom: tuple[float, float] | None = (1.0, 1.0),
               centre: float | None = None, t0_us: float = 0.0) -> StillScene:
    """A random :class:`StillScene` of ``image`` for ``duration`` exposures.

    Args:
        image: (H, W) or (H, W, 3), float [0, 1] or uint8/uint16.
        size: output (W, H).
        zoom: range of source pixels per output pixel (capped by what fits; None = the whole
            image, margin included, fills the view).
        random_view: random placement of the view in the source (else centred).
        centre: time (in exposures) at which the camera is at the reference view (default:
            the middle of ``duration``).
    """
    w, h = size
    if w < 2 or h < 2:
        raise InputError(f"output size {w}x{h} is too small")
    import cv2

    src = to_gray(image)
    k, ox, oy = _fit_view(src.shape[1], src.shape[0], w, h, motion.margin,
                          rng if random_view else None, zoom)
    if k > 1.25:
        # shrink with area averaging first: bilinear warps of a much larger source alias
        orig_w = src.shape[1]
        src = cv2.resize(src, (max(1, round(src.shape[1] / k)), max(1, round(src.shape[0] / k))),
                         interpolation=cv2.INTER_AREA)
        fx = src.shape[1] / orig_w
        k, ox, oy = k * fx, ox * fx, oy * fx
    view = _view_matrix(k, ox, oy)
    camera = CameraPath(w, h, motion, duration, rng, centre)
    layers: list[Layer] = []
    if motion.max_layers > 0 and motion.foreground_prob > 0 and \
            rng.random() < motion.foreground_prob:
        for _ in range(int(rng.integers(1, motion.max_layers + 1))):
            layers.append(_make_layer(src, size, motion, duration, rng, centre))
    return StillScene(src, view, size, camera, layers, exposure_us, t0_us)
