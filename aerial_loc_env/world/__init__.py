"""The world layer: map data and georeferences (``maps/``), the procedural city and its epochs (``city/``), cast
and cloud shadows (``shadows.py``), and the world a scenario flies over, assembled in one place (``scene.py``)."""

from aerial_loc_env.world.maps import LandCover, Orthomap, load_orthomap

__all__ = ["LandCover", "Orthomap", "load_orthomap"]
