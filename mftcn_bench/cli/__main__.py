"""`python -m mftcn_bench.cli`."""

import sys

from mftcn_bench.cli import main

sys.exit(main())
