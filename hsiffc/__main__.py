"""``python -m hsiffc``: the same as the ``hsiffc`` command."""

import sys

from .cli import main

sys.exit(main())
