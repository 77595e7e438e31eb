"""``python -m usdface ...``: the same as the ``usdface`` command (for environments without the console
script on PATH)."""

import sys

from .cli import main

sys.exit(main())
