"""``python -m omg4``: the same as the ``omg4`` command."""

import sys

from omg4.app.cli import main

sys.exit(main())
