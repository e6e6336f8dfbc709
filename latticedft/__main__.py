"""``python -m latticedft``: the command line."""

import sys

from latticedft.cli import main

sys.exit(main())
