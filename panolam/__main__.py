"""``python -m panolam``: the ``panolam`` command (also under ``torchrun ... -m panolam train``)."""
import sys

from .cli import main

sys.exit(main())
