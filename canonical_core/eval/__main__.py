"""``python -m canonical_core.eval DATASET --views 2,4,8,16 --out DIR ...`` (see `cli`)."""

import sys

from .cli import main

sys.exit(main())
