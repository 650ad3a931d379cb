"""`python -m pgps_jax.experiments.paper`: the command in `pgps_jax.experiments.paper.command`."""

import sys

from pgps_jax.experiments.paper.command import main

sys.exit(main())
