"""``python -m irft_torch.cli``: the ``irft`` command."""

import sys

from .command import main

sys.exit(main())
