"""``python -m diffgcl.cli``: the command line (see :mod:`diffgcl.cli`)."""

import sys

from diffgcl.cli import main

sys.exit(main())
