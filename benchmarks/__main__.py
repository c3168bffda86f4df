"""`python -m dmcr_jax.benchmarks`: run the benchmark suite (see `dmcr_jax.benchmarks.suite`).

    python -m dmcr_jax.benchmarks --quick --out /tmp/suite_quick   # a few minutes on 2 CPU cores
    python -m dmcr_jax.benchmarks                                  # the full sizes (GPU machine)
    python -m dmcr_jax.benchmarks --only physics,env --dry-run     # the commands it would run
"""

import sys

from dmcr_jax.benchmarks.suite import main

sys.exit(main())
