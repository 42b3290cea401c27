"""``python -m cellcal.cli``: the same as the ``cellcal`` command."""
import sys

from cellcal.cli.main import main

sys.exit(main())
