"""``python -m slamkit ...``: the ``slamkit`` command (:func:`slamkit.cli.main`)."""

import sys

from .cli import main

if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
