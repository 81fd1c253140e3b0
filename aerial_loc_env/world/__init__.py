"""The world layer: map databases, georeferences, the procedural city, shadows."""

from .io import load_orthomap
from .landcover import LandCover
from .orthomap import Orthomap

__all__ = ["LandCover", "Orthomap", "load_orthomap"]
