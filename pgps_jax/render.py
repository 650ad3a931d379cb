"""`python -m pgps_jax.render`: the command in `pgps_jax.cli.render`."""

import sys

from pgps_jax.cli.render import main

if __name__ == "__main__":
    sys.exit(main())
