"""``python -m client.cli``: the ``canonical`` command."""

import sys

from . import main

sys.exit(main())
