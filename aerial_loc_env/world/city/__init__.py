"""The procedural city: its layout, its painting, its content, and its epochs (the same city years later).

``default_city(config)`` is the embedded default map; ``generator.py`` draws it, ``layout.py`` plans streets,
blocks and parcels, ``paint.py`` holds the canvas and materials, ``content.py`` and ``roads.py`` paint what is
on the ground, and ``epochs.py`` changes a map into a later epoch of the same ground.
"""

from aerial_loc_env.world.city.generator import (
    GENERATOR_VERSION,
    MAX_PIXELS,
    CityConfig,
    city_cache_path,
    default_city,
    generate_city,
    height_ranges_m,
    small_city_config,
)

__all__ = ["GENERATOR_VERSION", "MAX_PIXELS", "CityConfig", "city_cache_path", "default_city", "generate_city",
           "height_ranges_m", "small_city_config"]
