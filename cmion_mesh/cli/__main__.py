"""``python -m cmion_mesh.cli``: the command line, as ``cmion-mesh``."""

import sys

from cmion_mesh.cli.main import main

sys.exit(main())
