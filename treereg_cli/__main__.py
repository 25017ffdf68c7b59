"""`python -m treereg_cli ...` = `treereg ...`."""

import sys

from .main import main

sys.exit(main())
