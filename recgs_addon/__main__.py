"""``python -m recgs_addon``: the command-line entry point (see ``recgs_addon.cli``)."""
import sys

from .cli import main

sys.exit(main())
