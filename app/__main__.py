"""``python -m twohr_app``: the ``twohr`` command line."""

import sys

from .cli import main

sys.exit(main())
