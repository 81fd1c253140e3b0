"""Map data: georeferences (``geo.py``), the ``Orthomap`` and its bundle format (``orthomap.py``), the file
loaders (``io.py``), the on-disk cache of generated maps (``cache.py``), land-cover codes (``landcover.py``), and
a map as another sensor acquired it (``acquisition.py``)."""

from aerial_loc_env.world.maps.io import load_orthomap
from aerial_loc_env.world.maps.landcover import LandCover
from aerial_loc_env.world.maps.orthomap import Orthomap

__all__ = ["LandCover", "Orthomap", "load_orthomap"]
