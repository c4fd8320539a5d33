"""`python -m dynqos.cli`: the same as the `dynqos` console script."""

import sys

from dynqos.cli.main import main

sys.exit(main())
