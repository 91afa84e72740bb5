"""``python -m service`` equals the ``topofusion`` console script."""

import sys

from service.cli import main

sys.exit(main())
