"""Exact per-pixel ray casting of textured planar rectangles (room faces, box faces) with a z-buffer.

A pixel's ray is ``o + t R (a, b, 1)`` with ``a = (x - cx) / fx`` and ``b = (y - cy) / fy``, so ``t`` is
the camera-frame depth z. For a plane, 1/z and the rectangle coordinates times 1/z are affine in
(a, b): hits are tested exactly at pixel centres, and colour is a perspective warp of the surface's
texture (1 cm per texel, Lambertian lighting from a point light baked in). Boxes are back-face culled.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from perception.camera import Intrinsics, pixel_rays, points_to_pixels, ray_matrix
from sources.base import ObjectTruth

TEXELS_PER_M = 100.0
TextureFn = Callable[[int, float, float], np.ndarray]  # (surface index, width m, height m) -> texture
_NEAR = 0.01
_EPS = 1e-4  # metres of slack on rectangle edges so that adjacent faces leave no gaps


def surface_texture(rng: np.random.Generator, width_m: float, height_m: float) -> np.ndarray:
    """A rich non-periodic texture (h, w, 3) uint8: greyish shapes of many scales on a tinted mid-tone."""
    w, h = int(np.ceil(width_m * TEXELS_PER_M)) + 1, int(np.ceil(height_m * TEXELS_PER_M)) + 1
    base = rng.uniform(100.0, 150.0) + rng.normal(0.0, 12.0, 3)
    low = cv2.resize(rng.normal(0.0, 20.0, (h // 50 + 2, w // 50 + 2, 3)), (w, h), interpolation=cv2.INTER_CUBIC)
    img = np.clip(base + low, 0, 255).astype(np.uint8)
    count = int(90 * width_m * height_m)
    tint = rng.normal(0.0, 1.0, (count, 3)) * np.where(rng.random(count) < 0.25, 40.0, 12.0)[:, None]
    _draw_shapes(img, rng, (2.0, 40.0), rng.uniform(10.0, 245.0, (count, 1)) + tint)
    return cv2.GaussianBlur(img, (0, 0), 0.6)


def object_texture(rng: np.random.Generator, extent_m: float, colour: np.ndarray) -> np.ndarray:
    """A square texture for one object (twice its extent): its colour with lighter/darker patches."""
    n = int(np.ceil(2.0 * extent_m * TEXELS_PER_M)) + 2
    img = np.empty((n, n, 3), np.uint8)
    img[:] = np.clip(colour, 0, 255).astype(np.uint8)
    count = max(8, int(300 * (2.0 * extent_m) ** 2))
    _draw_shapes(img, rng, (1.5, max(3.0, 15.0 * extent_m)), colour * rng.uniform(0.35, 1.5, (count, 1)))
    return cv2.GaussianBlur(img, (0, 0), 0.5)


def _draw_shapes(img: np.ndarray, rng: np.random.Generator, size_px: tuple[float, float], colours: np.ndarray) -> None:
    """Draw one random rectangle, disc or line per row of ``colours`` (log-uniform sizes) onto ``img``."""
    h, w = img.shape[:2]
    count = len(colours)
    kinds = rng.integers(0, 4, count).tolist()
    half = (np.exp(rng.uniform(np.log(size_px[0]), np.log(size_px[1]), (count, 2))) / 2.0).tolist()
    centres = (rng.uniform(0, 1, (count, 2)) * (w, h)).tolist()
    thick = rng.integers(1, 4, count).tolist()
    cols = np.clip(colours, 0, 255).tolist()
    for kind, (hw, hh), (cx, cy), t, c in zip(kinds, half, centres, thick, cols, strict=True):
        p0 = (int(cx - hw), int(cy - hh))
        if kind <= 1:
            cv2.rectangle(img, p0, (int(cx + hw), int(cy + hh)), c, -1)
        elif kind == 2:
            cv2.circle(img, (int(cx), int(cy)), max(1, int(hw)), c, -1)
        else:
            cv2.line(img, p0, (int(cx + hw), int(cy - hh)), c, t)


@dataclass(frozen=True)
class Surface:
    """A textured rectangle ``origin + s * eu + r * ev`` (0 <= s <= lu, 0 <= r <= lv) facing ``eu x ev``."""

    origin: np.ndarray
    eu: np.ndarray
    ev: np.ndarray
    lu: float
    lv: float
    instance: int
    texture: np.ndarray
    normal: np.ndarray = field(init=False)
    corners: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        """Precompute the normal and the four corners."""
        object.__setattr__(self, "normal", np.cross(self.eu, self.ev))
        steps = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]) * (self.lu, self.lv)
        object.__setattr__(self, "corners", self.origin + steps @ np.stack([self.eu, self.ev]))


def lit(surface: Surface, texture: np.ndarray, light: np.ndarray) -> Surface:
    """The surface with Lambertian point-light shading baked into (a crop of) ``texture``."""
    h, w = int(np.ceil(surface.lv * TEXELS_PER_M)) + 1, int(np.ceil(surface.lu * TEXELS_PER_M)) + 1
    r = ((np.arange(h) + 0.5) / TEXELS_PER_M)[:, None, None]
    s = ((np.arange(w) + 0.5) / TEXELS_PER_M)[None, :, None]
    to_light = (light - surface.origin - s * surface.eu - r * surface.ev).astype(np.float32)
    dist = np.sqrt(np.einsum("hwk,hwk->hw", to_light, to_light))
    cos = np.maximum(to_light @ surface.normal.astype(np.float32) / dist, 0.0)
    shade = 0.6 + 0.55 * cos * (6.0 / (6.0 + dist * dist))
    tex = np.minimum(texture[:h, :w] * shade[..., None], 255.0).astype(np.uint8)
    return Surface(surface.origin, surface.eu, surface.ev, surface.lu, surface.lv, surface.instance, tex)


def room_surfaces(size: tuple[float, float, float], light: np.ndarray, make_texture: TextureFn) -> list[Surface]:
    """The six inward-facing faces of the room box [0, size], ordered 2 * axis + (high side)."""
    out = []
    for axis in range(3):
        i, j = [k for k in range(3) if k != axis]
        for high in (0, 1):
            origin = np.zeros(3)
            origin[axis] = size[axis] * high
            eu, ev = np.eye(3)[i], np.eye(3)[j]
            if (np.cross(eu, ev)[axis] > 0) == bool(high):  # make the normal point into the room
                eu, ev, i, j = ev, eu, j, i
            texture = make_texture(2 * axis + high, size[i], size[j])
            out.append(lit(Surface(origin, eu, ev, size[i], size[j], 0, texture), texture, light))
    return out


def box_surfaces(obj: ObjectTruth, texture: np.ndarray, light: np.ndarray, rng: np.random.Generator) -> list[Surface]:
    """The six outward-facing faces of a yawed box, each lit with a random crop of the object texture."""
    c, s = np.cos(obj.yaw), np.sin(obj.yaw)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    half = np.asarray(obj.size) / 2.0
    out = []
    for axis in range(3):
        i, j = [k for k in range(3) if k != axis]
        for sign in (-1.0, 1.0):
            eu, ev = Rz[:, i], Rz[:, j]
            if np.cross(eu, ev) @ Rz[:, axis] * sign < 0:
                eu, ev, i, j = ev, eu, j, i
            origin = np.asarray(obj.center) + sign * half[axis] * Rz[:, axis] - half[i] * eu - half[j] * ev
            off = rng.integers(0, texture.shape[0] // 2, 2)
            plain = Surface(origin, eu, ev, 2 * half[i], 2 * half[j], obj.id, texture)
            out.append(lit(plain, texture[off[0] :, off[1] :], light))
    return out


@dataclass
class Render:
    """One view: true depth (m, 0 where nothing), instance ids, colour, and per-instance pixel rects."""

    depth: np.ndarray
    ids: np.ndarray
    rgb: np.ndarray
    rects: dict[int, tuple[int, int, int, int]]


class Renderer:
    """Z-buffered ray caster of textured rectangles for one pinhole camera."""

    def __init__(self, surfaces: list[Surface], K: Intrinsics, width: int, height: int) -> None:
        """Renderer of ``surfaces`` for intrinsics ``K`` and image size."""
        self.surfaces, self.K, self.width, self.height = surfaces, K, width, height
        a, b = pixel_rays(np.arange(width), np.arange(height), K)
        self.a, self.b = a.astype(np.float32), b.astype(np.float32)
        self.instance = np.array([s.instance for s in surfaces] + [0], dtype=np.uint16)

    def render(self, pose: np.ndarray) -> Render:
        """Ray-cast all surfaces from a camera-to-world ``pose``."""
        R, o = pose[:3, :3], pose[:3, 3]
        inv = np.zeros((self.height, self.width), np.float32)
        sid = np.full((self.height, self.width), -1, np.int16)
        drawn: dict[int, tuple[tuple[int, int, int, int], np.ndarray]] = {}
        for k, surf in enumerate(self.surfaces):
            coeffs = _plane_coeffs(surf, R, o)
            if coeffs is None:
                continue
            rect = self._rect(surf, R, o)
            if rect is not None and self._scan(surf, k, coeffs, rect, inv, sid):
                drawn[k] = (rect, coeffs)
        rgb = np.zeros((self.height, self.width, 3), np.uint8)
        rects: dict[int, tuple[int, int, int, int]] = {}
        for k, (rect, coeffs) in drawn.items():
            if self._paint(self.surfaces[k], k, coeffs, rect, sid, rgb):
                inst = self.surfaces[k].instance
                rects[inst] = _union(rects[inst], rect) if inst in rects else rect
        depth = np.zeros_like(inv)
        np.divide(np.float32(1.0), inv, out=depth, where=inv > 0)
        return Render(depth, self.instance[sid], rgb, rects)

    def _rect(self, surf: Surface, R: np.ndarray, o: np.ndarray) -> tuple[int, int, int, int] | None:
        """Pixel rectangle (y0, y1, x0, x1) bounding the near-clipped projection, or None when off-screen."""
        cam = (surf.corners - o) @ R
        if cam[:, 2].min() >= _NEAR:
            return self._bounds(cam)
        pts = []
        for p, q in zip(cam, cam[[1, 2, 3, 0]], strict=True):
            if p[2] >= _NEAR:
                pts.append(p)
            if (p[2] >= _NEAR) != (q[2] >= _NEAR):
                pts.append(p + (_NEAR - p[2]) / (q[2] - p[2]) * (q - p))
        return self._bounds(np.array(pts)) if pts else None

    def _bounds(self, cam: np.ndarray) -> tuple[int, int, int, int] | None:
        """Pixel rectangle (y0, y1, x0, x1) bounding camera-frame points in front of the camera."""
        uv = np.stack(points_to_pixels(cam, self.K), axis=1)
        lo = np.clip(np.floor(uv.min(0)).astype(np.int64) - 1, 0, (self.width, self.height))
        hi = np.clip(np.ceil(uv.max(0)).astype(np.int64) + 2, 0, (self.width, self.height))
        return (int(lo[1]), int(hi[1]), int(lo[0]), int(hi[0])) if hi[0] > lo[0] and hi[1] > lo[1] else None

    def _affine(self, c: np.ndarray, rect: tuple[int, int, int, int]) -> np.ndarray:
        """``c . (a, b, 1)`` over the pixels of ``rect`` as float32."""
        y0, y1, x0, x1 = rect
        row = np.float32(c[0]) * self.a[x0:x1]
        col = np.float32(c[1]) * self.b[y0:y1] + np.float32(c[2])
        return row[None, :] + col[:, None]

    def _scan(self, surf: Surface, k: int, coeffs: np.ndarray, rect: tuple, inv: np.ndarray, sid: np.ndarray) -> bool:
        """Z-test the surface's exact pixel-centre hits inside ``rect``; True when any pixel wins."""
        iv = self._affine(coeffs[0], rect)
        zin = inv[rect[0] : rect[1], rect[2] : rect[3]]
        hit = iv > zin
        for c, length in ((coeffs[1], surf.lu), (coeffs[2], surf.lv)):
            uh = self._affine(c, rect)
            hit &= (uh >= np.float32(-_EPS) * iv) & (uh <= np.float32(length + _EPS) * iv)
        if not hit.any():
            return False
        zin[hit] = iv[hit]
        sid[rect[0] : rect[1], rect[2] : rect[3]][hit] = k
        return True

    def _paint(self, surf: Surface, k: int, coeffs: np.ndarray, rect: tuple, sid: np.ndarray, rgb: np.ndarray) -> bool:
        """Warp the surface texture into the pixels of ``rect`` it owns; True when it owns any."""
        y0, y1, x0, x1 = rect
        mask = sid[y0:y1, x0:x1] == k
        if not mask.any():
            return False
        to_ab = ray_matrix(self.K, x0, y0)
        texel = np.array([[TEXELS_PER_M, 0.0, -0.5], [0.0, TEXELS_PER_M, -0.5], [0.0, 0.0, 1.0]])
        M = texel @ coeffs[[1, 2, 0]] @ to_ab
        flags, border = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, cv2.BORDER_REPLICATE
        warped = cv2.warpPerspective(surf.texture, M, (x1 - x0, y1 - y0), flags=flags, borderMode=border)
        cv2.copyTo(warped, mask.view(np.uint8), rgb[y0:y1, x0:x1])
        return True


def _plane_coeffs(surf: Surface, R: np.ndarray, o: np.ndarray) -> np.ndarray | None:
    """Rows (1/z, s/z, r/z) as linear forms in (a, b, 1), or None when the surface faces away."""
    n = surf.normal
    dist = n @ (surf.origin - o)
    if dist >= 0:
        return None
    k = (R.T @ n) / dist
    q = o - surf.origin
    return np.stack([k, (surf.eu @ q) * k + R.T @ surf.eu, (surf.ev @ q) * k + R.T @ surf.ev])


def _union(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
    """Smallest rect (y0, y1, x0, x1) containing both."""
    return min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3])
