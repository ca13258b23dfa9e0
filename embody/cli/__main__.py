"""`python -m embody.cli`: the `embody` command."""

import sys

from embody.cli import main

sys.exit(main())
