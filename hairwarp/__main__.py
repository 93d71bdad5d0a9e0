"""``python -m hairwarp``: the command-line interface."""

import sys

from hairwarp.cli import main

sys.exit(main())
