"""``python -m ttsim_jax.cli ARGS``: the same as ``ttsim ARGS``."""

import sys

from ttsim_jax.cli.main import main

sys.exit(main())
