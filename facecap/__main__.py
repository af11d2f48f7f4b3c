"""``python -m facecap``: the command line."""

import sys

from facecap.cli import main

sys.exit(main())
