"""The complete numpy description of a scenario's terrain (no ``bpy``): heightfield, rock
prototypes and placements. Used for the below-ground check before rendering and by
:func:`simulation.terrain.scene.build_world` to build exactly this terrain in Blender."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from simulation.terrain.heightfield import Heightfield
from simulation.terrain.rocks import N_PROTOTYPES, Rocks, make_rocks, rock_prototype, surface_height_at


@dataclass(frozen=True, eq=False)
class TerrainModel:
    heightfield: Heightfield
    prototypes: list
    rocks: Rocks

    def ground_height(self, x, y) -> np.ndarray:
        """Height of the triangulated terrain surface (without rocks) at (x, y)."""
        return self.heightfield.height_at(x, y)

    def surface_height(self, x, y) -> np.ndarray:
        """Conservative height of terrain or rock tops at (x, y)."""
        return surface_height_at(self.heightfield, self.rocks, x, y)


@functools.lru_cache(maxsize=2)
def make_terrain_model(terrain_cfg, seed: int) -> TerrainModel:
    """Deterministic terrain for ``terrain_cfg`` (:class:`simulation.scenario.TerrainConfig`);
    the last two models are cached (they are immutable in use)."""
    hf = Heightfield(terrain_cfg, seed)
    protos = [rock_prototype(seed * 131 + k, 2) for k in range(N_PROTOTYPES)]
    protos += [rock_prototype(seed * 131 + k, 1) for k in range(N_PROTOTYPES)]
    return TerrainModel(hf, protos, make_rocks(terrain_cfg, hf, seed, protos))
