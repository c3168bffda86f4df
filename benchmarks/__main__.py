"""`python -m benchmarks`: run the benchmark suite (see `benchmarks.suite`).

    python -m benchmarks --quick --out /tmp/suite_quick   # a few minutes on 2 CPU cores
    python -m benchmarks                                  # the full sizes (GPU machine)
    python -m benchmarks --only physics,env --dry-run     # the commands it would run
"""

import sys

from benchmarks.suite import main

sys.exit(main())
