"""aerial_loc_env: a Gymnasium benchmark for image-based absolute localization of drones without GNSS.

Importing the package registers the scenarios of ``envs/`` with Gymnasium (``AerialLoc/<Name>-v<N>``), so
``import aerial_loc_env; gym.make("AerialLoc/PaperShadows-v1")`` works; so does
``gym.make("aerial_loc_env:AerialLoc/PaperShadows-v1")`` without the explicit import.
"""

__version__ = "0.1.0"

from aerial_loc_env.env.scenarios import register_all as _register_all  # noqa: E402

_register_all()
