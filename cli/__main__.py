"""`python -m badf.cli` runs the badf command."""

import sys

from badf.cli import main

sys.exit(main())
