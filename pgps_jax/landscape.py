"""`python -m pgps_jax.landscape`: the experiment in `pgps_jax.experiments.landscape`."""

import sys

from pgps_jax.experiments.landscape.command import main

if __name__ == "__main__":
    sys.exit(main())
