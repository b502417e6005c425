"""``python -m warptex``: the ``warptex`` command, for environments without its script."""

import sys

from warptex.cli import main

sys.exit(main())
