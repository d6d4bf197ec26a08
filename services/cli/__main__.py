"""``python -m services.cli ...``: the ``trackgraph`` command (how ``launch`` starts each service)."""

import sys

from services.cli import main

sys.exit(main())
