"""Surfaces of a family scene (``sources.scene_family``): room faces, plain (texture-poor) walls, object boxes.

Rendered by ``sources.raycast`` like the room's; every texture is a pure function of (seed, face or object id).
"""

from __future__ import annotations

import cv2
import numpy as np

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
        out.extend(box_surfaces(obj, object_texture(rng, max(obj.size), colour + rng.normal(0.0, 20.0, 3)), light, rng))
    return out
