"""``python -m aerial_loc_env.sitl``: the same as ``aerial-loc sitl``."""

import sys

from aerial_loc_env.sitl.cli import run_as_script

sys.exit(run_as_script())
