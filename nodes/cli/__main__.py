"""`python -m derl.nodes.cli`: the `derl` command, with this interpreter."""

import sys

from derl.nodes.cli.main import main

sys.exit(main())
