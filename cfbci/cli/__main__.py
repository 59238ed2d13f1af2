"""``python -m cfbci.cli ...``: the ``cfbci`` command."""

import sys

from cfbci.cli import main

sys.exit(main())
