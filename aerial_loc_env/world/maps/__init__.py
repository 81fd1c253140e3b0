"""Map data: georeferences (``geo.py``), the ``Orthomap`` and its bundle format (``orthomap.py``), the file
loaders (``io.py``), maps opened by window (``raster.py``) and written as COGs (``cog.py``), the on-disk cache of
generated maps (``cache.py``), land-cover codes (``landcover.py``), and a map as another sensor acquired it
(``acquisition.py``)."""

from aerial_loc_env.world.maps.cog import write_cog
from aerial_loc_env.world.maps.io import load_orthomap, open_map
from aerial_loc_env.world.maps.landcover import LandCover
from aerial_loc_env.world.maps.orthomap import Orthomap
from aerial_loc_env.world.maps.raster import RasterMap

__all__ = ["LandCover", "Orthomap", "RasterMap", "load_orthomap", "open_map", "write_cog"]
