"""`python -m dano.cli`."""

import sys

from dano.cli import main

sys.exit(main())
