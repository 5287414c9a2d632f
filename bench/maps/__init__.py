"""The onboard map product of a landing: made on the truth side, handed to the flight software as plain data.

Inputs: the terrain configuration and seed (the region is regenerated from
them, :func:`models.terrain.generate_surface`), an
:class:`models.orbital_map.OrbitalMapConfig`, and the run's seed: the
georeferencing error and the products' noise come from the run's own "map"
stream (:mod:`bench.scenario.seeding`), so no other stream changes.

A product takes seconds and some 300 MB to make (the region's surface is
regenerated at texel resolution), so it is kept in the disk cache of
:mod:`bench.sim.terrain_cache` (``$LANDBENCH_CACHE_DIR/map``, about 1 MB an
entry), content-addressed by everything that shapes it: a campaign flown again
on the same seeds (a regression's candidate, a controller study's second law)
reads its maps instead of making them.

Outputs: (:class:`gnc.map_nav.OnboardMap` for the flight software,
:class:`MapTruth` for the bench: the drawn shift and where the map's target
truly lies).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import bench.scenario.seeding as seeding_module
import models.orbital_map as orbital_map_module
import models.terrain as terrain_module
from bench.scenario.seeding import component_rng
from bench.sim.terrain_cache import cached_arrays, content_address, source_digest
from gnc.map_nav import OnboardMap
from models.orbital_map import OrbitalMapConfig, OrbitalProduct, render_orbital_map
from models.terrain import Surface, TerrainConfig, generate_surface

MAP_CACHE_FORMAT = 1


@dataclass(frozen=True)
class MapTruth:
    """What the bench knows of the map and the flight software does not.

    Attributes:
        shift_xy_m: Georeferencing error delta: a feature's map position minus its true position in L [m].
        target_xy_L_m: Where the map's target truly is, in L [m] (target_xy_m - delta).
    """

    shift_xy_m: tuple[float, float]
    target_xy_L_m: tuple[float, float]


def draw_map_shift(cfg: OrbitalMapConfig, seed: int) -> tuple[tuple[float, float], np.random.Generator]:
    """The georeferencing error of the run with this seed, and the map's noise stream.

    The run's "map" stream spawns two children: the first draws the shift
    (``N(0, georef_sigma_m^2)`` per axis, x then y), the second the image and DEM noise.
    """
    rng_shift, rng_noise = component_rng(seed, "map").spawn(2)
    dx, dy = rng_shift.normal(0.0, 1.0, size=2) * cfg.georef_sigma_m
    return (float(dx), float(dy)), rng_noise


def onboard_map_from_product(product: OrbitalProduct, cfg: OrbitalMapConfig,
                             target_xy_m: tuple[float, float] = (0.0, 0.0)) -> OnboardMap:
    """The flight software's view of a product: arrays and stated georeferencing only."""
    half = product.size_m / 2.0
    return OnboardMap(image=product.image, image_res_m=product.image_res_m, image_origin_xy_m=(-half, -half),
                      dem_m=product.dem_m, dem_spacing_m=product.dem_spacing_m, dem_origin_xy_m=(-half, -half),
                      target_xy_m=(float(target_xy_m[0]), float(target_xy_m[1])),
                      georef_sigma_m=float(cfg.georef_sigma_m), dem_sigma_m=float(cfg.dem_noise_m))


def _free_idle_render_contexts() -> None:
    """Free an idle render context (a reused worker's last case's, about 120 MB) before a surface is
    generated (see :func:`bench.sim.world_builder.build_terrain`), if this process has rendered at all."""
    import sys

    if "models.render_context" in sys.modules:
        sys.modules["models.render_context"].free_shared_contexts()


def build_onboard_map(terrain_cfg: TerrainConfig, terrain_seed: int, map_cfg: OrbitalMapConfig, seed: int,
                      surface: Surface | None = None) -> tuple[OnboardMap, MapTruth]:
    """Make the run's onboard map.

    The designated target is the nominal site, (0, 0) in the map's stated
    coordinates; with the georeferencing error it truly lies at ``-delta`` in L.

    Args:
        terrain_cfg: The scenario's terrain.
        terrain_seed: The terrain's seed (``Scenario.terrain_seed()``).
        map_cfg: The product's settings.
        seed: The run's seed (the "map" stream).
        surface: The regenerated surface, when the caller has it already.

    Returns:
        (the map for the flight software, the truth about it for the bench).
    """
    shift, rng_noise = draw_map_shift(map_cfg, seed)

    def generate() -> OrbitalProduct:
        if surface is None:
            _free_idle_render_contexts()  # the surface's arrays need the memory
        ground = surface if surface is not None else generate_surface(terrain_cfg,
                                                                      component_rng(terrain_seed, "terrain"))
        return render_orbital_map(ground, map_cfg, shift, rng_noise, photometric=terrain_cfg.photometric_function)

    if surface is None and terrain_cfg.kind == "procedural":
        product = cached_arrays("map", map_key(terrain_cfg, terrain_seed, map_cfg, seed, shift), generate,
                                _decode_product, _encode_product)
    else:
        product = generate()
    onboard = onboard_map_from_product(product, map_cfg)
    truth = MapTruth(shift_xy_m=shift, target_xy_L_m=(-shift[0], -shift[1]))
    return onboard, truth


def map_key(terrain_cfg: TerrainConfig, terrain_seed: int, map_cfg: OrbitalMapConfig, seed: int,
            shift_xy_m: tuple[float, float]) -> str:
    """The content address (sha256 hex) of a run's map product: the terrain and map settings, the terrain
    seed, the run's seed and its drawn shift, the generators' code (the terrain, the product, this module's
    streams) and the numerical libraries' versions."""
    import cv2
    import scipy

    doc = {
        "format": MAP_CACHE_FORMAT,
        "terrain": json.loads(terrain_cfg.model_dump_json()),
        "terrain_seed": int(terrain_seed),
        "map": json.loads(map_cfg.model_dump_json()),
        "seed": int(seed),
        "shift_xy_m": [float(v).hex() for v in shift_xy_m],
        "code": [source_digest(m.__file__) for m in (terrain_module, orbital_map_module, seeding_module)]
                + [source_digest(Path(__file__))],
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "opencv": cv2.__version__,
    }
    return content_address(doc)


def _decode_product(header: dict, arrays: dict[str, np.ndarray]) -> OrbitalProduct:
    return OrbitalProduct(image=arrays["image"], image_res_m=float(header["image_res_m"]), dem_m=arrays["dem_m"],
                          dem_spacing_m=float(header["dem_spacing_m"]), size_m=float(header["size_m"]))


def _encode_product(product: OrbitalProduct) -> tuple[dict[str, np.ndarray], dict]:
    return ({"image": product.image, "dem_m": product.dem_m},
            {"image_res_m": product.image_res_m, "dem_spacing_m": product.dem_spacing_m, "size_m": product.size_m})


def scenario_onboard_map(scenario) -> tuple[OnboardMap, MapTruth]:
    """The onboard map of a (dispersed) scenario: its terrain, terrain seed, ``onboard_map`` and seed."""
    return build_onboard_map(scenario.terrain, scenario.terrain_seed(), scenario.onboard_map, scenario.seed)
