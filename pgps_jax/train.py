"""`python -m pgps_jax.train`: the command in `pgps_jax.cli.train`."""

import sys

from pgps_jax.cli.train import main

if __name__ == "__main__":
    sys.exit(main())
