"""``python -m drake_cert.cli``: the same as the ``drake-cert`` console script."""

import sys

from drake_cert.cli import main

sys.exit(main())
