"""``python -m toolkit.cli`` runs ``dars``."""

import sys

from . import main

sys.exit(main())
