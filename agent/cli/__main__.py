"""``python -m agent.cli``: the ``pgvd`` command without the installed console script."""

import sys

from agent.cli import main

sys.exit(main())
