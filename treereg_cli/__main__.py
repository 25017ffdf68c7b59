"""`python -m treereg_cli ...` = `treereg ...`."""

import sys

from . import main

sys.exit(main())
