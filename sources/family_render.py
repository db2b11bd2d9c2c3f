"""Surfaces of a family scene (``sources.scene_family``): room faces, plain (texture-poor) walls, object boxes,
and chairs as chairs (``chair_parts``).

Rendered by ``sources.raycast`` like the room's; every texture is a pure function of (seed, face or object id).
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from sources.base import ObjectTruth
from sources.raycast import TEXELS_PER_M, Surface, box_surfaces, object_texture, room_surfaces, surface_texture
from sources.scene_family import FamilyLayout

EXTRA_COLOURS: dict[str, tuple[int, int, int]] = {
    "bed": (170, 140, 120),
    "clock": (230, 230, 210),
    "suitcase": (90, 60, 40),
    "teddy bear": (160, 110, 60),
    "wine glass": (190, 200, 210),
    "keyboard": (35, 35, 40),
    "mouse": (90, 90, 95),
    "bowl": (210, 200, 170),
    "vase": (80, 110, 180),
    "apple": (190, 40, 40),
    "orange": (240, 150, 30),
}


SEAT_SHARE = 0.5
"""A chair's seat top lies at this share of its height (0.40-0.48 m for chairs 0.8-0.95 m tall)."""

SEAT_M, BACK_M, LEG_M = 0.05, 0.05, 0.04
"""A chair's seat and backrest thickness and its legs' side."""


def chair_parts(chair: ObjectTruth) -> list[ObjectTruth]:
    """A chair's seat, four legs and backrest as boxes of its instance, inside its box (its truth). The chair
    faces its local +y (``scene_family``: chairs face the table or the room), so the backrest stands at -y.
    A box-shaped chair seen over a table shows its near face; a real one shows its backrest, the far side
    (the 7-Scenes chairs: 0.2 m too far from the camera along the ray)."""
    w, d, h = chair.size
    c, s = np.cos(chair.yaw), np.sin(chair.yaw)
    bottom = chair.center[2] - h / 2.0
    seat = SEAT_SHARE * h

    def part(x: float, y: float, z0: float, size: tuple[float, float, float]) -> ObjectTruth:
        wx, wy = chair.center[0] + c * x - s * y, chair.center[1] + s * x + c * y
        return replace(chair, center=(float(wx), float(wy), float(bottom + z0 + size[2] / 2.0)), size=size)

    legs = [
        part(sx * (w - LEG_M) / 2.0, sy * (d - LEG_M) / 2.0, 0.0, (LEG_M, LEG_M, seat - SEAT_M))
        for sx in (-1.0, 1.0)
        for sy in (-1.0, 1.0)
    ]
    return [
        part(0.0, 0.0, seat - SEAT_M, (w, d, SEAT_M)),
        *legs,
        part(0.0, -(d - BACK_M) / 2.0, seat, (w, BACK_M, h - seat)),
    ]


def plain_texture(rng: np.random.Generator, width_m: float, height_m: float) -> np.ndarray:
    """A texture-poor painted wall (h, w, 3) uint8: one colour with faint metre-scale variation."""
    w, h = int(np.ceil(width_m * TEXELS_PER_M)) + 1, int(np.ceil(height_m * TEXELS_PER_M)) + 1
    base = rng.uniform(150.0, 215.0) + rng.normal(0.0, 8.0, 3)
    low = cv2.resize(rng.normal(0.0, 3.0, (h // 100 + 2, w // 100 + 2, 3)), (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(base + low, 0, 255).astype(np.uint8)


def family_surfaces(layout: FamilyLayout, colours: dict[str, tuple[int, int, int]]) -> list[Surface]:
    """Lit room faces (walls plain when ``plain_walls``) and the faces of every object (``colours`` by label)."""
    light, seed = np.asarray(layout.light), layout.seed

    def texture(k: int, width_m: float, height_m: float) -> np.ndarray:
        """Faces 0-3 are walls, 4-5 floor and ceiling."""
        rng = np.random.default_rng([seed, 1031, k])
        return (plain_texture if layout.plain_walls and k < 4 else surface_texture)(rng, width_m, height_m)

    out = room_surfaces(layout.room, light, texture)
    palette = {**colours, **EXTRA_COLOURS}
    for obj in layout.objects:
        rng = np.random.default_rng([seed, 1037, obj.id])
        colour = np.array(palette.get(obj.label, (128, 128, 128)), float) * rng.uniform(0.75, 1.25, 3)
        skin = object_texture(rng, max(obj.size), colour + rng.normal(0.0, 20.0, 3))
        for part in chair_parts(obj) if obj.label == "chair" else [obj]:
            out.extend(box_surfaces(part, skin, light, rng))
    return out
