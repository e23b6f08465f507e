"""`python -m nodes.cli`: the `derl` command, with this interpreter."""

import sys

from nodes.cli.main import main

sys.exit(main())
