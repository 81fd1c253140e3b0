"""aerial_loc_env: a Gymnasium benchmark for image-based absolute localization of drones without GNSS."""

__version__ = "0.1.0"
