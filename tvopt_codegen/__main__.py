"""``python -m tvopt_codegen``: the same as the ``tvopt-codegen`` command."""

import sys

from tvopt_codegen.cli import main

sys.exit(main())
