"""`python -m pgps_jax.evaluate`: the command in `pgps_jax.cli.evaluate`."""

import sys

from pgps_jax.cli.evaluate import main

if __name__ == "__main__":
    sys.exit(main())
